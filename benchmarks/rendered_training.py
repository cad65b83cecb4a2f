"""Training images from the sample's own renderer (the objects' meshes, not their splats): how well the detector
can do with perfect object data, per class.

    python -m benchmarks.rendered_training render SAMPLE_FOLDER DATASET [--images 1000] [--workers 2]
    python -m benchmarks.detector runs --dataset DATASET --testset SAMPLE_FOLDER/test_a --testset SAMPLE_FOLDER/test_b \
        --config default='{}' --seed S --threads T --out RUNS.json
    python -m benchmarks.rendered_training gaps RUNS.json [RUNS.json ...] [--label NAME=RUNS.json ...] [--cls plant]
    python -m benchmarks.rendered_training overlays TEST_SET EVAL_FOLDER [EVAL_FOLDER ...] --image OUT.jpg [--cls plant]
    python -m benchmarks.rendered_training neighbours TEST_SET EVAL_FOLDER [EVAL_FOLDER ...]

`render` draws a COCO training set (images/ + annotations.json, the layout compose writes) with the code that
draws the sample's test photos (stages/lib/sample_scene/testsets.py): 1-3 of the sample's objects standing on tables
and floors, seen by camera A (the capture camera), sometimes behind an occluder, in the sample's generic
background rooms (the rooms of the composed images' backgrounds, not the test rooms), from a random stream of
its own. The masks are the renderer's own labels: the test sets' masks of other scenes. SAMPLE_FOLDER is a sample
cache entry (its sample.json gives the seed, the objects and the image size).

A detector trained on these images with the defaults (`benchmarks.detector runs`) meets the test sets with no
gap between the object it learnt and the one it is tested on: what remains of a class's mask AP gap is the
detector's own. `gaps` prints per test set and configuration the mask AP of --cls against the mean of the
other classes (mean ± std over the seeds in the runs JSONs) and writes the table as Markdown (--md). `overlays`
draws the first --count true masks of --cls in a test set beside each eval folder's best-matching prediction of
that class: green where both are, red where only the truth is, blue where only the prediction is. `neighbours`
splits each class's true masks by whether another object's box touches theirs and prints, per eval folder, the
median IoU of the best-matching prediction and the mean share of its pixels that lie on the other objects' true
masks (a mask that takes in a neighbour).
"""
from __future__ import annotations

import argparse
import json
import logging
import statistics
import time
from functools import partial
from pathlib import Path

import cv2
import numpy as np

from benchmarks.lib.mask_matching import best_match, predicted_masks
from stages.lib.coco import CocoBuilder, load_coco
from stages.lib.dataset_formats.polygons import mask_iou
from stages.lib.processes import spawn_pool
from stages.lib.sample_scene.raytrace import RAY_THREADS
from stages.lib.sample_scene.testsets import render_test_image
from stages.sample.run import _models, _room  # the sample's generic rooms and object meshes, as it builds them

STREAM = 52  # the random stream of these images (stages/sample/run.py draws from streams 21-43)
ATTEMPTS = 5  # scenes tried per image when the renderer finds no place for the objects


def _one_ray_thread() -> None:
    """Worker initialiser: one ray-casting thread per process (the pool provides the parallelism)."""
    RAY_THREADS["count"] = 1


def render_image(sample: dict, out: Path, index: int) -> dict:
    """Render image `index` (1-3 distinct classes in generic room index % rooms) and write out/images/NNNN.png.

    Returns {"label": uint8 [H, W] (instance ids), "instances": [{"class_index", "visible_fraction",
    "support"}], "room": int, "seconds": float}.
    """
    started = time.perf_counter()
    objects = tuple((o["name"], float(o["height_m"])) for o in sample["objects"])
    rooms = max(1, -(-sample["num_backgrounds"] // sample["photos_per_room"]))
    room = index % rooms
    for attempt in range(ATTEMPTS):
        rng = np.random.default_rng([sample["seed"], STREAM, index, attempt])
        count = int(rng.integers(1, min(3, len(objects)) + 1))
        classes = sorted(int(c) for c in rng.choice(len(objects), size=count, replace=False))
        try:
            shot = render_test_image(_room(sample["seed"], "generic", room), _models(sample["seed"], objects),
                                     classes, "a", rng, sample["width"], sample["height"], sample["supersample"])
            break
        except RuntimeError:  # no place for these objects in this room from this stream: another draw
            continue
    else:
        raise RuntimeError(f"image {index}: no scene in generic room {room} after {ATTEMPTS} draws")
    cv2.imwrite(str(out / "images" / f"{index:04d}.png"), np.ascontiguousarray(shot["image"][..., ::-1]))
    return {"label": shot["label"].astype(np.uint8), "instances": shot["instances"], "room": room,
            "seconds": time.perf_counter() - started}


def render_dataset(sample_folder: Path, out: Path, images: int, workers: int) -> dict:
    """Write `images` rendered training images and their annotations.json into `out`; returns counts."""
    sample = json.loads((sample_folder / "sample.json").read_text())["config"]
    (out / "images").mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    job = partial(render_image, sample, out)
    if workers > 1:
        with spawn_pool(workers, _one_ray_thread) as pool:
            results = list(pool.map(job, range(images), chunksize=4))
    else:
        results = [job(index) for index in range(images)]
    names = [o["name"] for o in sample["objects"]]
    builder = CocoBuilder(names, info={"description": "the sample's renderer in its generic rooms (camera A)",
                                       "sample": str(sample_folder), "seed": sample["seed"]})
    for index, result in enumerate(results):
        image_id = builder.add_image(f"{index:04d}.png", sample["width"], sample["height"],
                                     room=f"generic{result['room']}")
        for instance_id, inst in enumerate(result["instances"], start=1):
            builder.add_instance(image_id, inst["class_index"] + 1, result["label"] == instance_id,
                                 visible_fraction=round(inst["visible_fraction"], 4), support=inst["support"])
    builder.dataset.write(out)
    per_class = {name: sum(a["category_id"] == i + 1 for a in builder.dataset.annotations) for i, name in enumerate(names)}
    return {"images": images, "instances": len(builder.dataset.annotations), "per_class": per_class,
            "render_s": round(sum(r["seconds"] for r in results), 1), "wall_s": round(time.perf_counter() - started, 1)}


def class_gaps(rows: list[dict], testset: str, cls: str) -> dict:
    """Mask AP of `cls` and the mean of the other classes over the runs `rows` (one per seed) on `testset`.

    Returns {"seeds", "cls": [AP per seed], "others": [mean AP per seed], "box_AP", "mask_AP"} (lists per seed).
    """
    per_seed = [row[testset]["mask_per_class"] for row in rows]
    return {"seeds": [row["seed"] for row in rows], "cls": [ap[cls] for ap in per_seed],
            "others": [statistics.fmean(v for k, v in ap.items() if k != cls) for ap in per_seed],
            "box_AP": [row[testset]["box_AP"] for row in rows], "mask_AP": [row[testset]["mask_AP"] for row in rows]}


def spread(values: list[float]) -> str:
    """mean ± sample std (just the value for one)."""
    return f"{statistics.fmean(values):.1f}" + (f" ± {statistics.stdev(values):.1f}" if len(values) > 1 else "")


def gaps_table(labelled: dict[str, list[dict]], cls: str) -> str:
    """Markdown: per runs label, configuration and test set, mask AP of `cls`, of the others, the gap, box and mask mAP."""
    lines = [f"| training data | configuration | test | seeds | {cls} mask AP | mean of the others | gap | "
             "mask mAP | box mAP |", "|---|---|---|---|---|---|---|---|---|"]
    for label, rows in labelled.items():
        for name in dict.fromkeys(row["name"] for row in rows):
            runs = [row for row in rows if row["name"] == name]
            testsets = [key for key, value in runs[0].items() if isinstance(value, dict) and "mask_per_class" in value]
            for testset in testsets:
                g = class_gaps(runs, testset, cls)
                gap = statistics.fmean(g["others"]) - statistics.fmean(g["cls"])
                lines.append(f"| {label} | {name} | {testset} | {len(runs)} | {spread(g['cls'])} | "
                             f"{statistics.fmean(g['others']):.1f} | **{gap:.1f}** | {spread(g['mask_AP'])} | "
                             f"{spread(g['box_AP'])} |")
    return "\n".join(lines)


def overlay_row(image: np.ndarray, truth: np.ndarray, predictions: list[np.ndarray | None], box: list[float],
                height: int = 200) -> np.ndarray:
    """The crop around `box` (x, y, w, h) of an RGB image [H, W, 3], then per prediction [H, W] bool (or None) the
    crop coloured by truth [H, W] against it, scaled to `height` rows with the IoU written on each."""
    x, y, w, h = (int(round(v)) for v in box)
    pad = max(4, int(0.08 * max(w, h)))
    rows, cols = slice(max(0, y - pad), y + h + pad), slice(max(0, x - pad), x + w + pad)
    crop, true = image[rows, cols], truth[rows, cols]
    panels = [crop]
    for mask in predictions:
        shown, iou = crop.copy(), 0.0
        predicted = np.zeros_like(true) if mask is None else mask[rows, cols]
        shown[true & predicted], shown[true & ~predicted], shown[predicted & ~true] = (0, 200, 0), (230, 0, 0), (0, 90, 255)
        if mask is not None:
            iou = mask_iou(mask, truth)
        cv2.putText(shown, f"{iou:.2f}", (2, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1)
        panels.append(shown)
    row = np.hstack(panels)
    return cv2.resize(row, (round(row.shape[1] * height / row.shape[0]), height), interpolation=cv2.INTER_NEAREST)


def overlays(test_set: Path, eval_folders: list[Path], cls: str, count: int) -> np.ndarray:
    """RGB [H, W, 3]: one overlay_row per true mask of class `cls` (the first `count`), one column per eval folder."""
    coco = load_coco(test_set)
    category = next(c["id"] for c in coco.loadCats(coco.getCatIds()) if c["name"] == cls)
    predictions = [predicted_masks(folder) for folder in eval_folders]
    rows = []
    for ann in [a for a in coco.dataset["annotations"] if a["category_id"] == category][:count]:
        image = cv2.imread(str(test_set / "images" / coco.imgs[ann["image_id"]]["file_name"]))[..., ::-1]
        truth = coco.annToMask(ann) > 0
        best = [best_match(truth, found.get((ann["image_id"], category), []))[1] for found in predictions]
        rows.append(overlay_row(image, truth, best, ann["bbox"]))
    width = max(row.shape[1] for row in rows)
    return np.vstack([np.pad(row, ((0, 4), (0, width - row.shape[1]), (0, 0))) for row in rows])


def neighbour_leaks(test_set: Path, eval_folder: Path) -> dict[str, dict[str, dict[str, float]]]:
    """{class: {"alone" | "touching": {"instances", "iou" (median), "leak" (mean)}}}: every true mask of the test set
    against the prediction of its class that overlaps it most; leak = the share of that prediction's pixels on
    the other instances' true masks of the image; "touching" when another instance's box meets its box."""
    coco = load_coco(test_set)
    names = {c["id"]: c["name"] for c in coco.loadCats(coco.getCatIds())}
    predictions = predicted_masks(eval_folder)
    found: dict[tuple[str, str], list[tuple[float, float]]] = {}
    for image_id in coco.getImgIds():
        anns = coco.loadAnns(coco.getAnnIds(imgIds=image_id))
        truths = [coco.annToMask(ann) > 0 for ann in anns]
        for k, ann in enumerate(anns):
            others = np.any([t for j, t in enumerate(truths) if j != k], axis=0) if len(anns) > 1 else None
            x, y, w, h = ann["bbox"]
            touching = any(b["bbox"][0] <= x + w and x <= b["bbox"][0] + b["bbox"][2] and b["bbox"][1] <= y + h
                           and y <= b["bbox"][1] + b["bbox"][3] for j, b in enumerate(anns) if j != k)
            iou, mask = best_match(truths[k], predictions.get((image_id, ann["category_id"]), []))
            leak = 0.0 if mask is None or others is None else float((mask & others).sum() / max(mask.sum(), 1))
            found.setdefault((names[ann["category_id"]], "touching" if touching else "alone"), []).append((iou, leak))
    table: dict[str, dict[str, dict[str, float]]] = {}
    for (name, kind), values in sorted(found.items()):
        table.setdefault(name, {})[kind] = {"instances": len(values), "iou": float(np.median([v[0] for v in values])),
                                            "leak": float(np.mean([v[1] for v in values]))}
    return table


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="mode", required=True)
    render = sub.add_parser("render", help="draw the training set")
    render.add_argument("sample", type=Path, help="a sample cache entry (holds sample.json)")
    render.add_argument("out", type=Path, help="the dataset folder to write (images/ + annotations.json)")
    render.add_argument("--images", type=int, default=1000)
    render.add_argument("--workers", type=int, default=2)
    gaps = sub.add_parser("gaps", help="a class's mask AP gap from the runs of benchmarks.detector")
    gaps.add_argument("runs", type=Path, nargs="*", help="runs JSONs, labelled by their training dataset's name")
    gaps.add_argument("--label", action="append", default=[], help="NAME=RUNS.json: a runs JSON under a name")
    gaps.add_argument("--cls", default="plant")
    gaps.add_argument("--md", type=Path, help="write the table here too")
    drawn = sub.add_parser("overlays", help="true masks of a class against each eval folder's predictions")
    drawn.add_argument("test_set", type=Path)
    drawn.add_argument("eval_folders", type=Path, nargs="+", help="eval outputs (predictions.json) on that test set")
    drawn.add_argument("--image", type=Path, required=True, help="the picture to write (.png or .jpg)")
    drawn.add_argument("--cls", default="plant")
    drawn.add_argument("--count", type=int, default=6)
    leaks = sub.add_parser("neighbours", help="masks of objects with and without a touching neighbour")
    leaks.add_argument("test_set", type=Path)
    leaks.add_argument("eval_folders", type=Path, nargs="+", help="eval outputs (predictions.json) on that test set")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.mode == "render":
        if (args.out / "annotations.json").exists():
            parser.error(f"{args.out} already holds a dataset (annotations.json): pass another folder")
        if not (args.sample / "sample.json").is_file():
            parser.error(f"{args.sample}: no sample.json (pass a sample cache entry, outputs/cache/sample/<key>)")
        print(json.dumps(render_dataset(args.sample, args.out, args.images, args.workers), indent=1))
        return
    if args.mode == "overlays":
        picture = overlays(args.test_set, args.eval_folders, args.cls, args.count)[..., ::-1]
        quality = [cv2.IMWRITE_JPEG_QUALITY, 85] if args.image.suffix.lower() in (".jpg", ".jpeg") else []
        if not cv2.imwrite(str(args.image), picture, quality):
            parser.error(f"could not write {args.image} (a .png or .jpg path in an existing folder)")
        return
    if args.mode == "neighbours":
        for folder in args.eval_folders:
            print(f"{folder}\n| class | neighbour | instances | median IoU | mask on other objects |\n|---|---|---|---|---|")
            for name, kinds in neighbour_leaks(args.test_set, folder).items():
                for kind, row in kinds.items():
                    print(f"| {name} | {kind} | {row['instances']} | {row['iou']:.2f} | {row['leak']:.3f} |")
        return
    labelled: dict[str, list[dict]] = {}
    for label, path in [(Path(json.loads(p.read_text())["dataset"]).name, p) for p in args.runs] + \
            [tuple(item.split("=", 1)) for item in args.label]:
        labelled.setdefault(label, []).extend(json.loads(Path(path).read_text())["runs"])
    table = gaps_table(labelled, args.cls)
    print(table)
    if args.md:
        args.md.write_text(table + "\n")


if __name__ == "__main__":
    main()
