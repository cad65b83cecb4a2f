"""Planes found on degraded depth against the planes of the true depth, per photo and over photos: which true
planes are found again, how far their normals turn, how wrong an object's size at a placement point comes out
(the scores of benchmarks/mono_depth.py, whose docstring defines them)."""
from __future__ import annotations

import math

import cv2
import numpy as np

MIN_PLANE_FRACTION = 0.005  # true planes and support surfaces smaller than this share of the photo are not counted
UP_WRONG_DEG = 15.0  # the planes search's up axis this far from the true depth's: horizontal surfaces are missed


def plane_pixels(result: dict) -> list[np.ndarray]:
    """Support masks [H, W] bool of the planes of a search result."""
    return [result["labels"] == index for index in range(len(result["planes"]))]


def overlapping(mask: np.ndarray, others: list[np.ndarray]) -> int | None:
    """Index of the mask of `others` overlapping `mask` most, if the overlap is half the smaller of the two."""
    best, best_overlap = None, 0
    for index, other in enumerate(others):
        overlap = int((mask & other).sum())
        if overlap >= 0.5 * min(mask.sum(), other.sum()) and overlap > best_overlap:
            best, best_overlap = index, overlap
    return best


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(min(1.0, abs(float(np.dot(a, b))))))


def score(depth: np.ndarray, support: np.ndarray | None, truth: dict, found: dict, recovered: np.ndarray) -> dict:
    """One photo's figures (benchmarks/mono_depth.py's docstring) of the planes `found` on a degraded depth, whose
    bg_depth map is `recovered` [H, W], against `truth`, the planes of its true depth [H, W]; support [H, W] bool:
    its true support surfaces (None for a real photo). Search results as find_placement_planes gives them."""
    minimum = MIN_PLANE_FRACTION * depth.size
    true_masks = [m for m in plane_pixels(truth) if m.sum() >= minimum]
    true_normals = [p["normal"] for p, m in zip(truth["planes"], plane_pixels(truth)) if m.sum() >= minimum]
    found_masks = plane_pixels(found)
    row = {"true_planes": len(true_masks), "found_planes": len(found["planes"]), "matched": 0, "normal_deg": [],
           "size": [], "size_true_scale": [], "on_support": None, "support_surfaces": 0, "support_found": 0,
           "up_error_deg": angle_deg(truth["up"], found["up"]) if true_masks else None}
    for mask, normal in zip(true_masks, true_normals):
        match = overlapping(mask, found_masks)
        if match is not None:
            row["matched"] += 1
            row["normal_deg"].append(angle_deg(normal, found["planes"][match]["normal"]))
    valid = (depth > 0) & (recovered > 0)
    true_scale = float(np.median(depth[valid] / recovered[valid])) if valid.any() else 1.0
    pixels = [np.floor(p["pixels"]).astype(int) for p in found["planes"]]
    for plane, uv in zip(found["planes"], pixels):
        z_true = depth[uv[:, 1], uv[:, 0]]
        keep = z_true > 0
        z_point = plane["points"][keep, 2]
        row["size"] += list(np.abs(z_true[keep] / z_point - 1))
        row["size_true_scale"] += list(np.abs(z_true[keep] / (true_scale * z_point) - 1))
    if support is not None:
        labels = cv2.connectedComponents(support.astype(np.uint8), connectivity=4)[1]
        surfaces = [labels == i for i in range(1, labels.max() + 1) if (labels == i).sum() >= minimum]
        row["support_surfaces"] = len(surfaces)
        row["support_found"] = sum(overlapping(s, found_masks) is not None for s in surfaces)
        all_uv = np.concatenate(pixels) if pixels else np.zeros((0, 2), int)
        row["on_support"] = float(support[all_uv[:, 1], all_uv[:, 0]].mean()) if len(all_uv) else None
    return row


def summarise(rows: list[dict]) -> dict:
    """The level's figures over its photos."""
    true_planes = sum(r["true_planes"] for r in rows)
    surfaces = sum(r["support_surfaces"] for r in rows)
    normals = [a for r in rows for a in r["normal_deg"]]
    sizes = [s for r in rows for s in r["size"]]
    sizes_true = [s for r in rows for s in r["size_true_scale"]]
    supports = [r["on_support"] for r in rows if r["on_support"] is not None]
    return {
        "photos": len(rows), "true_planes": true_planes,
        "recall": sum(r["matched"] for r in rows) / true_planes if true_planes else None,
        "support_recall": sum(r["support_found"] for r in rows) / surfaces if surfaces else None,
        "normal_deg_median": float(np.median(normals)) if normals else None,
        "normal_deg_p90": float(np.percentile(normals, 90)) if normals else None,
        "size_median": float(np.median(sizes)) if sizes else None,
        "size_true_scale_median": float(np.median(sizes_true)) if sizes_true else None,
        "on_support": float(np.mean(supports)) if supports else None,
        "false_planes": sum(r["found_planes"] for r in rows if r["true_planes"] == 0),
        "up_wrong": sum(r["up_error_deg"] is not None and r["up_error_deg"] > UP_WRONG_DEG for r in rows),
        "photos_with_planes": sum(r["true_planes"] > 0 for r in rows),
        "abs_rel": float(np.mean([r["abs_rel"] for r in rows])), "delta1": float(np.mean([r["delta1"] for r in rows])),
        "shift_error": (float(np.median([r["shift_error"] for r in rows])) if "shift_error" in rows[0] else None),
        "scale_ratio_median": float(np.median([r["scale_ratio"] for r in rows])),
        "scale_ratio_range": [float(np.min([r["scale_ratio"] for r in rows])),
                              float(np.max([r["scale_ratio"] for r in rows]))],
    }


def per_photo(row: dict) -> dict:
    """A photo's row as kept in mono_depth.json: its counts and the medians of its per-plane and per-point lists."""
    lists = ("normal_deg", "size", "size_true_scale")
    kept = {key: value for key, value in row.items() if key not in lists}
    kept.update({f"{key}_median": float(np.median(row[key])) if row[key] else None for key in lists})
    return kept
