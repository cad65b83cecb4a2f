"""Evaluation helpers of the benchmarks (and the tests): similarity alignment, camera pose errors,
precision and recall of a kept mask, angles between directions.

Cameras follow stages/lib/geometry.py (OpenCV axes, world-to-camera 4x4 viewmats).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from stages.lib.geometry import camera_centres
from stages.records.sfm import SfmRecord


def umeyama_similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R [3,3], t [3]) minimising |dst - (s R src + t)|^2 (Umeyama 1991).

    src, dst: [N, 3] corresponding points, N >= 3.
    """
    mean_src, mean_dst = src.mean(0), dst.mean(0)
    src_c, dst_c = src - mean_src, dst - mean_dst
    covariance = dst_c.T @ src_c / len(src)                         # [3, 3]
    u, singular, vt = np.linalg.svd(covariance)
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2, 2] = -1
    rotation = u @ sign @ vt
    variance_src = (src_c ** 2).sum() / len(src)
    scale = float(np.trace(np.diag(singular) @ sign) / variance_src)
    translation = mean_dst - scale * rotation @ mean_src
    return scale, rotation, translation


def pose_errors(est_viewmats: np.ndarray, gt_viewmats: np.ndarray) -> dict:
    """Compare estimated and true world-to-camera poses after a similarity alignment of the centres.

    est_viewmats, gt_viewmats: [N, 4, 4] corresponding world-to-camera matrices.
    Returns rotation errors (deg) and camera-position errors as % of the true orbit radius
    (mean distance of the true centres from their centroid).
    """
    est_centres, gt_centres = camera_centres(est_viewmats), camera_centres(gt_viewmats)  # [N, 3]
    scale, rotation, translation = umeyama_similarity(est_centres, gt_centres)
    aligned = scale * est_centres @ rotation.T + translation        # [N, 3]
    radius = np.linalg.norm(gt_centres - gt_centres.mean(0), axis=1).mean()
    position_pct = 100.0 * np.linalg.norm(aligned - gt_centres, axis=1) / radius
    # est cam-from-world in the ground-truth world frame: R_est @ R_align^T
    relative = np.einsum("nij,kj,nlk->nil", est_viewmats[:, :3, :3], rotation, gt_viewmats[:, :3, :3])
    cos = np.clip((np.trace(relative, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    rotation_deg = np.degrees(np.arccos(cos))
    return {"rotation_deg_mean": float(rotation_deg.mean()), "rotation_deg_max": float(rotation_deg.max()),
            "position_pct_mean": float(position_pct.mean()), "position_pct_max": float(position_pct.max()),
            "scale": scale}


def registered_viewmats(sfm_dir: Path) -> dict[str, np.ndarray]:
    """World-to-camera matrices [4, 4] of the registered images of an sfm output folder, by name."""
    return {frame.name: frame.viewmat for frame in SfmRecord.read(sfm_dir).scene().frames}


def score(keep: np.ndarray, is_object: np.ndarray) -> dict:
    """Precision and recall of the kept mask [N] against the true object mask [N]."""
    true_positive = int((keep & is_object).sum())
    return {"precision": true_positive / max(1, int(keep.sum())), "recall": true_positive / max(1, int(is_object.sum())),
            "kept": int(keep.sum()), "object": int(is_object.sum()), "total": len(keep)}


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle in degrees between two directions [3]."""
    return float(np.rad2deg(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))
