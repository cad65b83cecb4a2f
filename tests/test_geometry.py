"""Camera geometry (stages/lib/geometry.py): centres, look-at point, intrinsics from a field of view, look-at poses."""
from __future__ import annotations

import math

import numpy as np
import torch

from stages.lib.geometry import camera_centres, fov_intrinsics, image_ups, look_at_point, look_at_viewmat


def orbit(count: int, radius: float, height: float) -> np.ndarray:
    """Viewmats [count, 4, 4] on a circle of `radius` at z = `height`, looking at the origin."""
    angles = 2 * np.pi * np.arange(count) / count
    return np.stack([look_at_viewmat([radius * np.cos(a), radius * np.sin(a), height], np.zeros(3)) for a in angles])


def test_camera_centres_and_look_at_point():
    viewmats = orbit(12, radius=3.0, height=1.0)
    centres = camera_centres(viewmats)
    np.testing.assert_allclose(np.linalg.norm(centres[:, :2], axis=1), np.full(12, 3.0))
    np.testing.assert_allclose(look_at_point(viewmats), np.zeros(3), atol=1e-5)
    # the same function on torch tensors (the rasterizer's SH directions)
    torch.testing.assert_close(camera_centres(torch.as_tensor(viewmats)), torch.as_tensor(centres))
    # Parallel optical axes (a forward-facing rig) have no look-at point.
    sideways = np.repeat(viewmats[:1], 4, axis=0)
    sideways[:, 0, 3] += np.arange(4.0)
    assert look_at_point(sideways) is None
    # Cameras looking away from the point their axes meet (an outward-facing rig) have none either.
    outward = orbit(12, radius=3.0, height=1.0)
    outward[:, [0, 2]] *= -1  # turn every camera half around its image's vertical axis
    assert look_at_point(outward) is None


def test_look_at_viewmat_and_fov_intrinsics():
    eye, target = np.array([1.0, -2.0, 1.5]), np.array([0.0, 0.5, 0.2])
    viewmat = look_at_viewmat(eye, target, roll_deg=10.0)
    np.testing.assert_allclose(viewmat[:3, :3] @ viewmat[:3, :3].T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(camera_centres(viewmat), eye, atol=1e-12)
    target_cam = viewmat[:3, :3] @ target + viewmat[:3, 3]
    np.testing.assert_allclose(target_cam[:2], 0.0, atol=1e-12)  # on the optical axis, in front
    assert target_cam[2] > 0
    assert math.degrees(math.acos(image_ups(look_at_viewmat(eye, target)) @ [0, 0, 1])) < 90
    K = fov_intrinsics(640, 480)
    assert K[0, 0] == K[1, 1] == 320 / math.tan(math.radians(27.5)) and (K[0, 2], K[1, 2]) == (320, 240)
    assert fov_intrinsics(100, 50, 90.0, (2.0, -1.0))[:2, 2].tolist() == [52.0, 24.0]
