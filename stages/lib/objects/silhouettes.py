"""Background haze beside an object, found at the capture cameras (extract's halo step).

A trained scene can hold a haze of large, semi-transparent Gaussians beside the object that stands for the
background behind it (the real plush dog at 320 px: a white cloud beside its head that is the wall): in 3D it
touches the object, so the clusters keep it, yet rendered alone it is a cloud beside the object. Two things
give it away in the capture views. It lies outside the silhouette of the object's solid body, and there it
has the colour of the background behind it (the scene without the object), so it adds nothing the background
does not already show. A thin leaf or a fringe of fur outside the solid silhouette has its own colour and stays.

A solid cloud joined to the object draws the silhouette itself; stages/lib/objects/footprint_carve.py finds it.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import torch
from scipy import ndimage

from stages.lib.gaussians.rasterize import rasterize
from stages.records.cameras import CamerasRecord

ALPHA_THRESHOLD = 0.5  # the silhouette: rendered alpha above this


@dataclass
class Intrinsics:
    """The capture cameras' intrinsics and image sizes in pixels (their poses are viewmats [C, 4, 4])."""

    Ks: np.ndarray  # [C, 3, 3]
    sizes: np.ndarray  # [C, 2] (width, height)

    @classmethod
    def of_cameras(cls, cameras: CamerasRecord) -> "Intrinsics":
        """The intrinsics and image sizes of a splat folder's cameras (cameras.json), in its frames' order."""
        return cls(np.stack([frame.K for frame in cameras.frames]),
                   np.array([[frame.width, frame.height] for frame in cameras.frames]))

    def scaled(self, long_side: int) -> "Intrinsics":
        """The same cameras with images of `long_side` pixels on their longer side."""
        factors = long_side / self.sizes.max(axis=1)  # [C]
        Ks = np.array(self.Ks, dtype=np.float64)
        Ks[:, :2] *= factors[:, None, None]
        return Intrinsics(Ks, np.maximum(1, np.round(self.sizes * factors[:, None])).astype(np.int64))


@dataclass
class GaussianArrays:
    """Gaussians as arrays, enough to render them with fixed colours."""

    means: np.ndarray  # [N, 3]
    quats: np.ndarray  # [N, 4] (w, x, y, z)
    scales: np.ndarray  # [N, 3] linear
    opacities: np.ndarray  # [N] in [0, 1]
    colors: np.ndarray  # [N, 3] in [0, 1]

    def subset(self, mask: np.ndarray) -> "GaussianArrays":
        """The Gaussians where mask [N] (bool or indices) selects."""
        return GaussianArrays(self.means[mask], self.quats[mask], self.scales[mask], self.opacities[mask],
                              self.colors[mask])

    @cached_property
    def _tensors(self) -> tuple[torch.Tensor, ...]:
        """means, quats, scales, opacities (below 1) and colours as float32 tensors, made once for every view."""
        return tuple(_tensor(array) for array in (self.means, self.quats, self.scales,
                                                  np.minimum(self.opacities, 0.999), self.colors))

    def render(self, viewmat: np.ndarray, K: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """Colour [H, W, 3] (over black) and alpha [H, W] at one camera (viewmat [4, 4], K [3, 3])."""
        with torch.no_grad():
            out = rasterize(*self._tensors, _tensor(viewmat), _tensor(K), int(width), int(height))
        return out.rgb.numpy(), out.alpha.numpy()


def _tensor(array: np.ndarray) -> torch.Tensor:
    """A contiguous float32 CPU tensor of the array."""
    return torch.as_tensor(np.ascontiguousarray(array), dtype=torch.float32)


def pixels(points: np.ndarray, viewmat: np.ndarray, K: np.ndarray, width: int, height: int
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The points [N, 3] (world) that one camera sees, in front of it and inside its image: their indices [M],
    pixel columns [M] and rows [M], and depths [M]."""
    camera = points @ viewmat[:3, :3].T + viewmat[:3, 3]  # [N, 3]
    depth = camera[:, 2]
    seen = depth > 1e-9
    uv = camera[seen, :2] / depth[seen, None] @ K[:2, :2].T + K[:2, 2]  # [M, 2]
    in_image = (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)
    index = np.flatnonzero(seen)[in_image]
    return index, uv[in_image, 0].astype(np.int64), uv[in_image, 1].astype(np.int64), depth[index]


@dataclass
class HazeScores:
    """Per point: how far outside the body's silhouette it gets, and how close to the background its colour is."""

    outside: np.ndarray  # [N] largest distance outside the silhouette over the views (world units at the point's
    #                      depth); 0 inside in every view
    colour_difference: np.ndarray  # [N] over the views where it lies beyond `min_outside`: the mean of its largest
    #                                channel difference to the background's colour at its pixel; nan without such views


def haze_scores(points: np.ndarray, colors: np.ndarray, body: GaussianArrays, background: GaussianArrays,
                viewmats: np.ndarray, intrinsics: Intrinsics, min_outside: float) -> HazeScores:
    """Score points [N, 3] with colours [N, 3] in [0, 1] against the silhouette (alpha > ALPHA_THRESHOLD) of the
    `body` Gaussians and the colour of the `background` Gaussians rendered at the cameras (viewmats [C, 4, 4]
    world-to-camera; `min_outside` in world units). A view counts for a point only when the point lies in
    front of the camera and inside its image."""
    farthest = np.zeros(len(points))  # [N]
    difference_sum, difference_views = np.zeros(len(points)), np.zeros(len(points))  # [N], [N]
    for viewmat, K, (width, height) in zip(viewmats, intrinsics.Ks, intrinsics.sizes):
        _, body_alpha = body.render(viewmat, K, width, height)
        inside = body_alpha > ALPHA_THRESHOLD
        if not inside.any():
            continue
        index, u, v, depth = pixels(points, viewmat, K, width, height)
        pixels_out = ndimage.distance_transform_edt(~inside)  # [H, W] pixels to the silhouette
        distance = pixels_out[v, u] * depth / np.sqrt(K[0, 0] * K[1, 1])  # world units at the depth
        farthest[index] = np.maximum(farthest[index], distance)
        beyond = distance > min_outside
        if beyond.any():
            background_rgb, _ = background.render(viewmat, K, width, height)
            index, u, v = index[beyond], u[beyond], v[beyond]
            difference_sum[index] += np.abs(colors[index] - background_rgb[v, u]).max(axis=1)
            difference_views[index] += 1
    with np.errstate(invalid="ignore", divide="ignore"):
        return HazeScores(farthest, np.where(difference_views > 0, difference_sum / difference_views, np.nan))
