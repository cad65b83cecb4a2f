"""Mask AP per class of one trained detector for several settings of the eval stage's mask post-processing: the
guided filter along the photo's edges (eval.mask_refine_radius and eval.mask_refine_eps) and the disjoint masks of
different classes (eval.mask_owner_score), the detector run once per image.

    python -m benchmarks.mask_refinement MODEL_FOLDER DATASET [--images 150] [--radius 0 4.8 6 8]
        [--eps 3e-4 1e-3] [--owner-score none 0.5] [--threads 2] [--json rows.json]

MODEL_FOLDER is a train_maskrcnn cache entry (model.pt). To choose the settings without the test photos, DATASET is
a compose output of another seed (the training domain, which a user has: benchmarks/in_domain.py); a test set
measures them. Radius 0 with owner score none is the mask head's masks as they are. Prints one row per (radius, eps,
owner score): mask mAP, each class's mask AP and the post-processing's seconds per image; box AP does not depend on
them and is printed once.
"""
from __future__ import annotations

import argparse
import itertools
import json
import logging
import time
from pathlib import Path

import numpy as np
from PIL import Image

from benchmarks.lib.detector_runs import add_run_arguments, start
from stages.eval.run import category_mapping, coco_metrics, detect, threshold_masks, to_coco_results
from stages.eval.spec import EvalConfig
from stages.lib.coco import load_coco
from stages.lib.detection.model import load_detector
from stages.lib.masks.refine import refine_radius
from stages.records.coco_dataset import CocoDataset

log = logging.getLogger("benchmarks.mask_refinement")


def mask_ap_by_setting(model_file: Path, dataset: Path, settings: list[tuple[float, float, float | None]],
                       images: int = 0, device: str = "cpu") -> dict:
    """{"box_AP", "rows": [{"radius", "eps", "owner_score", "AP", "per_class", "seconds_per_image", "results"}]}: the
    eval stage's metrics and COCO result records of the detector in model_file on the first `images` images of
    `dataset` (0 = all), its masks post-processed with each (radius at the detector's input scale, eps, owner score
    or None) of `settings`; the detector runs once per image."""
    model, model_cfg, names = load_detector(model_file, device)
    coco_gt = load_coco(dataset)
    label_to_category = category_mapping(names, coco_gt, str(dataset / CocoDataset.JSON))
    image_ids = sorted(coco_gt.getImgIds())[: images or None]
    cfg = EvalConfig()
    results = {setting: [] for setting in settings}
    seconds = dict.fromkeys(settings, 0.0)
    for image_id in image_ids:
        image = np.asarray(Image.open(CocoDataset.image_file(dataset, coco_gt.imgs[image_id])).convert("RGB"))
        detected = detect(model, image, device)
        for setting in settings:
            radius, eps, owner_score = setting
            started = time.perf_counter()
            detections = threshold_masks(detected, cfg.mask_threshold,
                                         refine_radius(radius, image.shape[:2], model_cfg.image_size), eps, owner_score)
            seconds[setting] += time.perf_counter() - started
            results[setting] += to_coco_results(image_id, detections, label_to_category, cfg.mask_score.value)
    rows, box_ap = [], None
    for setting in settings:
        metrics = coco_metrics(coco_gt, results[setting], image_ids)
        box_ap = metrics["bbox"]["AP"]
        rows.append({"radius": setting[0], "eps": setting[1], "owner_score": setting[2], "AP": metrics["segm"]["AP"],
                     "per_class": metrics["segm"]["per_class"],
                     "seconds_per_image": seconds[setting] / max(len(image_ids), 1), "results": results[setting]})
    return {"box_AP": box_ap, "rows": rows}


def owner_score(text: str) -> float | None:
    """--owner-score's parser: "none" (case-insensitive) or a float."""
    return None if text.lower() == "none" else float(text)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", type=Path, help="a train_maskrcnn output folder")
    parser.add_argument("dataset", type=Path, help="a COCO folder (images/ + annotations.json): a compose output")
    parser.add_argument("--images", type=int, default=150, help="the first N images (0 = all)")
    parser.add_argument("--radius", type=float, nargs="+", default=[0.0, 4.8, EvalConfig.mask_refine_radius, 8.0],
                        help="pixels at the detector's input scale (0 = no refinement)")
    parser.add_argument("--eps", type=float, nargs="+", default=[EvalConfig.mask_refine_eps, 1e-3])
    parser.add_argument("--owner-score", type=owner_score, nargs="+", default=[EvalConfig.mask_owner_score],
                        help="eval.mask_owner_score values: a box score in [0, 1], or none (overlaps kept)")
    add_run_arguments(parser)
    args = parser.parse_args()
    device = start(args)
    filters = [(0.0, EvalConfig.mask_refine_eps)] if 0.0 in args.radius else []
    filters += [(r, e) for r, e in itertools.product(args.radius, args.eps) if r > 0]
    settings = [(r, e, o) for (r, e), o in itertools.product(filters, args.owner_score)]
    table = mask_ap_by_setting(args.model / "model.pt", args.dataset, settings, args.images, device)
    log.info("box AP %.1f (every setting)", table["box_AP"])
    for row in table["rows"]:
        classes = ", ".join(f"{name} {ap:.1f}" for name, ap in row["per_class"].items() if ap is not None)
        log.info("radius %4.1f eps %.0e owner score %s: mask AP %.1f (%s), %.3f s per image", row["radius"], row["eps"],
                 row["owner_score"], row["AP"], classes, row["seconds_per_image"])
    if args.json:
        rows = [{k: v for k, v in row.items() if k != "results"} for row in table["rows"]]
        args.json.write_text(json.dumps({"model": str(args.model), "dataset": str(args.dataset),
                                         "box_AP": table["box_AP"], "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
