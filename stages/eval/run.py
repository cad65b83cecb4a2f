"""Stage eval: COCO box and mask AP of a trained detector on one test set.

inputs:  `model` (a train_maskrcnn folder with model.pt), `testset` (folder with images/ + annotations.json).
returns: the metrics ({"bbox": {"AP", "AP50", "AP75", "per_class": {name: AP}}, "segm": {...}} in percent,
         plus inference seconds per image), which the engine writes as metrics.json (its one writer);
writes:  predictions.json (COCO results, RLE masks),
         predictions.png (a grid of test images with the detections drawn), model.onnx when cfg.onnx (with the
         description predict reads: `python -m stages.app.predict model.onnx SOURCE` runs it).
Categories are matched by name (ids may differ between the training data and the test set).
"""
from __future__ import annotations

import contextlib
import io
import json
import logging
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import torch
from PIL import Image
from pycocotools.cocoeval import COCOeval

from stages.contract.errors import StageError
from stages.eval.spec import EvalConfig
from stages.lib.coco import format_ap, load_coco
from stages.lib.detection.model import load_detector
from stages.lib.detection.model_folder import ONNX_KEY, describe
from stages.lib.detection.onnx_export import check_onnx, export_onnx
from stages.lib.detection.overlay import draw_detections
from stages.lib.detection.postprocess import PostProcessing, predict, to_coco_results
from stages.lib.detection.postprocess import detect, threshold_masks  # noqa: F401 (benchmarks/mask_refinement.py's)
from stages.lib.masks.refine import refine_radius
from stages.records.coco_dataset import CocoDataset

if TYPE_CHECKING:  # the engine's object; not part of the stage's cache key
    from stages.engine.context import Context

log = logging.getLogger(__name__)


def category_mapping(model_names: list[str], test_coco, source: str) -> dict[int, int]:
    """Model label (1..K, label i+1 = model_names[i]) -> test-set category id, matched by name.

    Every test category must be known to the model; model classes absent from the test set are
    dropped from the predictions (with a warning). Raises ValueError naming both lists otherwise.
    """
    test_ids = {c["name"]: c["id"] for c in test_coco.loadCats(test_coco.getCatIds())}
    unknown = sorted(set(test_ids) - set(model_names))
    if unknown:
        raise ValueError(f"{source}: test categories {unknown} are not among the model's categories "
                         f"{model_names}; the test set and the training data must use the same object names")
    extra = sorted(set(model_names) - set(test_ids))
    if extra:
        log.warning("%s: model categories %s are absent from the test set; their detections are dropped", source, extra)
    return {i + 1: test_ids[name] for i, name in enumerate(model_names) if name in test_ids}


def has_masks(coco_gt, image_ids: list[int]) -> bool:
    """Whether every ground-truth annotation of the evaluated images has a segmentation (RLE or polygon)."""
    anns = coco_gt.loadAnns(coco_gt.getAnnIds(imgIds=list(image_ids)))
    return all(a.get("segmentation") for a in anns)


def ranked_results(results: list[dict], iou_type: str) -> list[dict]:
    """Copies of the COCO result records whose "score" ranks them for `iou_type` ("bbox" or "segm"): a record's
    "mask_score", where it has one, ranks its mask; the box score ranks its box."""
    if iou_type == "segm":
        return [{**r, "score": r.get("mask_score", r["score"])} for r in results]
    return [dict(r) for r in results]


def evaluate_images(coco_gt, results: list[dict], image_ids: list[int], iou_type: str) -> COCOeval:
    """COCOeval of `iou_type` ("bbox" or "segm") over image_ids with every image matched (evaluate()), not yet
    accumulated; results ranked as ranked_results ranks them."""
    with contextlib.redirect_stdout(io.StringIO()):
        evaluator = COCOeval(coco_gt, coco_gt.loadRes(ranked_results(results, iou_type)), iou_type)
        evaluator.params.imgIds = list(image_ids)
        evaluator.evaluate()
    return evaluator


def average_precision(precision: np.ndarray) -> float | None:
    """The mean of COCO precision values (any shape; -1 = no object) in points, None when there are none."""
    valid = precision[precision > -1]
    return float(valid.mean() * 100) if valid.size else None


def coco_metrics(coco_gt, results: list[dict], image_ids: list[int]) -> dict:
    """COCOeval box and mask metrics in percent: {"bbox"|"segm": {"AP", "AP50", "AP75", "per_class"}}.

    results: COCO result records with "bbox", "segmentation" and "score" (which ranks them), and optionally
    "mask_score", which then ranks the masks instead; image_ids: the images evaluated.
    No detections at all gives AP 0. Per-class AP is None for a class without ground truth. A test set
    with boxes only (annotations without "segmentation") has no mask metrics: "segm" is
    {"available": False, "reason": ...} and its APs are None (not a zero).
    """
    names = {c["id"]: c["name"] for c in coco_gt.loadCats(coco_gt.getCatIds())}
    metrics = {}
    iou_types = ("bbox", "segm") if has_masks(coco_gt, image_ids) else ("bbox",)
    if "segm" not in iou_types:
        metrics["segm"] = {"available": False, "AP": None, "AP50": None, "AP75": None, "per_class": {},
                           "reason": "the test set has boxes only (no segmentation in its annotations)"}
    for iou_type in iou_types:
        if not results:
            metrics[iou_type] = {"AP": 0.0, "AP50": 0.0, "AP75": 0.0, "per_class": {n: 0.0 for n in names.values()}}
            continue
        evaluator = evaluate_images(coco_gt, results, image_ids, iou_type)
        with contextlib.redirect_stdout(io.StringIO()):
            evaluator.accumulate()
            evaluator.summarize()
        precision = evaluator.eval["precision"]  # [IoU thresholds, recall, class, area range, max dets]
        per_class = {}
        for k, cat_id in enumerate(evaluator.params.catIds):
            per_class[names[cat_id]] = average_precision(precision[:, :, k, 0, -1])
        stats = evaluator.stats
        metrics[iou_type] = {"AP": float(stats[0] * 100), "AP50": float(stats[1] * 100),
                             "AP75": float(stats[2] * 100), "per_class": per_class}
    return metrics


def image_grid(images: list[np.ndarray], columns: int = 4, cell_width: int = 320) -> np.ndarray:
    """Tile RGB images (resized to `cell_width` wide, aspect kept) into one [H, W, 3] uint8 grid."""
    cells = [cv2.resize(im, (cell_width, round(im.shape[0] * cell_width / im.shape[1])), interpolation=cv2.INTER_AREA)
             for im in images]
    cell_h = max(c.shape[0] for c in cells)
    rows = -(-len(cells) // columns)
    grid = np.full((rows * cell_h, min(columns, len(cells)) * cell_width, 3), 255, np.uint8)
    for i, cell in enumerate(cells):
        r, c = divmod(i, columns)
        grid[r * cell_h: r * cell_h + cell.shape[0], c * cell_width: (c + 1) * cell_width] = cell
    return grid


def run(ctx: Context) -> dict:
    """Evaluate ctx.inputs["model"] on ctx.inputs["testset"]; write metrics, predictions and a preview."""
    cfg = ctx.typed(EvalConfig)
    torch.set_num_threads(cfg.threads or os.cpu_count() or 1)
    model_file = Path(ctx.inputs["model"]) / "model.pt"
    test_folder = Path(ctx.inputs["testset"])
    try:
        if not model_file.is_file():
            raise FileNotFoundError(f"model file not found: {model_file} (expected a train_maskrcnn output)")
        model, model_cfg, names = load_detector(model_file, ctx.device)
        coco_gt = load_coco(test_folder)  # checked: every listed image exists
        label_to_category = category_mapping(names, coco_gt, str(test_folder / CocoDataset.JSON))
    except (ValueError, FileNotFoundError, StageError) as err:
        raise StageError(f"eval[{ctx.item}]: {err}") from err
    image_ids = sorted(coco_gt.getImgIds())
    if cfg.max_images:
        image_ids = image_ids[: cfg.max_images]
    results, drawn, seconds = [], [], 0.0
    for image_id in ctx.progress(image_ids):
        image = np.asarray(Image.open(CocoDataset.image_file(test_folder, coco_gt.imgs[image_id])).convert("RGB"))
        started = time.perf_counter()
        radius = refine_radius(cfg.mask_refine_radius, image.shape[:2], model_cfg.image_size)
        detections = predict(model, image, ctx.device, cfg.mask_threshold, radius, cfg.mask_refine_eps,
                             cfg.mask_owner_score)
        seconds += time.perf_counter() - started
        results += to_coco_results(image_id, detections, label_to_category, cfg.mask_score)
        if len(drawn) < cfg.draw_images:
            drawn.append(draw_detections(image, detections, names, cfg.draw_score_threshold))
    metrics = coco_metrics(coco_gt, results, image_ids)
    metrics.update({"images": len(image_ids), "detections": len(results), "backbone": model_cfg.backbone,
                    "inference_seconds_per_image": seconds / max(len(image_ids), 1), "device": ctx.device})
    if cfg.onnx:
        first = np.asarray(Image.open(CocoDataset.image_file(test_folder, coco_gt.imgs[image_ids[0]])).convert("RGB"))
        post = PostProcessing.of(cfg)
        export_onnx(model, ctx.out / "model.onnx", first, {ONNX_KEY: json.dumps(describe(names, model_cfg, post))})
        metrics["onnx"] = check_onnx(model, ctx.out / "model.onnx", first, post, model_cfg.image_size)
    (ctx.out / "predictions.json").write_text(json.dumps(results))
    if drawn:
        Image.fromarray(image_grid(drawn)).save(ctx.out / "predictions.png")
    log.info("eval %s: box AP %.1f, mask AP %s on %d images", test_folder, metrics["bbox"]["AP"],
             format_ap(metrics["segm"]["AP"]), len(image_ids))
    return metrics
