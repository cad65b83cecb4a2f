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
from stages.gaussians.projection import project_gaussians
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


def object_window(g: Gaussians, K: np.ndarray, width: int, height: int,
                  reach: float = 1.0) -> tuple[int, int, int, int] | None:
    """Pixel box (x0, y0, x1, y1), x1/y1 exclusive, covering every pixel the object can touch.

    g: Gaussians in the camera frame. The box is not clipped to the image: it is searched in a
    virtual image extended by `reach` image sizes on every side. None when nothing is visible there.
    """
    pad_x, pad_y = int(math.ceil(reach * width)), int(math.ceil(reach * height))
    K_virtual = torch.as_tensor(K, dtype=torch.float32).clone()
    K_virtual[0, 2] += pad_x
    K_virtual[1, 2] += pad_y
    with torch.no_grad():
        proj = project_gaussians(g.means, g.quats, g.scales, g.opacities, torch.eye(4), K_virtual,
                                 width + 2 * pad_x, height + 2 * pad_y)
    visible = proj.radii > 0
    if not bool(visible.any()):
        return None
    centres, extents = proj.means2d[visible], proj.extents[visible]  # [M, 2]
    low = torch.floor((centres - extents).min(dim=0).values).to(torch.int64)
    high = torch.ceil((centres + extents).max(dim=0).values).to(torch.int64)
    return int(low[0]) - pad_x, int(low[1]) - pad_y, int(high[0]) - pad_x, int(high[1]) - pad_y


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
    window = object_window(posed, K, width, height)
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
