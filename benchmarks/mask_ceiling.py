"""What masks the detector can give, per class: the ceiling the mask head's resolution sets, and how the masks of
a training set compare with those of a test set.

    python -m benchmarks.mask_ceiling TEST_SET [TEST_SET ...] [--train DATASET] [--resolution 28]
                                      [--blur 1 2 3] [--predictions EVAL_FOLDER ...]

Mask R-CNN predicts each mask on a `resolution` x `resolution` grid inside its box (torchvision's mask head:
28) and pastes it back. Each ground-truth mask of a test set goes through the same round trip (crop to its box,
resize to the grid, threshold 0.5, paste back at the box) and is then scored as if it were a perfect detector's
prediction (score 1, its own box): the mask AP that resolution allows at best, per class, with pycocotools.
With `--blur`, the same with the grid blurred by Gaussians of so many cells before the threshold: a head that
is as unsure of the edges of every class, which costs thin shapes (the plant's leaves) the most. The
training set's masks (`--train`, a composed dataset) and the test sets' are compared by how much of their box they
fill (thin leaves fill little) and by the share of their pixels on the mask's boundary. With `--predictions`
(eval output folders, one per test set, in the same order): per class, each ground-truth mask against the
predicted mask of its class that overlaps it most (median mask IoU, and predicted area / true area).
Writes benchmarks/results/mask_ceiling.md (and prints it).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from stages.eval.run import coco_metrics
from benchmarks.lib.mask_matching import best_match, predicted_masks
from stages.lib.coco import load_coco, mask_to_rle

RESULTS = Path(__file__).resolve().parent / "results"


def grid_round_trip(mask: np.ndarray, box: list[float], resolution: int, blur_cells: float = 0.0) -> np.ndarray:
    """A mask [H, W] bool as the mask head gives it back: cropped to its box [x, y, w, h], resized to the
    resolution x resolution grid (area average), blurred by a Gaussian of blur_cells grid cells (a head as
    unsure of edges as that), thresholded at 0.5 and pasted back (bilinear) into the box."""
    x0, y0, w, h = (int(round(v)) for v in box)
    w, h = max(w, 1), max(h, 1)
    crop = mask[y0:y0 + h, x0:x0 + w].astype(np.float32)
    grid = cv2.resize(crop, (resolution, resolution), interpolation=cv2.INTER_AREA)
    if blur_cells > 0:
        grid = cv2.GaussianBlur(grid, (0, 0), blur_cells)
    back = cv2.resize(grid, (crop.shape[1], crop.shape[0]), interpolation=cv2.INTER_LINEAR) >= 0.5
    out = np.zeros_like(mask, dtype=bool)
    out[y0:y0 + crop.shape[0], x0:x0 + crop.shape[1]] = back
    return out


def mask_shape(mask: np.ndarray, box: list[float]) -> tuple[float, float]:
    """(fill: mask pixels / box pixels, boundary: share of mask pixels next to a background pixel)."""
    area = int(mask.sum())
    eroded = cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    return area / max(box[2] * box[3], 1.0), float((mask & ~eroded).sum() / max(area, 1))


def per_class_shapes(folder: Path) -> dict[str, dict[str, float]]:
    """{class: {"fill", "boundary", "instances"}} (medians) over the masks of a COCO folder."""
    coco = load_coco(folder)
    names = {c["id"]: c["name"] for c in coco.loadCats(coco.getCatIds())}
    values: dict[str, list[tuple[float, float]]] = {}
    for ann in coco.dataset["annotations"]:
        values.setdefault(names[ann["category_id"]], []).append(mask_shape(coco.annToMask(ann) > 0, ann["bbox"]))
    return {name: {"fill": float(np.median([v[0] for v in found])), "boundary": float(np.median([v[1] for v in found])),
                   "instances": len(found)} for name, found in sorted(values.items())}


def matched_predictions(folder: Path, eval_folder: Path, score: float = 0.5) -> dict[str, dict[str, float]]:
    """{class: {"iou", "area_ratio", "matched", "instances"}} (medians): every true mask of the test set against
    the prediction of its class (score >= `score`) whose mask overlaps it most (IoU > 0.1 counts as matched)."""
    coco = load_coco(folder)
    names = {c["id"]: c["name"] for c in coco.loadCats(coco.getCatIds())}
    predictions = predicted_masks(eval_folder, score)
    found: dict[str, list[tuple[float, float]]] = {}
    for ann in coco.dataset["annotations"]:
        truth = coco.annToMask(ann) > 0
        iou, mask = best_match(truth, predictions.get((ann["image_id"], ann["category_id"]), []))
        area_ratio = 0.0 if mask is None else float(mask.sum() / max(truth.sum(), 1))
        found.setdefault(names[ann["category_id"]], []).append((iou, area_ratio))
    return {name: {"iou": float(np.median([v[0] for v in values])),
                   "area_ratio": float(np.median([v[1] for v in values if v[0] > 0.1] or [0.0])),
                   "matched": sum(v[0] > 0.1 for v in values), "instances": len(values)}
            for name, values in sorted(found.items())}


def ceiling(coco, masks: list[np.ndarray], resolution: int, blur_cells: float = 0.0) -> dict:
    """Mask AP (per class) of a test set's own masks (a loaded COCO and its annotations' masks [H, W] bool, in
    order) after the grid round trip, scored as detections."""
    results = []
    for ann, mask in zip(coco.dataset["annotations"], masks):
        back = grid_round_trip(mask, ann["bbox"], resolution, blur_cells)
        results.append({"image_id": ann["image_id"], "category_id": ann["category_id"], "bbox": ann["bbox"],
                        "score": 1.0, "segmentation": mask_to_rle(back)})
    return coco_metrics(coco, results, coco.getImgIds())["segm"]


def main() -> None:
    """Command line: see the module docstring."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("test_sets", type=Path, nargs="+")
    parser.add_argument("--train", type=Path, default=None, help="a composed dataset to compare")
    parser.add_argument("--resolution", type=int, nargs="+", default=[28, 56])
    parser.add_argument("--blur", type=float, nargs="*", default=[1.0, 2.0, 3.0],
                        help="also with the grid blurred by these Gaussian sigmas (grid cells)")
    parser.add_argument("--predictions", type=Path, nargs="*", default=[], help="eval folders, one per test set")
    args = parser.parse_args()
    lines = ["# Mask ceiling: the mask AP the mask head's grid allows, and the masks' shapes", "",
             f"`python -m benchmarks.mask_ceiling {' '.join(map(str, args.test_sets))}"
             f"{' --train ' + str(args.train) if args.train else ''} --resolution {' '.join(map(str, args.resolution))}"
             f" --blur {' '.join(map(str, args.blur))}`", ""]
    report = {}
    for folder in args.test_sets:
        label = folder.name
        coco = load_coco(folder)
        masks = [coco.annToMask(ann) > 0 for ann in coco.dataset["annotations"]]  # each decoded once
        report[label] = {"ceiling": {r: ceiling(coco, masks, r) for r in args.resolution},
                         "shapes": per_class_shapes(folder)}
        classes = sorted(report[label]["shapes"])
        lines += [f"## {label}", "", "| class | " + " | ".join(f"mask AP at {r}x{r}" for r in args.resolution)
                  + " | fill of box | boundary share | instances |", "|---|" + "---|" * (len(args.resolution) + 3)]
        for name in classes:
            shape = report[label]["shapes"][name]
            aps = " | ".join(f"{report[label]['ceiling'][r]['per_class'][name]:.1f}" for r in args.resolution)
            lines.append(f"| {name} | {aps} | {shape['fill']:.2f} | {shape['boundary']:.2f} | {shape['instances']} |")
        lines += ["", "All classes: " + ", ".join(f"{report[label]['ceiling'][r]['AP']:.1f} at {r}x{r}"
                                                    for r in args.resolution), ""]
        if args.blur:
            blurred = {(r, sigma): ceiling(coco, masks, r, sigma)["per_class"]
                       for r in args.resolution for sigma in args.blur}
            report[label]["blurred"] = {f"{r}x{r} blur {sigma}": aps for (r, sigma), aps in blurred.items()}
            lines += ["The same with the grid blurred (a head equally unsure of the edges of every class, in grid "
                      "cells):", "", "| class | " + " | ".join(f"{r}x{r}, blur {sigma}" for r, sigma in blurred) + " |",
                      "|---|" + "---|" * len(blurred)]
            lines += [f"| {name} | " + " | ".join(f"{aps[name]:.1f}" for aps in blurred.values()) + " |"
                      for name in classes]
            lines.append("")
        if len(args.predictions) == len(args.test_sets):
            matched = matched_predictions(folder, args.predictions[args.test_sets.index(folder)])
            report[label]["predictions"] = matched
            lines += [f"Predictions of {args.predictions[args.test_sets.index(folder)]} (score >= 0.5), each true "
                      "mask against its class's prediction that overlaps it most:", "",
                      "| class | median mask IoU | median predicted / true area | matched |", "|---|---|---|---|"]
            lines += [f"| {name} | {m['iou']:.3f} | {m['area_ratio']:.2f} | {m['matched']} / {m['instances']} |"
                      for name, m in matched.items()]
            lines.append("")
    if args.train is not None:
        report["train"] = per_class_shapes(args.train)
        lines += [f"## training set {args.train}", "", "| class | fill of box | boundary share | instances |",
                  "|---|---|---|---|"]
        lines += [f"| {name} | {s['fill']:.2f} | {s['boundary']:.2f} | {s['instances']} |"
                  for name, s in report["train"].items()]
    text = "\n".join(lines) + "\n"
    (RESULTS / "mask_ceiling.md").write_text(text)
    (RESULTS / "mask_ceiling" / "mask_ceiling.json").write_text(json.dumps(report, indent=1, default=str))
    print(text)


if __name__ == "__main__":
    main()
