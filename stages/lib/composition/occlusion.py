"""Occlusion: objects behind the background surface are hidden, and objects hide each other by depth.

Every returned mask is exactly the visible part of an object: its alpha times the transmittance of
whatever lies in front of it (background surface, nearer objects), thresholded.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.ndimage import median_filter

from stages.lib.composition.render_object import ObjectLayer


def filtered_background_depth(depth: np.ndarray, size: int) -> np.ndarray:
    """Median-filtered background depth [H, W] with missing depth (<= 0, non-finite) as +inf.

    depth: [H, W] float32 metres (0 = missing). +inf never occludes anything.
    """
    clean = np.where(np.isfinite(depth) & (depth > 0), depth, np.inf).astype(np.float32)
    if size <= 1:
        return clean
    return median_filter(clean, size=size, mode="nearest")


def occlude_by_background(layer: ObjectLayer, background_depth: np.ndarray, relative_tolerance: float,
                          absolute_tolerance: float) -> ObjectLayer:
    """Remove the object pixels lying behind the background surface.

    background_depth: [H, W] filtered depth (+inf = no surface). An object pixel stays when its
    expected depth <= surface depth * (1 + relative_tolerance) + absolute_tolerance (the tolerance
    keeps the contact with the supporting plane).
    """
    h, w = layer.shape
    surface = background_depth[layer.y0:layer.y0 + h, layer.x0:layer.x0 + w]
    keep = (layer.depth <= surface * (1.0 + relative_tolerance) + absolute_tolerance).astype(np.float32)
    return replace(layer, rgb=layer.rgb * keep[..., None], alpha=layer.alpha * keep,
                   depth=np.where(keep > 0, layer.depth, np.inf).astype(np.float32))


def composite_layers(background: np.ndarray, layers: list[ObjectLayer]) -> tuple[np.ndarray, np.ndarray]:
    """Alpha-composite object layers over the background in per-pixel depth order (nearest first).

    background: [H, W, 3] float32 in [0, 1]. Returns the image [H, W, 3] in [0, 1] and each layer's visible
    alpha [L, H, W] (its alpha times the transmittance of the nearer layers at that pixel).
    """
    height, width = background.shape[:2]
    visible = np.zeros((len(layers), height, width), np.float32)
    image = background.astype(np.float32, copy=True)
    if not layers:
        return image, visible
    y0 = min(layer.y0 for layer in layers)
    x0 = min(layer.x0 for layer in layers)
    y1 = max(layer.y0 + layer.shape[0] for layer in layers)
    x1 = max(layer.x0 + layer.shape[1] for layer in layers)
    count, h, w = len(layers), y1 - y0, x1 - x0
    alpha = np.zeros((count, h, w), np.float32)
    rgb = np.zeros((count, h, w, 3), np.float32)
    depth = np.full((count, h, w), np.inf, np.float32)
    for k, layer in enumerate(layers):
        lh, lw = layer.shape
        region = (k, slice(layer.y0 - y0, layer.y0 - y0 + lh), slice(layer.x0 - x0, layer.x0 - x0 + lw))
        alpha[region], rgb[region], depth[region] = layer.alpha, layer.rgb, layer.depth
    order = np.argsort(depth, axis=0, kind="stable")  # [L, h, w] nearest first
    alpha_sorted = np.take_along_axis(alpha, order, axis=0)
    transmittance = np.cumprod(np.concatenate([np.ones((1, h, w), np.float32), 1.0 - alpha_sorted[:-1]]), axis=0)
    visible_sorted = alpha_sorted * transmittance
    visible_window = np.empty_like(visible_sorted)
    np.put_along_axis(visible_window, order, visible_sorted, axis=0)
    weights = visible_window / np.maximum(alpha, 1e-8)  # transmittance in front of each layer
    colour = (rgb * weights[..., None]).sum(axis=0)  # [h, w, 3]
    remaining = 1.0 - visible_window.sum(axis=0)  # [h, w]
    image[y0:y1, x0:x1] = np.clip(image[y0:y1, x0:x1] * remaining[..., None] + colour, 0.0, 1.0)
    visible[:, y0:y1, x0:x1] = visible_window
    return image, visible
