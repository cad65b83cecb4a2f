"""A depth map's surfaces pixel by pixel, for the planes search (stages/lib/planes/search.py): normals of the point
map and how much they scatter, smoothing of noisy (estimated) depth, each pixel's footprint, height steps, the
connected horizontal regions that are candidate planes, and the member pixels each candidate grows to.

Point maps are [H, W, 3] camera-frame points of a depth grid (0 / invalid where the depth is missing).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from stages.lib.planes.search_config import PlaneSearchConfig


@dataclass
class Region:
    """A candidate placement plane: connected, roughly horizontal pixels of the grid."""

    normal: np.ndarray        # [3] camera-facing
    center: np.ndarray        # [3]
    mask: np.ndarray          # [H, W] bool, its pixels
    area: float               # sum of its pixel footprints (depth units squared)


def masked_blur(values: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian (sigma px) average [H, W(, C)] of values [H, W] or [H, W, C] over the pixels of mask [H, W] bool
    only (normalised convolution), so it also reaches a little beyond them; 0 where no mask pixel is near."""
    weight = cv2.GaussianBlur(mask.astype(np.float32), (0, 0), sigma)
    if values.ndim == 3:
        mask, weight = mask[..., None], weight[..., None]
    total = cv2.GaussianBlur(np.where(mask, values, 0).astype(np.float32), (0, 0), sigma)
    return np.where(weight > 1e-3, total / np.maximum(weight, 1e-3), 0.0)


def normal_noise_deg(normals: np.ndarray) -> float:
    """Median angle (degrees) between pixel normals [H, W, 3] (0 where undefined) and their average over a
    Gaussian of 2 pixels: how much the local normals scatter."""
    mean = cv2.GaussianBlur(normals, (0, 0), 2.0)
    mean /= np.maximum(np.linalg.norm(mean, axis=-1, keepdims=True), 1e-9)
    defined = np.any(normals != 0, axis=-1)
    if not defined.any():
        return 0.0
    return float(np.median(np.degrees(np.arccos(np.clip(np.sum(normals * mean, axis=-1)[defined], -1.0, 1.0)))))


def denoise_depth(depth: np.ndarray, cfg: PlaneSearchConfig) -> np.ndarray:
    """Depth [H, W] (0 = missing) smoothed: a bilateral filter of log depth, over a Gaussian of
    denoise_sigma_rel of the width, that does not average across steps of more than about
    denoise_edge_rel of the depth (a table's edge over the floor behind it)."""
    valid = depth > 0
    log_depth = np.log(np.where(valid, depth, 1.0)).astype(np.float32)
    sigma = max(cfg.denoise_sigma_rel * depth.shape[1], 0.5)
    filled = np.where(valid, log_depth, masked_blur(log_depth, valid, sigma)).astype(np.float32)
    smoothed = cv2.bilateralFilter(filled, 0, cfg.denoise_edge_rel, sigma)
    return np.where(valid, np.exp(smoothed), 0.0).astype(np.float32)


def pixel_normals(points: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Unit surface normals [H, W, 3] of a point map [H, W, 3] (5x5 Sobel); 0 where undefined."""
    d_du = np.stack([cv2.Sobel(points[..., c], cv2.CV_32F, 1, 0, ksize=5) for c in range(3)], -1)
    d_dv = np.stack([cv2.Sobel(points[..., c], cv2.CV_32F, 0, 1, ksize=5) for c in range(3)], -1)
    normals = np.cross(d_du, d_dv)                                        # [H, W, 3]
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    inside = cv2.erode(valid.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    return np.where(inside[..., None] & (length > 0), normals / np.maximum(length, 1e-12), 0.0)


def facing_normals(points: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Unit normals [H, W, 3] of a point map [H, W, 3], turned to face the camera; 0 where undefined."""
    return -pixel_normals(points, valid)     # the Sobel cross product points away from the camera


def pixel_footprints(points: np.ndarray, facing: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Surface area [H, W] each pixel of a point map [H, W, 3] covers, z^3 / (fx fy |n . p|), given its
    normals [H, W, 3] (the plane footprint of sample_on_planes with the local normal); 0 where undefined."""
    offset = np.abs(np.einsum("hwc,hwc->hw", facing, points))
    return np.where(offset > 0, points[..., 2] ** 3 / (K[0, 0] * K[1, 1] * np.maximum(offset, 1e-9)), 0.0)


def height_steps(points: np.ndarray, up: np.ndarray, tolerance: np.ndarray) -> np.ndarray:
    """Pixels [H, W] bool whose height along up differs from a 4-neighbour's by more than tolerance [H, W]."""
    height = points @ up
    vertical = np.abs(np.diff(height, axis=0)) > np.minimum(tolerance[1:], tolerance[:-1])          # [H-1, W]
    horizontal = np.abs(np.diff(height, axis=1)) > np.minimum(tolerance[:, 1:], tolerance[:, :-1])  # [H, W-1]
    steps = np.zeros(height.shape, bool)
    steps[1:] |= vertical
    steps[:-1] |= vertical
    steps[:, 1:] |= horizontal
    steps[:, :-1] |= horizontal
    return steps


def horizontal_regions(points: np.ndarray, facing: np.ndarray, valid: np.ndarray, K: np.ndarray, up: np.ndarray,
                       cfg: PlaneSearchConfig, rng: np.random.Generator) -> list[Region]:
    """Candidate planes: connected pixels of a point map [H, W, 3] whose normal [H, W, 3] lies within
    horizontal_tol_deg of up, cut where the height jumps by more than plane_distance_rel * depth between
    neighbours (a table top over the floor), at least min_plane_pixel_fraction of the grid each; largest first."""
    min_cos = math.cos(math.radians(cfg.horizontal_tol_deg))
    depth = points[..., 2]
    horizontal = valid & (facing @ up > min_cos) & ~height_steps(points, up, cfg.plane_distance_rel * depth)
    horizontal = cv2.morphologyEx(horizontal.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    count, components = cv2.connectedComponents(horizontal, connectivity=4)
    sizes = np.bincount(components.ravel(), minlength=count)
    footprints = pixel_footprints(points, facing, K)
    regions = []
    for label in np.flatnonzero(sizes >= cfg.min_plane_pixel_fraction * depth.size):
        if label == 0:
            continue
        mask = components == label
        normal, center = refit_plane(points[mask].astype(np.float64), rng)
        regions.append(Region(normal, center, mask, float(footprints[mask].sum())))
    return sorted(regions, key=lambda region: region.area, reverse=True)


def member_labels(points: np.ndarray, facing: np.ndarray, valid: np.ndarray, planes: list[Region],
                   cfg: PlaneSearchConfig) -> np.ndarray:
    """Per-pixel plane index [H, W] int (-1 = none): visible surface connected to each plane's region or to
    the smaller regions that lie on its plane.

    points/facing [H, W, 3] the point map and its normals. A pixel is a member of a plane when its local surface
    normal is within member_normal_tol_deg of the plane normal and its point within plane_distance_rel *
    depth of the plane, or rather of the smooth surface the members found so far follow: estimated depth is
    bent by slow warps (a few % of the depth across the photo), so its floors are gently curved; the offset
    of the members from the plane, smoothed over member_smooth_rel of the width, becomes the reference for
    the next of member_follow_steps rounds. On a true plane the offset stays 0.
    """
    height, width = valid.shape
    depth = points[..., 2]
    min_cos = math.cos(math.radians(cfg.member_normal_tol_deg))
    labels = np.full((height, width), -1, dtype=np.int32)
    kernel = np.ones((3, 3), np.uint8)
    sigma = max(cfg.member_smooth_rel * width, 1.0)
    for index, plane in enumerate(planes):
        signed = (points - plane.center) @ plane.normal                       # [H, W]
        seeds_mask = plane.mask.copy()
        for other in planes[index + 1:]:   # the same surface seen in several pieces (objects in between)
            if np.median(np.abs(signed[other.mask]) / depth[other.mask]) < cfg.plane_distance_rel:
                seeds_mask |= other.mask
        free = valid & (np.abs(facing @ plane.normal) > min_cos) & (labels < 0)
        reference = np.zeros_like(signed)
        for step in range(cfg.member_follow_steps + 1):
            near = (free & (np.abs(signed - reference) < cfg.plane_distance_rel * depth)).astype(np.uint8)
            near = cv2.morphologyEx(near, cv2.MORPH_OPEN, kernel)
            _, components = cv2.connectedComponents(near, connectivity=4)
            seeds = np.unique(components[seeds_mask & (near > 0)])
            members = np.isin(components, seeds[seeds > 0])
            if step < cfg.member_follow_steps and members.any():
                reference = masked_blur(signed, members, sigma)
        labels[members] = index
    return labels


def colour_grown(labels: np.ndarray, colours: np.ndarray, points: np.ndarray, valid: np.ndarray,
                 normals: np.ndarray, centers: np.ndarray, cfg: PlaneSearchConfig) -> np.ndarray:
    """labels [H, W] int (-1 = none; plane indices) with each plane's members grown over pixels of its own colour
    next to it. Estimated depth blurs a table's front edge into the floor below: that part of the top bends off
    its plane, but it still looks like the rest of the top.

    colours [H, W, 3] float CIELAB of the photo on the grid; points [H, W, 3] its point map; valid [H, W] bool the
    pixels that may join; normals/centers [P, 3] the planes. A free pixel joins a plane when
    - its ray meets the plane within colour_grow_distance_rel of its depth (an object stood there comes out at
      most that much too large or small);
    - its CIELAB colour lies within colour_grow_tolerance standard deviations (at least colour_grow_min_delta)
      of the colour of the plane's members around it: a Gaussian of colour_grow_reach_rel of the width over the
      members without their 2-pixel edge, which may hold a neighbour's pixels;
    - and it is connected to the members. colour_grow_steps rounds.
    """
    labels = labels.copy()
    depth = points[..., 2]
    sigma = max(cfg.colour_grow_reach_rel * valid.shape[1], 1.0)
    kernel, core_kernel = np.ones((3, 3), np.uint8), np.ones((5, 5), np.uint8)
    for index, (normal, center) in enumerate(zip(normals, centers)):
        facing_plane = (points @ normal) * (center @ normal) > 0      # the pixel's ray meets the plane in front
        plane_depth = (center @ normal) * depth / np.where(facing_plane, points @ normal, 1.0)   # [H, W] z there
        near_plane = valid & facing_plane & (np.abs(plane_depth / np.maximum(depth, 1e-9) - 1.0)
                                             < cfg.colour_grow_distance_rel)
        for _ in range(cfg.colour_grow_steps):
            members = labels == index
            if not members.any():
                break
            inner = cv2.erode(members.astype(np.uint8), core_kernel) > 0   # its edge may hold a neighbour's pixels
            if not inner.any():
                break
            mean = masked_blur(colours, inner, sigma)                                            # [H, W, 3]
            spread = masked_blur((colours - mean) ** 2, inner, sigma).sum(axis=-1)                # [H, W]
            reached = cv2.GaussianBlur(inner.astype(np.float32), (0, 0), sigma) > 1e-3
            limit = np.maximum(cfg.colour_grow_tolerance * np.sqrt(spread), cfg.colour_grow_min_delta)
            alike = reached & near_plane & (labels < 0) & (np.linalg.norm(colours - mean, axis=-1) < limit)
            alike = cv2.morphologyEx(alike.astype(np.uint8), cv2.MORPH_OPEN, kernel) > 0
            _, components = cv2.connectedComponents((alike | members).astype(np.uint8), connectivity=4)
            seeds = np.unique(components[members])
            grown = alike & np.isin(components, seeds[seeds > 0])
            if not grown.any():
                break
            labels[grown] = index
    return labels


def refit_plane(points: np.ndarray, rng: np.random.Generator, max_fit: int = 5000
                ) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares plane of points [N, 3] -> (camera-facing unit normal [3], centroid [3])."""
    if len(points) > max_fit:
        points = points[rng.choice(len(points), max_fit, replace=False)]
    center = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - center, full_matrices=False)
    normal = vt[2]
    return (normal if normal @ center < 0 else -normal), center
