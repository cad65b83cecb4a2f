"""A preview grid of composed images with each instance mask outlined in its category colour."""
from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

PALETTE = [(230, 25, 75), (60, 180, 75), (255, 225, 25), (0, 130, 200), (245, 130, 48), (145, 30, 180),
           (70, 240, 240), (240, 50, 230), (210, 245, 60), (250, 190, 190)]


def outline_masks(image: np.ndarray, masks: list[np.ndarray], category_ids: list[int]) -> np.ndarray:
    """Draw mask outlines on a copy of image [H, W, 3] uint8 RGB; masks [H, W] bool."""
    canvas = image.copy()
    for mask, category_id in zip(masks, category_ids):
        contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(canvas, contours, -1, PALETTE[(category_id - 1) % len(PALETTE)], 2)
    return canvas


def preview_grid(tiles: list[np.ndarray], tile_width: int = 320) -> np.ndarray:
    """Tiles [H, W, 3] uint8 resized to `tile_width` and laid out in a near-square grid."""
    if not tiles:
        return np.zeros((8, tile_width, 3), np.uint8)
    resized = [cv2.resize(t, (tile_width, max(1, round(t.shape[0] * tile_width / t.shape[1]))),
                          interpolation=cv2.INTER_AREA) for t in tiles]
    tile_height = max(t.shape[0] for t in resized)
    columns = math.ceil(math.sqrt(len(resized)))
    rows = math.ceil(len(resized) / columns)
    grid = np.zeros((rows * tile_height, columns * tile_width, 3), np.uint8)
    for k, tile in enumerate(resized):
        r, c = divmod(k, columns)
        grid[r * tile_height:r * tile_height + tile.shape[0], c * tile_width:(c + 1) * tile_width] = tile
    return grid


def write_preview(path: Path, images: list[np.ndarray], masks: list[list[np.ndarray]],
                  category_ids: list[list[int]]) -> None:
    """Write the outlined grid of `images` (RGB uint8) to a PNG at `path`."""
    tiles = [outline_masks(im, ms, cs) for im, ms, cs in zip(images, masks, category_ids)]
    cv2.imwrite(str(path), cv2.cvtColor(preview_grid(tiles), cv2.COLOR_RGB2BGR))
