"""predict against eval and PyTorch against onnxruntime on the sample's test photos, and predict's speed (issue 61).

    python -m benchmarks.predict --cache outputs/cache [--images 0] [--threads 1 2] [--json predict.json]

Finds the detector whose evals are in the cache (the newest eval entries that read one train_maskrcnn entry, one per
test set), writes its model folder (as `python dag.py run.action=predict predict.export=DIR` does) into a temporary
folder, and measures:
- parity with eval: `python -m stages.app.predict` (conf 0, eval's thread count) on each test set's photos against that
  eval's predictions.json: every record's image_id, category_id, score, bbox and RLE equal;
- ONNX against PyTorch on every photo: the same count and labels, boxes within 1 px, mask IoU at least 0.99 (at
  conf 0.05, every detection the detector gives, and at predict's default conf);
- speed, end to end (decoding, inference, post-processing, predictions.json; no overlays) over all the photos, per
  backend and thread count, at predict's default conf and at conf 0 (eval's workload), with the seconds per phase;
  where eval's time per photo goes (its predict: the network, the paste, the refinement, the class separation, the
  threshold and RLE); and a 640x480 video of the test photos, with and without its overlay video.
Prints Markdown tables (benchmarks/results/predict.md keeps them).
"""
from __future__ import annotations

import stages  # noqa: F401  (first: OMP_WAIT_POLICY before torch loads)

import argparse
import json
import logging
import os
import tempfile
import time
from pathlib import Path

import torch
from PIL import Image

from stages.engine.cache_entry import input_path, read_manifest
from stages.eval.run import image_grid
from stages.eval.spec import EvalConfig
from stages.lib.coco import mask_to_rle
from stages.lib.detection.inference import head_outputs, paste
from stages.lib.detection.model_folder import open_model, write_model_folder
from stages.lib.detection.onnx_export import compare_detections
from stages.lib.detection.postprocess import PostProcessing, postprocess
from stages.lib.detection.predict_config import PredictConfig
from stages.lib.detection.predict_outputs import PredictionWriter
from stages.lib.detection.predictor import predict_source
from stages.lib.detection.sources import Source, read_photo
from stages.lib.masks.overlap import separate_classes
from stages.lib.masks.refine import refine_masks, refine_radius
from stages.lib.sample_scene.videos import write_mp4
from stages.records.coco_dataset import CocoDataset

log = logging.getLogger("benchmarks.predict")
COMPARED = ("image_id", "category_id", "score", "bbox", "segmentation")  # what parity with eval compares


def cached_evals(cache: Path) -> list[Path]:
    """The newest eval entries of the cache that read the same train_maskrcnn entry, one per test set."""
    entries = sorted((p for p in (cache / "eval").glob("*") if (p / "manifest.json").is_file()),
                     key=lambda p: (p / "manifest.json").stat().st_mtime, reverse=True)
    if not entries:
        raise SystemExit(f"no eval entries in {cache / 'eval'}: run `python dag.py` first")
    model = read_manifest(entries[0])["inputs"]["model"]
    chosen: dict[str, Path] = {}
    for entry in entries:
        manifest = read_manifest(entry)
        if manifest["inputs"]["model"] == model:
            chosen.setdefault(manifest["item"], entry)
    return [chosen[item] for item in sorted(chosen)]


def photos_of(testset: Path, limit: int) -> list[tuple[Path, str, int]]:
    """(path, file name, image id) of a COCO test set's photos in id order, the first `limit` (0: all)."""
    dataset = CocoDataset.read(testset)
    images = sorted(dataset.images, key=lambda image: image["id"])[: limit or None]
    return [(CocoDataset.image_file(testset, image), image["file_name"], image["id"]) for image in images]


def run_predict(model_path: Path, photos: list[tuple[Path, str]], out: Path, threads: int, conf: float,
                overlays: bool = False, video: Path | None = None) -> tuple[dict, dict]:
    """predict (stages.lib.detection.predictor) with `threads` threads on the photos (or the video) into `out`: its
    summary and predictions.json."""
    torch.set_num_threads(threads)
    model = open_model(model_path, "cpu", threads)
    source = Source(str(video), "video", video=video, fps=10.0, frame_count=len(photos)) if video else \
        Source("benchmark", "photos", photos)
    options = PredictConfig(conf=conf, overlays=overlays, threads=threads)
    writer = PredictionWriter(out, source, model.class_names, options, {"model": str(model_path)})
    summary = predict_source(model, source, writer, options)
    return summary, json.loads(Path(summary["predictions"]).read_text())


def record_differences(mine: list[dict], theirs: list[dict]) -> dict:
    """How two lists of COCO records (in the same order) differ: records with every COMPARED field equal, with the
    same RLE, with the same mask_score, and the largest score and box differences."""
    pairs = list(zip(mine, theirs))
    return {"equal records": sum(all(a[k] == b[k] for k in COMPARED) for a, b in pairs),
            "same RLE": sum(a["segmentation"] == b["segmentation"] for a, b in pairs),
            "mask_score equal": sum(a["mask_score"] == b["mask_score"] for a, b in pairs),
            "max score difference": max((abs(a["score"] - b["score"]) for a, b in pairs), default=0.0),
            "max box difference px": max((max(abs(x - y) for x, y in zip(a["bbox"], b["bbox"])) for a, b in pairs),
                                         default=0.0)}


def eval_parity(folder: Path, evals: list[Path], limit: int, work: Path) -> list[dict]:
    """Per eval entry: predict with the model folder (conf 0) against its predictions.json, at eval's thread count
    and on one thread."""
    rows = []
    for entry in evals:
        manifest = read_manifest(entry)
        photos = photos_of(input_path(entry, "testset"), limit)
        kept = {i for _, _, i in photos}
        theirs = [r for r in json.loads((entry / "predictions.json").read_text()) if r["image_id"] in kept]
        eval_threads = EvalConfig(**manifest["params"]).threads or os.cpu_count() or 1  # as eval sets them
        for threads in dict.fromkeys((eval_threads, 1)):
            named = [(p, name) for p, name, _ in photos]
            _, found = run_predict(folder, named, work / f"parity_{entry.name}_{threads}", threads, 0.0)
            ids = {image["id"]: {name: i for _, name, i in photos}[image["file_name"]] for image in found["images"]}
            mine = [{**record, "image_id": ids[record["image_id"]]} for record in found["annotations"]]
            rows.append({"test set": manifest["item"], "photos": len(photos), "eval threads": eval_threads,
                         "predict threads": threads, "eval": len(theirs), "predict": len(mine),
                         **record_differences(mine, theirs)})
    return rows


def onnx_parity(folder: Path, photos: list[Path], threads: int) -> list[dict]:
    """ONNX against PyTorch on each photo at conf 0.05 and 0.5: photos with the same count and labels, largest box
    difference, smallest mask IoU."""
    torch.set_num_threads(threads)
    reference, other = open_model(folder), open_model(folder / "model.onnx", threads=threads)
    rows = {conf: {"conf": conf, "photos": 0, "same count and labels": 0, "max box difference px": 0.0,
                   "min mask IoU": 1.0, "detections": 0} for conf in (0.05, 0.5)}
    for path in photos:
        image = read_photo(path)[0]
        outputs = reference.detector.outputs(image), other.detector.outputs(image)
        for conf, row in rows.items():
            found = [postprocess(o, reference.post, reference.detector_size, conf) for o in outputs]
            check = compare_detections(*found)
            row["photos"] += 1
            row["detections"] += check["reference_detections"]
            if check["same_labels"]:
                row["same count and labels"] += 1
                row["max box difference px"] = max(row["max box difference px"], check["max_box_difference_px"])
                row["min mask IoU"] = min(row["min mask IoU"], check["min_mask_iou"])
    return list(rows.values())


def eval_breakdown(folder: Path, photos: list[Path], threads: int) -> dict:
    """Seconds per photo of eval's predict (every detection) by step: network (up to the mask head), paste,
    refinement, class separation, threshold and maskness, RLE; and the detections per photo."""
    torch.set_num_threads(threads)
    model = open_model(folder)
    post = model.post
    steps = dict.fromkeys(("network", "paste", "refine", "separate", "threshold", "rle"), 0.0)
    detections = 0
    for path in photos:
        image = read_photo(path)[0]
        t0 = time.perf_counter()
        outputs = head_outputs(model.detector.model, image, "cpu")
        t1 = time.perf_counter()
        detected = paste(outputs)
        t2 = time.perf_counter()
        radius = refine_radius(post.mask_refine_radius, image.shape[:2], model.detector_size)
        probability = refine_masks(detected["image"], detected["probability"], radius, post.mask_refine_eps)
        t3 = time.perf_counter()
        if post.mask_owner_score is not None:
            probability = separate_classes(probability, detected["scores"], detected["labels"], post.mask_threshold,
                                           post.mask_owner_score)
        t4 = time.perf_counter()
        masks = (probability > post.mask_threshold)
        ((probability * masks).sum(dim=(1, 2)) / masks.sum(dim=(1, 2)).clamp_min(1)).numpy()
        masks = masks.numpy()
        t5 = time.perf_counter()
        [mask_to_rle(mask) for mask in masks]
        t6 = time.perf_counter()
        detections += len(masks)
        for step, seconds in zip(steps, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4, t6 - t5)):
            steps[step] += seconds
    return {"threads": threads, "detections per photo": detections / len(photos),
            **{step: seconds / len(photos) for step, seconds in steps.items()}}


def speed(folder: Path, photos: list[Path], threads_list: list[int], work: Path) -> list[dict]:
    """predict's images/s over the photos per backend and thread count (default conf; PyTorch also at conf 0)."""
    rows = []
    named = [(p, p.name) for p in photos]
    for threads in threads_list:
        runs = (("pytorch", folder, PredictConfig.conf), ("onnxruntime", folder / "model.onnx", PredictConfig.conf),
                ("pytorch", folder, 0.0))
        for backend, model_path, conf in runs:
            summary, _ = run_predict(model_path, named, work / f"speed_{backend}_{threads}_{conf}", threads, conf)
            rows.append({"backend": backend, "threads": threads, "conf": conf, "images": summary["images"],
                         "images/s": summary["images_per_second"], "detections": summary["detections"],
                         **{f"{phase} ms": 1000 * seconds / summary["images"]
                            for phase, seconds in summary["seconds_per_phase"].items()}})
            log.info("%s", rows[-1])
    return rows


def video_speed(folder: Path, photos: list[Path], threads: int, work: Path) -> list[dict]:
    """predict on a 640x480 mp4 of the photos (10 fps), with and without the overlay video."""
    video = work / "test_photos.mp4"
    write_mp4(video, [read_photo(p)[0] for p in photos], 10.0)
    rows = []
    for overlays in (False, True):
        summary, _ = run_predict(folder, [(p, p.name) for p in photos], work / f"video_{overlays}", threads,
                                 PredictConfig.conf, overlays=overlays, video=video)
        rows.append({"overlays": overlays, "threads": threads, "frames": summary["images"],
                     "frames/s": summary["images_per_second"]})
    return rows


def write_figure(folder: Path, photos: list[Path], path: Path, work: Path) -> None:
    """predict's overlays of the photos (default settings) tiled 4 across into a JPEG at `path` (the README's)."""
    summary, found = run_predict(folder, [(p, p.name) for p in photos], work / "figure", 2, PredictConfig.conf,
                                 overlays=True)
    tiles = [read_photo(work / "figure" / "overlays" / image["file_name"])[0] for image in found["images"]]
    Image.fromarray(image_grid(tiles)).save(path, quality=90)
    log.info("figure %s: %d photos, %d detections", path, summary["images"], summary["detections"])


def table(rows: list[dict]) -> str:
    """Rows as a Markdown table (floats to 3 significant digits)."""
    heads = list(rows[0])
    cell = lambda v: f"{v:.3g}" if isinstance(v, float) else str(v)  # noqa: E731
    return "\n".join(["| " + " | ".join(heads) + " |", "|" + "---|" * len(heads)] +
                     ["| " + " | ".join(cell(row[h]) for h in heads) + " |" for row in rows])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cache", type=Path, default=Path("outputs/cache"))
    parser.add_argument("--images", type=int, default=0, help="photos per test set (0: all)")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--json", type=Path, help="write every table here")
    parser.add_argument("--figure", type=Path, help="write predict's overlays of 8 test photos here (a JPEG)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    evals = cached_evals(args.cache)
    train = input_path(evals[0], "model")
    photos = [p for entry in evals for p, _, _ in photos_of(input_path(entry, "testset"), args.images)]
    log.info("detector %s, evals %s, %d photos", train, [e.name for e in evals], len(photos))
    with tempfile.TemporaryDirectory() as tmp:
        work, folder = Path(tmp), Path(tmp) / "detector"
        trained = json.loads((train / "train.json").read_text())
        card = {"training": {"images": trained["images"], "variant": read_manifest(train)["item"], "generator": "?",
                             "seed": read_manifest(train)["seed"], "backbone": trained["backbone"],
                             "iterations": trained["iterations"], "epochs": read_manifest(train)["params"]["epochs"],
                             "seconds": trained["seconds"], "device": trained["device"]},
                "evaluation": {}, "source": {"command": "benchmarks/predict.py", "train_maskrcnn": str(train),
                                             "created": time.strftime("%Y-%m-%d %H:%M")}}
        post = PostProcessing.of(EvalConfig(**read_manifest(evals[0])["params"]))
        started = time.perf_counter()
        write_model_folder(folder, train / "model.pt", post, card, read_photo(photos[0])[0])
        log.info("model folder written in %.1f s", time.perf_counter() - started)
        results = {"eval parity": eval_parity(folder, evals, args.images, work),
                   "onnx parity": onnx_parity(folder, photos, max(args.threads)),
                   "speed": speed(folder, photos, args.threads, work),
                   "eval breakdown": [eval_breakdown(folder, photos, t) for t in args.threads],
                   "video": video_speed(folder, photos[:50], max(args.threads), work)}
        if args.figure:
            write_figure(folder, photos[:8], args.figure, work)
    for name, rows in results.items():
        print(f"\n## {name}\n\n{table(rows)}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
