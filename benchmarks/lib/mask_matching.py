"""An eval folder's predicted masks, and the one that matches a true mask best (the mask ceiling and rendered-training
benchmarks)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from stages.lib.coco import rle_to_mask
from stages.lib.dataset_formats.polygons import mask_iou


def predicted_masks(eval_folder: Path, score: float = 0.5) -> dict[tuple[int, int], list[np.ndarray]]:
    """An eval folder's predicted masks [H, W] bool with at least `score`, by (image id, category id)."""
    predictions: dict[tuple[int, int], list[np.ndarray]] = {}
    for result in json.loads((eval_folder / "predictions.json").read_text()):
        if result["score"] >= score:
            predictions.setdefault((result["image_id"], result["category_id"]), []).append(
                rle_to_mask(result["segmentation"]))
    return predictions


def best_match(truth: np.ndarray, masks: list[np.ndarray]) -> tuple[float, np.ndarray | None]:
    """(IoU, mask) of the mask [H, W] that overlaps the true mask [H, W] most; (0, None) without masks."""
    best: tuple[float, np.ndarray | None] = (0.0, None)
    for mask in masks:
        iou = mask_iou(mask, truth)
        if best[1] is None or iou > best[0]:
            best = (iou, mask)
    return best
