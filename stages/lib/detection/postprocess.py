"""From the detector's outputs to detections with masks, and to COCO result records: what eval scores and predict
writes, for both backends (PyTorch and onnxruntime give the same head outputs, stages/lib/detection/inference.py).

The masks: the pasted probabilities guided-filtered by the photo's colours (mask_refine.py), made disjoint across
classes (mask_overlap.py), thresholded; each detection's maskness is the mean probability inside its mask.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch

from stages.lib.coco import mask_to_rle
from stages.lib.detection.inference import head_outputs, paste, select
from stages.lib.detection.mask_settings import MASK_REFINE_EPS
from stages.lib.masks.overlap import separate_classes
from stages.lib.masks.refine import refine_masks, refine_radius


@dataclass(frozen=True)
class PostProcessing:
    """The mask settings of eval (stages/eval/spec.py EvalConfig, which documents them), kept with a model:
    mask_threshold, mask_score ("box" | "maskness"), mask_refine_radius (pixels at the detector's input scale),
    mask_refine_eps and mask_owner_score (None: overlaps kept)."""

    mask_threshold: float
    mask_score: str
    mask_refine_radius: float
    mask_refine_eps: float
    mask_owner_score: float | None

    @classmethod
    def of(cls, settings) -> "PostProcessing":
        """The post-processing settings of an object that has these fields (EvalConfig, a config section, a dict)."""
        get = settings.get if isinstance(settings, dict) else lambda name: getattr(settings, name)
        values = {f.name: get(f.name) for f in fields(cls)}
        values["mask_score"] = str(values["mask_score"])
        return cls(**values)


def detect(model: torch.nn.Module, image: np.ndarray, device: str) -> dict:
    """The detector's outputs on one RGB uint8 image [H, W, 3], as tensors on `device`: image [3, H, W] in [0, 1],
    boxes [N, 4] x0y0x1y1, scores [N], labels [N], probability [N, H, W] (the masks pasted into the image)."""
    return paste(head_outputs(model, image, device))


def threshold_masks(detected: dict, mask_threshold: float, radius_px: int = 0,
                    eps: float = MASK_REFINE_EPS, owner_score: float | None = None) -> dict:
    """detect()'s outputs as numpy detections: boxes [N, 4], scores [N], labels [N], masks [N, H, W] bool
    (probability > mask_threshold, after refine_masks with a radius of radius_px image pixels and eps when radius_px
    is > 0, then separate_classes with owner_score unless it is None) and maskness [N] (the mean probability inside
    each mask, 0 for an empty one)."""
    probability = refine_masks(detected["image"], detected["probability"], radius_px, eps)  # [N, H, W]
    if owner_score is not None:
        probability = separate_classes(probability, detected["scores"], detected["labels"], mask_threshold,
                                       owner_score)
    masks = probability > mask_threshold
    inside = masks.sum(dim=(1, 2))  # [N]
    maskness = (probability * masks).sum(dim=(1, 2)) / inside.clamp_min(1)  # [N]
    return {"boxes": detected["boxes"].cpu().numpy(), "scores": detected["scores"].cpu().numpy(),
            "labels": detected["labels"].cpu().numpy(), "masks": masks.cpu().numpy(), "maskness": maskness.cpu().numpy()}


def predict(model: torch.nn.Module, image: np.ndarray, device: str, mask_threshold: float, radius_px: int = 0,
            eps: float = MASK_REFINE_EPS, owner_score: float | None = None) -> dict:
    """Detections on one RGB uint8 image [H, W, 3]: threshold_masks(detect(...)); radius_px in the image's pixels
    (0 and owner_score None: the mask head's masks as they are)."""
    return threshold_masks(detect(model, image, device), mask_threshold, radius_px, eps, owner_score)


def postprocess(outputs: dict, post: PostProcessing, detector_size: int, min_score: float = 0.0) -> dict:
    """threshold_masks' detections (boxes, scores, labels, masks [N, H, W], maskness) of the head outputs
    (inference.head_outputs, or the ONNX graph's as tensors) whose score is at least min_score, with the settings of
    `post` (the refinement radius scaled from the detector's input size `detector_size` to the image).

    Only those detections and the ones that may take pixels from them (box score at least post.mask_owner_score)
    are pasted and refined: each kept detection's mask, box and maskness are those of all detections processed."""
    scores = outputs["scores"]
    needed = scores >= min_score
    if post.mask_owner_score is not None:
        needed |= scores >= post.mask_owner_score
    detected = paste(select(outputs, needed))
    radius = refine_radius(post.mask_refine_radius, tuple(outputs["image"].shape[-2:]), detector_size)
    detections = threshold_masks(detected, post.mask_threshold, radius, post.mask_refine_eps, post.mask_owner_score)
    wanted = detections["scores"] >= min_score
    return {name: value[wanted] for name, value in detections.items()}


def to_coco_results(image_id: int, detections: dict, label_to_category: dict[int, int],
                    mask_score: str) -> list[dict]:
    """COCO result records (bbox xywh, RLE segmentation, score) for one image's detections. Each also holds
    "mask_score", which ranks its mask in the mask AP: the box score, or with mask_score "maskness" the box score
    times detections["maskness"]."""
    results = []
    mask_factors = detections["maskness"] if mask_score == "maskness" else np.ones(len(detections["scores"]))
    for box, score, label, mask, factor in zip(detections["boxes"], detections["scores"], detections["labels"],
                                               detections["masks"], mask_factors):
        if int(label) not in label_to_category:
            continue
        x0, y0, x1, y1 = (float(v) for v in box)
        results.append({"image_id": int(image_id), "category_id": label_to_category[int(label)],
                        "bbox": [x0, y0, x1 - x0, y1 - y0], "score": float(score),
                        "mask_score": float(score * factor), "segmentation": mask_to_rle(mask)})
    return results
