"""One class's mask AP gap to the other classes (issue 31's plant): where it is made, how precisely it is measured.

Where: along the IoU thresholds. How precisely: over test sets drawn from the test set's own images.

    python -m benchmarks.class_gap by-iou TESTSET EVAL_FOLDER [EVAL_FOLDER ...]
    python -m benchmarks.class_gap resample TESTSET EVAL_FOLDER [EVAL_FOLDER ...] [--category plant]
        [--draws 500] [--target 15] [--seed 0]

TESTSET is a folder with images/ + annotations.json; each EVAL_FOLDER an eval cache entry on that test set (its
predictions.json, masks ranked as the eval stage ranks them), e.g. one per seed.
- by-iou: each class's mask AP at each IoU threshold 0.50-0.95, the mean over the folders.
- resample: the gap over test sets drawn from TESTSET with replacement (a bootstrap over its images). Every folder
  is scored on the same draws, so the folders' mean gap has an interval of its own. Prints JSON: for each folder
  and for their mean, the gap on the whole test set (the eval stage's figure), and over the draws its mean,
  standard deviation, 2.5 / 97.5 % percentiles and the share of draws where it is at most --target.
"""
from __future__ import annotations

import argparse
import contextlib
import copy
import io
import json
from pathlib import Path

import numpy as np
from pycocotools.cocoeval import COCOeval

from stages.eval.run import average_precision as stage_average_precision, evaluate_images
from stages.lib.coco import load_coco


def evaluate_masks(coco_gt, results: list[dict]) -> COCOeval:
    """The eval stage's COCOeval of the masks on every image of coco_gt, matched and not yet accumulated."""
    return evaluate_images(coco_gt, results, sorted(coco_gt.getImgIds()), "segm")


def precision_on(evaluator: COCOeval, draw: np.ndarray) -> np.ndarray:
    """COCO's precision [IoU thresholds, recall, class] (area "all", 100 detections, -1 where a class has no
    object) on the test set made of the images at positions `draw` [M] (repeats allowed) of evaluator's list."""
    images = len(evaluator.params.imgIds)
    areas = len(evaluator.params.areaRng)
    drawn = copy.copy(evaluator)
    drawn.params = copy.deepcopy(evaluator.params)
    drawn._paramsEval = copy.deepcopy(evaluator._paramsEval)
    drawn.params.imgIds = drawn._paramsEval.imgIds = list(range(len(draw)))
    drawn.evalImgs = [evaluator.evalImgs[(k * areas + a) * images + i]
                      for k in range(len(evaluator.params.catIds)) for a in range(areas) for i in draw]
    with contextlib.redirect_stdout(io.StringIO()):
        drawn.accumulate()
    return drawn.eval["precision"][:, :, :, 0, -1]


def average_precision(precision: np.ndarray) -> float:
    """The eval stage's average_precision of COCO precision values (any shape), NaN where it has none."""
    ap = stage_average_precision(precision)
    return float("nan") if ap is None else ap


def class_names(evaluator: COCOeval) -> list[str]:
    """The names of evaluator's classes, in its order."""
    return [evaluator.cocoGt.cats[c]["name"] for c in evaluator.params.catIds]


def ap_by_iou(evaluator: COCOeval) -> dict[str, list[float]]:
    """Each class's mask AP in points at each of the 10 IoU thresholds (0.50, 0.55, ... 0.95), whole test set."""
    precision = precision_on(evaluator, np.arange(len(evaluator.params.imgIds)))
    return {name: [average_precision(p) for p in precision[:, :, k]] for k, name in enumerate(class_names(evaluator))}


def gap_on_draw(evaluator: COCOeval, draw: np.ndarray, category: str) -> float:
    """The mean mask AP of the other classes minus `category`'s, in points, on the test set made of the images at
    positions `draw` [M] (repeats allowed) of evaluator's image list; NaN when a class has no object in it."""
    precision = precision_on(evaluator, draw)
    ap = {name: average_precision(precision[:, :, k]) for k, name in enumerate(class_names(evaluator))}
    return float(np.mean([v for n, v in ap.items() if n != category]) - ap[category])


def resampled_gaps(evaluators: list[COCOeval], category: str, draws: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The gap of each evaluator on the whole test set [E], and on `draws` test sets drawn with replacement from
    its images, the same draws for every evaluator [draws, E]."""
    images = len(evaluators[0].params.imgIds)
    whole = np.array([gap_on_draw(e, np.arange(images), category) for e in evaluators])
    rng = np.random.default_rng(seed)
    drawn = np.array([[gap_on_draw(e, draw, category) for e in evaluators]
                      for draw in (rng.integers(0, images, images) for _ in range(draws))])
    return whole, drawn


def summary(whole: float, drawn: np.ndarray, target: float) -> dict:
    """The whole-set gap and the draws' [draws] mean, std, 95 % interval and share at most `target`."""
    drawn = drawn[~np.isnan(drawn)]
    low, high = np.percentile(drawn, [2.5, 97.5])
    return {"gap": round(whole, 2), "draws": len(drawn), "mean": round(float(drawn.mean()), 2),
            "std": round(float(drawn.std()), 2), "interval_95": [round(float(low), 2), round(float(high), 2)],
            "share_at_most_target": round(float((drawn <= target).mean()), 3)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    for name in ("by-iou", "resample"):
        command = commands.add_parser(name)
        command.add_argument("testset", type=Path)
        command.add_argument("evals", type=Path, nargs="+", help="eval cache entries (predictions.json) on TESTSET")
    resample = commands.choices["resample"]
    resample.add_argument("--category", default="plant")
    resample.add_argument("--draws", type=int, default=500)
    resample.add_argument("--target", type=float, default=15.0)
    resample.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    coco_gt = load_coco(args.testset)
    evaluators = [evaluate_masks(coco_gt, json.loads((folder / "predictions.json").read_text()))
                  for folder in args.evals]
    if args.command == "by-iou":
        tables = [ap_by_iou(e) for e in evaluators]
        print(json.dumps({"testset": str(args.testset), "folders": [str(f) for f in args.evals],
                          "iou_thresholds": [round(t, 2) for t in evaluators[0].params.iouThrs],
                          "ap_by_iou": {name: [round(float(v), 1) for v in np.mean([t[name] for t in tables], axis=0)]
                                        for name in tables[0]}}, indent=1))
        return
    whole, drawn = resampled_gaps(evaluators, args.category, args.draws, args.seed)
    report = {"testset": str(args.testset), "category": args.category, "images": len(coco_gt.getImgIds()),
              "objects": len(coco_gt.getAnnIds(catIds=[c for c, v in coco_gt.cats.items()
                                                        if v["name"] == args.category])),
              "folders": {str(f): summary(w, drawn[:, i], args.target)
                          for i, (f, w) in enumerate(zip(args.evals, whole))},
              "mean_of_folders": summary(float(whole.mean()), drawn.mean(axis=1), args.target)}
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
