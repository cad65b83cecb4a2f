"""Render one posed object into the window of the background image it covers.

The camera frame of the background is the world frame (viewmat = identity); the window is rendered
with the background intrinsics shifted by the window origin, so a window pixel equals the image
pixel it lies on. The opacity map is the rasterizer's accumulated alpha, which is exactly the
paper's second render "with the splat colour set to white" (tests check this equality), so one
pass gives both.

A small object is rendered at a multiple of the resolution and reduced by area (`supersample`): one sample per
pixel with the rasterizer's 0.3 px^2 low-pass (3DGS's anti-aliasing) fattens thin parts of a small render, so
its alpha > 0.5 mask would be wider than the object's coverage (on the sample's plant at 60 px, mask IoU with the
true coverage 0.72, area 1.4x; rendered at 4x and reduced: 0.93, 1.02; benchmarks/results/mask_ceiling.md).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from stages.lib.composition.placement import NEAR_DEPTH, Pose
from stages.lib.gaussians.model import Gaussians
from stages.lib.gaussians.rasterize import render

ALPHA_EPS = 1e-4  # below this accumulated alpha a pixel holds no object (expected depth undefined)
MAX_SUPERSAMPLE = 4


@dataclass
class ObjectLayer:
    """An object rendered in its window of the image (window pixel (r, c) = image (y0 + r, x0 + c))."""

    x0: int
    y0: int
    rgb: np.ndarray  # [h, w, 3] float32 premultiplied colour (colour * alpha)
    alpha: np.ndarray  # [h, w] float32 accumulated opacity
    depth: np.ndarray  # [h, w] float32 expected camera z, +inf where alpha < ALPHA_EPS
    full_alpha_sum: float  # alpha mass of the whole object, also the part outside the image
    pose: Pose  # where it was rendered
    unoccluded_alpha: np.ndarray  # [h, w] float32 the object's own opacity before any occlusion (amodal)

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


def supersample_factor(window: tuple[int, int, int, int], min_side: int) -> int:
    """How many samples per pixel and axis a window gets: enough for its shorter side to reach `min_side`
    pixels, at most MAX_SUPERSAMPLE (1 for a window already that large, or min_side 0)."""
    side = max(1, min(window[2] - window[0], window[3] - window[1]))
    return int(min(MAX_SUPERSAMPLE, max(1, math.ceil(min_side / side))))


def render_window(g: Gaussians, K: np.ndarray, window: tuple[int, int, int, int], sh_view_dir: np.ndarray | None,
                  backend: str = "auto", supersample: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render camera-frame Gaussians in an image window with the image intrinsics K [3, 3].

    Returns premultiplied rgb [h, w, 3], alpha [h, w] and expected depth [h, w] (+inf where empty), rendered at
    `supersample` x the resolution and reduced by area (the mean of the samples in each pixel).
    sh_view_dir [3] (camera frame) evaluates view-dependent colour from that one direction.
    """
    x0, y0, x1, y1 = window
    s = supersample
    K_window = torch.as_tensor(K, dtype=torch.float32).clone()
    K_window[0, 2] -= x0
    K_window[1, 2] -= y0
    K_window[:2] *= s  # pixel centres at (u + 0.5) / s: the same continuous frame, s times finer
    view_dir = None if sh_view_dir is None else torch.as_tensor(sh_view_dir, dtype=torch.float32)
    with torch.no_grad():
        out = render(g, torch.eye(4), K_window, (x1 - x0) * s, (y1 - y0) * s, sh_view_dir=view_dir, backend=backend)
        layers = torch.cat([out.rgb, out.alpha[..., None], out.depth[..., None]], dim=-1)  # [h s, w s, 5]
        if s > 1:  # each pixel: the mean of its s x s samples (premultiplied colour and alpha-weighted depth)
            layers = layers.reshape(y1 - y0, s, x1 - x0, s, 5).mean(dim=(1, 3))
    layers = layers.numpy().astype(np.float32)
    alpha = layers[..., 3]
    depth = np.where(alpha >= ALPHA_EPS, layers[..., 4] / np.maximum(alpha, ALPHA_EPS), np.inf)
    return layers[..., :3], alpha, depth.astype(np.float32)


def render_object_layer(g: Gaussians, pose: Pose, K: np.ndarray, width: int, height: int,
                        sh_view_dir: np.ndarray | None, max_window_pixels: int,
                        backend: str = "auto", supersample_min_side: int = 0) -> ObjectLayer | None:
    """Pose the object, render the window it covers and crop it to the image; a window shorter than
    `supersample_min_side` pixels is rendered finer and reduced (supersample_factor; 0: never).

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
    rgb, alpha, depth = render_window(posed, K, window, sh_view_dir, backend,
                                      supersample_factor(window, supersample_min_side))
    full_alpha_sum = float(alpha.sum())
    cx0, cy0 = max(x0, 0), max(y0, 0)
    cx1, cy1 = min(x1, width), min(y1, height)
    crop = (slice(cy0 - y0, cy1 - y0), slice(cx0 - x0, cx1 - x0))
    return ObjectLayer(cx0, cy0, rgb[crop], alpha[crop], depth[crop], full_alpha_sum, pose, alpha[crop])
