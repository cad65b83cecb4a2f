"""Capture orbits and projection of world points (cameras as in stages/lib/geometry.py)."""
from __future__ import annotations

import numpy as np

from stages.lib.geometry import look_at_viewmat


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
            viewmats.append(look_at_viewmat(eye, aim, roll_deg=(jitter * 30 * rng.uniform(-1, 1) if jitter else 0.0)))
    return viewmats
