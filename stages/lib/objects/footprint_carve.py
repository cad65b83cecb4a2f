"""The footprint carve (extract's halo step, after the haze test; issue 60): what lies outside the cut's visible
footprint in many capture views is not the object.

A trained scene can grow a solid, backdrop-coloured cloud joined to the object (the real_dog experiment's dog in 6 of
9 trainings: a sheet beside it, 26-53 % of the cut's alpha outside the hand-drawn boxes). Solid, it draws the
silhouette the haze test judges by (stages/lib/objects/silhouettes.py). What gives it away is that it changes
nothing: the scene rendered with and without the cut agrees where it lies, so in many views it falls outside the
cut's visible footprint, which a point of the object never does (a visual hull of the views).
"""
from __future__ import annotations

import logging

import numpy as np
from scipy import ndimage

from stages.lib.objects import pointcloud, support
from stages.lib.objects.cut_config import CutConfig
from stages.lib.objects.silhouettes import GaussianArrays, Intrinsics, pixels

log = logging.getLogger(__name__)
FOOTPRINT_ROUNDS = 3  # carve_outside_footprint carves at most this many times ...
MAX_CARVED_SHARE = 0.5  # ... and nothing when more of the cut than this lies outside its footprint


def outside_share(gaussians: GaussianArrays, kept: np.ndarray, background: np.ndarray, viewmats: np.ndarray,
                  intrinsics: Intrinsics, min_difference: float, min_outside: float) -> np.ndarray:
    """Per kept Gaussian (kept [N] bool, M of them): the share of the capture views seeing its centre in which the
    centre lies more than `min_outside` (world units at its depth) outside the kept set's visible footprint, [M] in
    [0, 1] (0 where no view sees it). The footprint in a view: where the kept and `background` Gaussians (background
    [N] bool) rendered together differ from the background alone by more than `min_difference` in some channel, its
    holes filled (a white chest on a pale backdrop changes little, yet lies inside the dog's outline).
    viewmats [C, 4, 4]; images of `intrinsics`."""
    behind, both = gaussians.subset(background), gaussians.subset(kept | background)
    centres = gaussians.means[kept]  # [M, 3]
    outside, seen = np.zeros(len(centres)), np.zeros(len(centres))  # [M], [M]
    for viewmat, K, (width, height) in zip(viewmats, intrinsics.Ks, intrinsics.sizes):
        index, u, v, depth = pixels(centres, viewmat, K, width, height)
        if len(index) == 0:
            continue
        with_kept, _ = both.render(viewmat, K, width, height)
        without, _ = behind.render(viewmat, K, width, height)
        footprint = ndimage.binary_fill_holes(np.abs(with_kept - without).max(axis=2) > min_difference)  # [H, W]
        distance = ndimage.distance_transform_edt(~footprint)[v, u] * depth / np.sqrt(K[0, 0] * K[1, 1])
        seen[index] += 1
        outside[index] += distance > min_outside
    return outside / np.maximum(seen, 1)


def beyond_footprint_views(gaussians: GaussianArrays, points: np.ndarray, across: np.ndarray, heights: np.ndarray,
                           keep: np.ndarray, viewmats: np.ndarray, intrinsics: Intrinsics, scale: float,
                           cfg: CutConfig) -> np.ndarray:
    """Mask [N] of kept Gaussians (keep [N]) that lie outside the kept set's visible footprint in more than
    cfg.max_outside_share of the capture views that see them (outside_share; the footprint is where the kept set
    changes the view by more than cfg.footprint_difference over the Gaussians farther than cfg.footprint_clearance
    from it, since the removed ones nearer, such as the object's own inner fill, would show the object without it;
    outside: farther than cfg.silhouette_distance). A point of the object lies inside its outline in every view; a
    backdrop-coloured cloud joined to it changes nothing where it lies, and falls outside in many. The object's base
    stays, left to the support checks (the floor beside it can hide it): over the footprint of the solid Gaussians
    inside (support.over_base), below cfg.base_band of their height. None when more than MAX_CARVED_SHARE of the cut
    lies outside: an object coloured like what is behind it. gaussians in model units; points [N, 3] normalised by
    `scale` model units, across [N, 2] and heights [N] their plane coordinates and heights; viewmats [C, 4, 4] and
    their intrinsics, rendered at cfg.silhouette_long_side."""
    outside = np.zeros(len(keep), dtype=bool)
    background = ~keep
    background[background] = pointcloud.nearest_distance(points[background], points[keep]) > cfg.footprint_clearance
    share = outside_share(gaussians, keep, background, viewmats, intrinsics.scaled(cfg.silhouette_long_side),
                          cfg.footprint_difference, cfg.silhouette_distance * scale)  # [M]
    kept, beyond = np.flatnonzero(keep), share > cfg.max_outside_share  # [M], [M]
    body = kept[~beyond & (gaussians.opacities[kept] >= cfg.height_opacity)]
    if len(body) == 0 or beyond.mean() > MAX_CARVED_SHARE:
        log.warning("extract: %.0f%% of the cut lies outside its visible footprint: the views cannot tell the object "
                    "from what is behind it (its colours?); nothing carved", 100 * beyond.mean())
        return outside
    base = support.over_base(across, heights, kept, body) & (heights[kept] < cfg.base_band * heights[body].max())
    outside[kept[beyond & ~base]] = True
    return outside


def carve_outside_footprint(gaussians: GaussianArrays, points: np.ndarray, across: np.ndarray, heights: np.ndarray,
                            keep: np.ndarray, viewmats: np.ndarray, intrinsics: Intrinsics, scale: float,
                            cfg: CutConfig) -> np.ndarray:
    """Mask [N] of the kept Gaussians (keep [N]) that beyond_footprint_views carves (its arguments), up to
    FOOTPRINT_ROUNDS times, since a cloud's own footprint can shield part of it; a round finding fewer than
    cfg.dbscan_min_points carves none of them and ends (a cloud is at least a cluster). Every capture view judges:
    a cloud lies beside the object in some of them only (30 of the real dog's 76, evenly spread, missed 3 of its 6
    clouds)."""
    carved = np.zeros(len(keep), dtype=bool)
    for _ in range(FOOTPRINT_ROUNDS if cfg.max_outside_share < 1.0 else 0):  # 1: the carve is off
        found = beyond_footprint_views(gaussians, points, across, heights, keep & ~carved, viewmats, intrinsics,
                                       scale, cfg)
        if found.sum() < cfg.dbscan_min_points:
            break
        carved |= found
    return carved
