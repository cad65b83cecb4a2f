"""Contact sheets: grids of thumbnails (with mask overlays) for a person to look at."""
from __future__ import annotations

import cv2
import numpy as np

OVERLAY_COLOURS = np.array([[255, 60, 60], [60, 200, 255], [255, 220, 40], [120, 255, 120], [255, 120, 255]], np.float32)


def overlay(image: np.ndarray, label: np.ndarray, alpha: float = 0.45) -> np.ndarray:
    """Tint pixels of image [H, W, 3] uint8 whose label [H, W] int > 0 in a colour per label; outlines in white."""
    out = image.astype(np.float32)
    for value in np.unique(label[label > 0]):
        mask = label == value
        out[mask] = (1 - alpha) * out[mask] + alpha * OVERLAY_COLOURS[(int(value) - 1) % len(OVERLAY_COLOURS)]
        edge = mask & ~cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        out[edge] = 255
    return out.astype(np.uint8)


def depth_colour(depth: np.ndarray, max_m: float = 6.0) -> np.ndarray:
    """A depth map [H, W] in metres as an RGB uint8 image (near = bright)."""
    scaled = np.clip(1 - depth / max_m, 0, 1) * 255
    return cv2.applyColorMap(scaled.astype(np.uint8), cv2.COLORMAP_VIRIDIS)[..., ::-1].copy()


def contact_sheet(images: list[np.ndarray], columns: int = 6, thumb_width: int = 213) -> np.ndarray:
    """Tile RGB uint8 images (any sizes) into one RGB uint8 grid of `columns` thumbnails per row."""
    if not images:
        raise ValueError("a contact sheet needs at least one image")
    thumbs = []
    for image in images:
        h, w = image.shape[:2]
        thumbs.append(cv2.resize(image, (thumb_width, max(1, round(h * thumb_width / w))), interpolation=cv2.INTER_AREA))
    thumb_h = max(t.shape[0] for t in thumbs)
    rows = -(-len(thumbs) // columns)
    sheet = np.full((rows * (thumb_h + 4), columns * (thumb_width + 4), 3), 255, np.uint8)
    for k, thumb in enumerate(thumbs):
        r, c = divmod(k, columns)
        sheet[r * (thumb_h + 4):r * (thumb_h + 4) + thumb.shape[0], c * (thumb_width + 4):c * (thumb_width + 4) + thumb_width] = thumb
    return sheet
