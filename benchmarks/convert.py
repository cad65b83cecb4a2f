"""Benchmark of the dataset conversions (issue 33): YOLO polygons against the COCO masks, YOLO boxes against the COCO boxes,
BOP poses reprojected into the amodal masks, Ultralytics' own checker, and export time against compose's.

Usage: python -m benchmarks.convert [DATASET] [--images 200] [--out outputs/export_bench] [--model NAME=OBJECT_PLY ...]

DATASET is a compose output folder, e.g. the default run's outputs/cache/compose/<key>. In the engine's cache
(manifest.json beside it, inputs still cached) compose is rerun into --out with the same settings, inputs and
seed, which times it in this run and compares its images and masks with the cached ones byte for byte;
the objects' object.ply are found through the cache. Without DATASET, ../shared/real/splats/plant.splat is
composed onto the real TUM photo (benchmarks.compose) with --images images. Ultralytics' checks run when it
imports (`/tmp/ulvenv/bin/python -m benchmarks.convert ...` with a venv holding it; it is AGPL-3.0, never a
dependency). Prints the figures as JSON and writes benchmarks/results/convert.md.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from stages.app.convert import export, model_argument
from stages.compose import run as compose
from stages.engine.cache_entry import MANIFEST, input_path, read_manifest
from stages.engine.context import Context
from stages.lib.coco import rle_to_mask
from stages.lib.composition.placement import MetricFrame
from stages.lib.dataset_formats.polygons import mask_iou, polygon_mask
from stages.lib.gaussians.ply import read_ply
from stages.records.coco_dataset import CocoDataset

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "export.md"
INSIDE_TARGET, IOU_TARGET = 0.98, 0.95


def read_yolo_labels(path: Path) -> list[tuple[int, np.ndarray]]:
    """(class id, values [N]) of each line of a YOLO label file."""
    rows = [line.split() for line in path.read_text().splitlines() if line.strip()]
    return [(int(row[0]), np.asarray(row[1:], dtype=np.float64)) for row in rows]


def yolo_polygon_ious(export_dir: Path, split: str, dataset_folder: Path) -> list[tuple[float, float | None]]:
    """Per instance (file order): the IoU of the YOLO polygon, filled as Ultralytics fills it, against the COCO
    mask, and for one below IOU_TARGET the ceiling any single polygon could reach (single_polygon_ceiling)."""
    dataset, ious = CocoDataset.read(dataset_folder), []
    by_image = dataset.annotations_by_image()
    for image in dataset.images:
        size = np.array([image["width"], image["height"]], dtype=np.float64)
        labels = read_yolo_labels((export_dir / "labels" / split / image["file_name"]).with_suffix(".txt"))
        anns = [a for a in by_image[image["id"]] if not a.get("iscrowd", 0)]
        assert len(labels) == len(anns), image["file_name"]
        for (_, values), ann in zip(labels, anns):
            mask = rle_to_mask(ann["segmentation"])
            iou = mask_iou(mask, polygon_mask(values.reshape(-1, 2) * size, image["width"], image["height"]))
            ious.append((iou, single_polygon_ceiling(mask) if iou < IOU_TARGET else None))
    return ious


def single_polygon_ceiling(mask: np.ndarray, max_components: int = 12) -> float:
    """An upper bound of the IoU any one polygon, filled as Ultralytics fills it, can reach against mask [H, W] bool.

    A filled polygon is 8-connected (fillPoly also fills every pixel its edges cross), so joining two of the
    mask's 8-connected components fills at least their Chebyshev gap minus one pixels outside the mask, and a
    component left out loses its pixels. The bound is the best, over the subsets of components kept (all of them
    beyond `max_components`), of kept pixels / (mask pixels + the gap pixels of the kept components' minimum
    spanning tree)."""
    import itertools

    import cv2
    from scipy.sparse.csgraph import minimum_spanning_tree
    from scipy.spatial import cKDTree

    count, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    pixels = [np.argwhere(labels == k) for k in range(1, count)]  # [P_k, 2] per component
    if len(pixels) <= 1:
        return 1.0
    gaps = np.zeros((len(pixels), len(pixels)))  # [C, C] pixels outside the mask a joining path must cross
    for i, j in itertools.combinations(range(len(pixels)), 2):
        chebyshev = cKDTree(pixels[i]).query(pixels[j], p=np.inf)[0].min()
        gaps[i, j] = gaps[j, i] = max(chebyshev - 1.0, 1e-9)  # 1e-9: touching at a corner costs nothing
    sizes, total = np.array([len(p) for p in pixels]), float(mask.sum())
    subsets = ([list(c) for r in range(1, len(pixels) + 1) for c in itertools.combinations(range(len(pixels)), r)]
               if len(pixels) <= max_components else [list(range(len(pixels)))])
    best = 0.0
    for kept in subsets:
        bridge = float(np.floor(minimum_spanning_tree(gaps[np.ix_(kept, kept)]).sum()))
        best = max(best, float(sizes[kept].sum()) / (total + bridge))
    return best


def yolo_box_errors(export_dir: Path, split: str, dataset_folder: Path, task: str) -> np.ndarray:
    """Per instance: the largest difference in pixels between the COCO box's edges and the YOLO box's (task
    detect: the label's box; segment: the polygon's extent, the box Ultralytics derives from it)."""
    dataset, errors = CocoDataset.read(dataset_folder), []
    by_image = dataset.annotations_by_image()
    for image in dataset.images:
        size = np.array([image["width"], image["height"]], dtype=np.float64)
        labels = read_yolo_labels((export_dir / "labels" / split / image["file_name"]).with_suffix(".txt"))
        for (_, values), ann in zip(labels, [a for a in by_image[image["id"]] if not a.get("iscrowd", 0)]):
            if task == "detect":
                centre, extent = values[:2] * size, values[2:] * size
                edges = np.concatenate([centre - extent / 2, centre + extent / 2])
            else:
                points = values.reshape(-1, 2) * size
                edges = np.concatenate([points.min(axis=0), points.max(axis=0)])
            x, y, w, h = ann["bbox"]
            errors.append(float(np.abs(edges - np.array([x, y, x + w, y + h])).max()))
    return np.asarray(errors)


def inside_fraction(points: np.ndarray, rotation: np.ndarray, translation: np.ndarray, K: np.ndarray,
                    mask: np.ndarray, slack_px: float = 0.0) -> float | None:
    """Of the model points [N, 3] whose projection with the pose (R [3, 3], t [3], same units as the points)
    and K [3, 3] lands in the image, the share inside mask [H, W] bool (pixel (u, v) is mask[floor v, floor u],
    the top-left pixel's centre at (0.5, 0.5)), or with `slack_px` > 0 (at most 1) within that many pixels of a
    mask pixel (Chebyshev); None when none lands in the image."""
    camera = points @ rotation.T + translation  # [N, 3]
    uv = camera[:, :2] / camera[:, 2:] * np.diag(K)[:2] + K[:2, 2]  # [N, 2]
    height, width = mask.shape
    inside_image = (camera[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < width) & (uv[:, 1] < height)
    if not inside_image.any():
        return None
    uv, inside = uv[inside_image], np.zeros(int(inside_image.sum()), bool)
    for du, dv in ((0, 0), (-1, -1), (-1, 1), (1, -1), (1, 1)) if slack_px else ((0, 0),):
        columns = np.clip(np.floor(uv[:, 0] + du * slack_px).astype(int), 0, width - 1)
        rows = np.clip(np.floor(uv[:, 1] + dv * slack_px).astype(int), 0, height - 1)
        inside |= mask[rows, columns]
    return float(inside.mean())


def bop_reprojection(bop_dir: Path, slack_px: float = 0.0) -> list[float]:
    """Per instance of a BOP export with models: the share of its model's points (mm) projected with
    cam_R_m2c, cam_t_m2c and cam_K that fall inside its mask/ PNG (the amodal mask), or within `slack_px` of it."""
    import cv2

    models = {int(path.stem.split("_")[1]): np.loadtxt(path, skiprows=7)
              for path in sorted((bop_dir / "models").glob("obj_*.ply"))}
    shares = []
    for scene in sorted(p for p in (bop_dir / "train").iterdir() if p.is_dir()):
        cameras = json.loads((scene / "scene_camera.json").read_text())
        for im_id, gts in json.loads((scene / "scene_gt.json").read_text()).items():
            K = np.asarray(cameras[im_id]["cam_K"]).reshape(3, 3)
            for gt_id, gt in enumerate(gts):
                mask = cv2.imread(str(scene / "mask" / f"{int(im_id):06d}_{gt_id:06d}.png"), cv2.IMREAD_GRAYSCALE) > 0
                share = inside_fraction(models[gt["obj_id"]], np.asarray(gt["cam_R_m2c"]).reshape(3, 3),
                                        np.asarray(gt["cam_t_m2c"]), K, mask, slack_px)
                if share is not None:
                    shares.append(share)
    return shares


def all_means_reprojection(dataset_folder: Path, models: dict[str, Path]) -> list[float]:
    """Per instance: the share of all its object's Gaussian means (faint ones too, not only the model points)
    projected with the COCO pose and K that fall inside its amodal mask; objects whose object.ply is neither
    given nor in the cache are skipped."""
    dataset = CocoDataset.read(dataset_folder)
    names, images, means = {c["id"]: c["name"] for c in dataset.categories}, {i["id"]: i for i in dataset.images}, {}
    for name, model in dataset.info.get("object_models", {}).items():
        path = models.get(name) or (input_path(dataset_folder, model["input"]) or Path("/nonexistent")) / model["file"]
        if path.is_file():
            means[name] = MetricFrame.from_dict(model).from_model(read_ply(path).means.numpy())
    shares = []
    for ann in dataset.annotations:
        if names[ann["category_id"]] in means:
            share = inside_fraction(means[names[ann["category_id"]]], np.asarray(ann["pose"]["R"]),
                                    np.asarray(ann["pose"]["t"]), np.asarray(images[ann["image_id"]]["K"]),
                                    rle_to_mask(ann["amodal_segmentation"]))
            if share is not None:
                shares.append(share)
    return shares


def share_summary(shares: list[float]) -> dict:
    """min, mean and count below INSIDE_TARGET of per-instance shares."""
    values = np.asarray(shares)
    return {"instances": len(values), "min": round(float(values.min()), 4), "mean": round(float(values.mean()), 4),
            "below_098": int((values < INSIDE_TARGET).sum())} if len(values) else {}


def ultralytics_check(export_dir: Path, task: str) -> dict:
    """Ultralytics' own checks of a YOLO export: check_det_dataset on data.yaml, then its YOLODataset reading
    every label of every split (verify_image_label); {"available": False} when it does not import."""
    try:
        from ultralytics.cfg import get_cfg
        from ultralytics.data.dataset import YOLODataset
        from ultralytics.data.utils import check_det_dataset
        from ultralytics.utils import DEFAULT_CFG
    except ImportError as error:
        return {"available": False, "reason": str(error)}
    import ultralytics

    data = check_det_dataset(str(export_dir / "data.yaml"), autodownload=False)
    result = {"available": True, "version": ultralytics.__version__, "names": list(data["names"].values())}
    for split in ("train", "val", "test"):
        if data.get(split):
            dataset = YOLODataset(img_path=data[split], imgsz=640, augment=False, data=data, task=task,
                                  hyp=get_cfg(DEFAULT_CFG), prefix=f"{split}: ")
            labels = dataset.get_labels()
            result[split] = {"images": len(labels), "instances": int(sum(len(label["cls"]) for label in labels)),
                             "segments": int(sum(len(label["segments"]) for label in labels))}
    return result


def recompose(dataset: Path, out: Path) -> dict:
    """Rerun compose for a cached dataset into `out` with its manifest's settings, inputs and seed: seconds and
    whether its images and masks are byte-identical to the cached ones."""
    manifest = read_manifest(dataset)
    inputs = {name: input_path(dataset, name) for name in manifest["inputs"]}
    if any(path is None for path in inputs.values()):
        return {"rerun": False, "why": "an input is a raw file or no longer cached"}
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    started = time.perf_counter()
    compose.run(Context(stage="compose", item=manifest["item"], params=manifest["params"], inputs=inputs, out=out,
                        seed=manifest["seed"]))
    seconds = time.perf_counter() - started
    images = sorted((dataset / "images").iterdir())
    same_images = sum(path.read_bytes() == (out / "images" / path.name).read_bytes() for path in images)
    old, new = (json.loads((folder / CocoDataset.JSON).read_text())["annotations"] for folder in (dataset, out))
    same_masks = len(old) == len(new) and all(a["segmentation"] == b["segmentation"] and a["bbox"] == b["bbox"]
                                              for a, b in zip(old, new))
    return {"rerun": True, "seconds": round(seconds, 1), "what": "compose rerun in this run", "images": len(images),
            "identical_images": same_images,
            "identical_masks_and_boxes": same_masks}


def compose_real(out: Path, images: int) -> tuple[Path, dict, dict[str, Path]]:
    """The real plant on the TUM photo (benchmarks.compose), timed: (dataset, timing, {name: object.ply})."""
    from benchmarks.lib.real_plant import real_plant_on_tum

    stats = real_plant_on_tum(out, images)["compose"]
    return out / "out", {"seconds": stats["seconds"], "images": stats["images"],
                         "what": "compose's image loop in this run (stats.json seconds; asset loading excluded)"}, \
        {"plant": out / "extract" / "object.ply"}


def measure(dataset: Path, compose_timing: dict, out: Path, models: dict[str, Path]) -> dict:
    """Export the dataset in every format (timed) and check each export."""
    result = {"dataset": str(dataset), "compose": compose_timing, "exports": {}}
    for fmt in ("yolo-segment", "yolo-detect", "bop"):
        target = out / fmt
        shutil.rmtree(target, ignore_errors=True)
        started = time.perf_counter()
        summary = export(dataset, fmt, target, models=models)
        seconds = time.perf_counter() - started
        entry = {"seconds": round(seconds, 2), "summary": summary}
        entry["share_of_compose"] = round(seconds / compose_timing["seconds"], 4)
        if fmt.startswith("yolo"):
            task = fmt.split("-")[1]
            boxes = yolo_box_errors(target, "train", dataset, task)
            entry["box_edge_error_px"] = {"max": round(float(boxes.max()), 4), "mean": round(float(boxes.mean()), 4)}
            if task == "segment":
                pairs = yolo_polygon_ious(target, "train", dataset)
                iou = np.asarray([value for value, _ in pairs])
                entry["polygon_iou"] = {"instances": len(iou), "min": round(float(iou.min()), 4),
                                        "mean": round(float(iou.mean()), 4), "p1": round(float(np.percentile(iou, 1)), 4),
                                        "below_095": int((iou < IOU_TARGET).sum()),
                                        "below_095_with_ceiling": [[round(value, 4), round(ceiling, 4)]
                                                                   for value, ceiling in pairs if ceiling is not None]}
            entry["ultralytics"] = ultralytics_check(target, task)
        else:
            entry["reprojection_inside_amodal"] = share_summary(bop_reprojection(target))
            entry["reprojection_within_half_pixel"] = share_summary(bop_reprojection(target, slack_px=0.5))
            entry["all_means_inside_amodal"] = share_summary(all_means_reprojection(dataset, models))
        result["exports"][fmt] = entry
    return result


def write_markdown(result: dict, command: str) -> None:
    """benchmarks/results/convert.md from the figures."""
    exports, timing = result["exports"], result["compose"]
    segment, detect, bop = exports["yolo-segment"], exports["yolo-detect"], exports["bop"]
    iou, reproj, all_means = segment["polygon_iou"], bop["reprojection_inside_amodal"], bop["all_means_inside_amodal"]
    half = bop["reprojection_within_half_pixel"]
    lines = [
        "# Export benchmark (issue 33)", "", "Command (repository root):", "", "```", command, "```", "",
        f"Dataset: `{result['dataset']}`; compose: {json.dumps(timing)}.", "",
        "| check | target | measured | met |", "|---|---|---|---|",
        f"| YOLO polygon filled again (Ultralytics' rule) vs COCO mask, per instance | IoU >= 0.95 | min {iou['min']}, "
        f"mean {iou['mean']}, 1st percentile {iou['p1']}, {iou['below_095']} of {iou['instances']} below 0.95 "
        f"(IoU, and the most any one polygon can reach for that mask: {iou['below_095_with_ceiling']}) | "
        f"{'yes' if iou['below_095'] == 0 else 'no'} |",
        "| the same, instances for which one polygon can reach 0.95 (benchmarks.convert.single_polygon_ceiling) | IoU >= "
        f"0.95 | {sum(c >= IOU_TARGET for _, c in iou['below_095_with_ceiling'])} below | "
        f"{'yes' if all(c < IOU_TARGET for _, c in iou['below_095_with_ceiling']) else 'no'} |",
        f"| YOLO detect boxes vs COCO boxes | within 1 px | largest edge difference {detect['box_edge_error_px']['max']} px | "
        f"{'yes' if detect['box_edge_error_px']['max'] <= 1 else 'no'} |",
        f"| box Ultralytics derives from a YOLO polygon vs COCO box | within 1 px | largest edge difference "
        f"{segment['box_edge_error_px']['max']} px | {'yes' if segment['box_edge_error_px']['max'] <= 1 else 'no'} |",
        "| model points (Gaussians >= 0.5 opaque) projected with the BOP pose and K inside the amodal mask "
        "(`mask/`) | >= 98 % per instance | "
        + (f"min {reproj['min']:.1%}, mean {reproj['mean']:.1%}, {reproj['below_098']} of {reproj['instances']} below 98 % | "
           f"{'yes' if reproj['below_098'] == 0 else 'no'} |" if reproj else "no models found | - |"),
        "| the same, a point within half a pixel of a mask pixel counted in | (not a target: a mask pixel is one at "
        "least half covered, so a point on the outline of a part thinner than two pixels can lie in a pixel left out) | "
        + (f"min {half['min']:.1%}, mean {half['mean']:.1%}, {half['below_098']} of {half['instances']} below 98 % "
           "| - |" if half else "no models found | - |"),
        "| all Gaussian means (faint ones too) projected with the COCO pose and K inside the amodal mask | (not a "
        "target: faint Gaussians draw no mask pixel) | "
        + (f"min {all_means['min']:.1%}, mean {all_means['mean']:.1%}, {all_means['below_098']} of "
           f"{all_means['instances']} below 98 % | - |" if all_means else "no models found | - |"),
    ]
    images = segment["summary"]["splits"]["train"]["images"]
    for fmt in ("yolo-segment", "yolo-detect", "bop"):
        share, seconds = exports[fmt]["share_of_compose"], exports[fmt]["seconds"]
        lines.append(f"| {fmt} export time | <= 10 % of compose | {seconds} s ({1000 * seconds / images:.1f} ms per "
                     f"image) = {share:.1%} of compose's {timing['seconds']} s ({1000 * timing['seconds'] / images:.0f} "
                     f"ms per image) | {'yes' if share <= 0.1 else 'no'} |")
    for fmt in ("yolo-segment", "yolo-detect"):
        check = exports[fmt]["ultralytics"]
        lines.append(f"| Ultralytics' checker on the {fmt} export | accepts it | "
                     + (f"{check['version']}: check_det_dataset passed, YOLODataset read {json.dumps({k: v for k, v in check.items() if k in ('train', 'val', 'test')})} | yes |"
                        if check["available"] else f"not installed ({check['reason']}) | - |"))
    lines += ["", "Polygon details: " + json.dumps(segment["summary"]["splits"]["train"]), "",
              "How: a YOLO label holds one polygon per instance; the mask's outer boundaries and holes (boundary-pixel "
              "centres) are joined by zero-width bridges, the components along a minimum spanning tree and each hole "
              "to its own boundary (stages/lib/dataset_formats/polygons.py). Filled again with the even-odd rule, holes come back "
              "exactly and only the pixels a bridge crosses outside the mask are extra; every component is kept, so "
              "the polygon's extent is the mask's box. The reprojection uses the BOP files: models/obj_*.ply (model "
              "points, mm), scene_gt.json, scene_camera.json and mask/.", "",
              "All figures: `" + json.dumps({k: v for k, v in result.items() if k != "exports"}) + "`", ""]
    RESULTS.write_text("\n".join(lines))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path, nargs="?", help="a compose output folder")
    parser.add_argument("--images", type=int, default=200, help="without DATASET: images of the real plant to compose")
    parser.add_argument("--out", type=Path, default=REPO / "outputs" / "export_bench",
                        help="work folder (default beside the cache: /tmp is 3x slower to create files in here)")
    parser.add_argument("--model", type=model_argument, action="append", default=[],
                        help="NAME=PATH of an object's object.ply when the dataset is not in the cache")
    args = parser.parse_args()
    models = dict(args.model)
    if args.dataset is None:
        dataset, timing, found = compose_real(args.out / "compose", args.images)
        models = {**found, **models}
    else:
        dataset = args.dataset
        timing = recompose(dataset, args.out / "recomposed") if (dataset / MANIFEST).is_file() else {}
        if not timing.get("rerun"):
            stats = json.loads((dataset / "stats.json").read_text())
            timing = {**timing, "seconds": stats["seconds"], "what": "the dataset's own stats.json (another run)"}
    result = measure(dataset, timing, args.out, models)
    print(json.dumps(result, indent=1))
    with_ultralytics = result["exports"]["yolo-segment"]["ultralytics"]["available"]
    python = sys.executable if with_ultralytics else "python"  # a venv that has ultralytics, when it ran
    write_markdown(result, f"{python} -m benchmarks.convert {' '.join(sys.argv[1:])}")


if __name__ == "__main__":
    main()
