"""Render one posed object into the window of the background image it covers.

The camera frame of the background is the world frame (viewmat = identity); the window is rendered
with the background intrinsics shifted by the window origin, so a window pixel equals the image
pixel it lies on. The opacity map is the rasterizer's accumulated alpha, which is exactly the
paper's second render "with the splat colour set to white" (tests check this equality), so one
pass gives both.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from stages.composition.placement import NEAR_DEPTH, Pose
from stages.gaussians.model import Gaussians
from stages.gaussians.rasterize import render

ALPHA_EPS = 1e-4  # below this accumulated alpha a pixel holds no object (expected depth undefined)


@dataclass
class ObjectLayer:
    """An object rendered in its window of the image (window pixel (r, c) = image (y0 + r, x0 + c))."""

    x0: int
    y0: int
    rgb: np.ndarray  # [h, w, 3] float32 premultiplied colour (colour * alpha)
    alpha: np.ndarray  # [h, w] float32 accumulated opacity
    depth: np.ndarray  # [h, w] float32 expected camera z, +inf where alpha < ALPHA_EPS
    full_alpha_sum: float  # alpha mass of the whole object, also the part outside the image

    @property
    def shape(self) -> tuple[int, int]:
        """Window size (h, w)."""
        return self.alpha.shape


def object_window(g: Gaussians, K: np.ndarray) -> tuple[int, int, int, int] | None:
    """Pixel box (x0, y0, x1, y1), x1/y1 exclusive, surely covering every pixel the object can touch.

    g: Gaussians in the camera frame. A cheap conservative bound (no covariance projection): each
    Gaussian reaches sqrt(2 ln(255 o)) standard deviations (where its alpha drops below 1/255),
    the longest axis is used for every direction, the perspective stretch off the optical axis is
    bounded by sqrt(1 + (x/z)^2 + (y/z)^2), and the rasterizer's 0.3 px^2 low-pass adds < 3 px.
    The box is not clipped to the image. None when no Gaussian can be seen in front of the camera.
    """
    with torch.no_grad():
        means = g.means.double()
        reach = torch.sqrt(torch.clamp(2.0 * torch.log(g.opacities.double() * 255.0), min=0.0))  # [N] sigmas
        radius = reach * g.scales.double().max(dim=1).values  # [N] world units
        x, y, z = means.unbind(-1)
        visible = (z > NEAR_DEPTH) & (reach > 0)
        if not bool(visible.any()):
            return None
        x, y, z, radius = x[visible], y[visible], z[visible], radius[visible]
        stretch = torch.sqrt(1.0 + (x / z) ** 2 + (y / z) ** 2)
        fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
        u, v = fx * x / z + cx, fy * y / z + cy
        ru, rv = fx * radius / z * stretch + 3.0, fy * radius / z * stretch + 3.0
        box = [float((u - ru).min()), float((v - rv).min()), float((u + ru).max()), float((v + rv).max())]
    return math.floor(box[0]), math.floor(box[1]), math.ceil(box[2]), math.ceil(box[3])


def posed_gaussians(g: Gaussians, pose: Pose) -> Gaussians:
    """The object model moved into the camera frame by `pose`."""
    return g.transformed(torch.as_tensor(pose.rotation), torch.as_tensor(pose.translation, dtype=torch.float32),
                         pose.scale)


def render_window(g: Gaussians, K: np.ndarray, window: tuple[int, int, int, int],
                  sh_view_dir: np.ndarray | None, backend: str = "auto") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render camera-frame Gaussians in an image window with the image intrinsics K [3, 3].

    Returns premultiplied rgb [h, w, 3], alpha [h, w] and expected depth [h, w] (+inf where empty).
    sh_view_dir [3] (camera frame) evaluates view-dependent colour from that one direction.
    """
    x0, y0, x1, y1 = window
    K_window = torch.as_tensor(K, dtype=torch.float32).clone()
    K_window[0, 2] -= x0
    K_window[1, 2] -= y0
    view_dir = None if sh_view_dir is None else torch.as_tensor(sh_view_dir, dtype=torch.float32)
    with torch.no_grad():
        out = render(g, torch.eye(4), K_window, x1 - x0, y1 - y0, sh_view_dir=view_dir, backend=backend)
    alpha = out.alpha.numpy().astype(np.float32)
    depth = np.where(alpha >= ALPHA_EPS, out.depth.numpy() / np.maximum(alpha, ALPHA_EPS), np.inf)
    return out.rgb.numpy().astype(np.float32), alpha, depth.astype(np.float32)


def render_object_layer(g: Gaussians, pose: Pose, K: np.ndarray, width: int, height: int,
                        sh_view_dir: np.ndarray | None, max_window_pixels: int,
                        backend: str = "auto") -> ObjectLayer | None:
    """Pose the object, render the window it covers and crop it to the image.

    None when the object is behind/too near the camera, outside the image, or its window is larger
    than `max_window_pixels` (a placement far too close to the camera).
    """
    posed = posed_gaussians(g, pose)
    if float(posed.means[:, 2].min()) < NEAR_DEPTH:
        return None
    window = object_window(posed, K)
    if window is None:
        return None
    x0, y0, x1, y1 = window
    if (x1 - x0) * (y1 - y0) > max_window_pixels or x1 <= 0 or y1 <= 0 or x0 >= width or y0 >= height:
        return None
    rgb, alpha, depth = render_window(posed, K, window, sh_view_dir, backend)
    full_alpha_sum = float(alpha.sum())
    cx0, cy0 = max(x0, 0), max(y0, 0)
    cx1, cy1 = min(x1, width), min(y1, height)
    crop = (slice(cy0 - y0, cy1 - y0), slice(cx0 - x0, cx1 - x0))
    return ObjectLayer(cx0, cy0, rgb[crop], alpha[crop], depth[crop], full_alpha_sum)
