"""Pinhole cameras: intrinsics, look-at poses (OpenCV, world-to-camera) and capture orbits."""
from __future__ import annotations

import numpy as np

WORLD_UP = np.array([0.0, 0.0, 1.0])


def intrinsics(width: int, height: int, hfov_deg: float, principal_offset=(0.0, 0.0)) -> np.ndarray:
    """K [3, 3] for a horizontal field of view; principal point at the image centre (+ offset in px).

    COLMAP convention: the top-left pixel's centre is (0.5, 0.5), so the centre is (width/2, height/2).
    """
    focal = 0.5 * width / np.tan(np.radians(hfov_deg) / 2)
    return np.array([[focal, 0, width / 2 + principal_offset[0]],
                     [0, focal, height / 2 + principal_offset[1]],
                     [0, 0, 1]], np.float64)


def look_at(eye, target, roll_deg: float = 0.0) -> np.ndarray:
    """World-to-camera viewmat [4, 4] (OpenCV axes) of a camera at `eye` looking at `target`, z up."""
    eye, target = np.asarray(eye, np.float64), np.asarray(target, np.float64)
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, WORLD_UP)
    if np.linalg.norm(right) < 1e-6:  # looking straight up or down
        right = np.array([1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    roll = np.radians(roll_deg)
    right, down = np.cos(roll) * right + np.sin(roll) * down, -np.sin(roll) * right + np.cos(roll) * down
    viewmat = np.eye(4)
    viewmat[:3, :3] = np.stack([right, down, forward])
    viewmat[:3, 3] = -viewmat[:3, :3] @ eye
    return viewmat


def camera_centre(viewmat: np.ndarray) -> np.ndarray:
    """Camera position [3] in the world of a world-to-camera viewmat [4, 4]."""
    return -viewmat[:3, :3].T @ viewmat[:3, 3]


def project(points: np.ndarray, K: np.ndarray, viewmat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points [N, 3] -> continuous pixel positions [N, 2] (COLMAP convention) and camera z [N]."""
    cam = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    pix = cam @ np.asarray(K).T
    return pix[:, :2] / pix[:, 2:3], cam[:, 2]


def orbit(num_frames: int, radius: float, target, elevations_deg=(20.0, 45.0), rng: np.random.Generator | None = None,
          jitter: float = 0.0) -> list[np.ndarray]:
    """Viewmats of a hand-held orbit: half the frames around `target` at each elevation, azimuth continuing.

    jitter: relative random perturbation of radius, height and aim (a hand-held camera), needs `rng`.
    """
    target = np.asarray(target, np.float64)
    per_ring = [num_frames // len(elevations_deg)] * len(elevations_deg)
    per_ring[-1] += num_frames - sum(per_ring)
    viewmats, azimuth0 = [], 0.0 if rng is None else rng.uniform(0, 2 * np.pi)
    for ring, (count, elevation) in enumerate(zip(per_ring, elevations_deg)):
        for k in range(count):
            azimuth = azimuth0 + 2 * np.pi * (ring + k / count)
            r = radius * (1 + (jitter * rng.uniform(-1, 1) if jitter else 0.0))
            el = np.radians(elevation + (jitter * 20 * rng.uniform(-1, 1) if jitter else 0.0))
            eye = target + r * np.array([np.cos(el) * np.cos(azimuth), np.cos(el) * np.sin(azimuth), np.sin(el)])
            aim = target + (radius * jitter * 0.3 * rng.uniform(-1, 1, 3) if jitter else 0.0)
            viewmats.append(look_at(eye, aim, roll_deg=(jitter * 30 * rng.uniform(-1, 1) if jitter else 0.0)))
    return viewmats
