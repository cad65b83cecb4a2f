"""Pasting an object cut-out into an image with the blend modes of Cut-and-Paste (Dwibedi et al.).

Modes: "none" (hard mask), "gaussian" (Gaussian-blurred mask edges), "motion" (object and mask
motion-blurred along a random direction), "poisson" (cv2.seamlessClone gradient-domain blending).
The annotation mask is always the hard mask: blending only changes how the edge looks.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from stages.lib.composition.settings import BLEND_MODES


def alpha_blend(image: np.ndarray, colour: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """image * (1 - alpha) + colour * alpha. image, colour: [H, W, 3] float32; alpha: [H, W]."""
    return image * (1.0 - alpha[..., None]) + colour * alpha[..., None]


def motion_kernel(length: int, angle: float) -> np.ndarray:
    """Normalised linear motion-blur kernel [length, length] along `angle` radians."""
    kernel = np.zeros((length, length), np.float32)
    centre = (length - 1) / 2
    dx, dy = math.cos(angle) * centre, math.sin(angle) * centre
    cv2.line(kernel, (round(centre - dx), round(centre - dy)), (round(centre + dx), round(centre + dy)), 1.0, 1)
    return kernel / kernel.sum()


def poisson_paste(image: np.ndarray, colour: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Gradient-domain paste of `colour` where `mask` is set (cv2.seamlessClone, NORMAL_CLONE).

    image, colour: [H, W, 3] float32 in [0, 1] (colour aligned with the image); mask: [H, W] bool.
    Pixels on the image border are left out of the clone region (OpenCV needs a 1-pixel margin).
    """
    inner = mask.copy()
    inner[[0, -1], :] = False
    inner[:, [0, -1]] = False
    if inner.sum() < 4:
        return alpha_blend(image, colour, mask.astype(np.float32))
    ys, xs = np.nonzero(inner)
    x0, x1, y0, y1 = xs.min(), xs.max() + 1, ys.min(), ys.max() + 1
    # seamlessClone puts the centre of the source's mask box at `centre`; crop so the box is the crop.
    src = np.ascontiguousarray((colour[y0:y1, x0:x1] * 255).round().astype(np.uint8))
    src_mask = np.ascontiguousarray(inner[y0:y1, x0:x1].astype(np.uint8) * 255)
    dst = np.ascontiguousarray((image * 255).round().astype(np.uint8))
    centre = (int(x0 + (x1 - x0) // 2), int(y0 + (y1 - y0) // 2))
    cloned = cv2.seamlessClone(src, dst, src_mask, centre, cv2.NORMAL_CLONE)
    return cloned.astype(np.float32) / 255.0


def paste(image: np.ndarray, colour: np.ndarray, mask: np.ndarray, mode: str,
          rng: np.random.Generator) -> np.ndarray:
    """Paste an object (colour [H, W, 3] aligned with image [H, W, 3], mask [H, W] bool) with `mode`."""
    hard = mask.astype(np.float32)
    if mode == "none":
        return alpha_blend(image, colour, hard)
    if mode == "gaussian":
        return alpha_blend(image, colour, cv2.GaussianBlur(hard, (5, 5), 2.0))
    if mode == "motion":
        kernel = motion_kernel(int(rng.choice([3, 5, 7])), float(rng.uniform(0, math.pi)))
        soft = cv2.filter2D(hard, -1, kernel, borderType=cv2.BORDER_CONSTANT)
        blurred = cv2.filter2D(colour * hard[..., None], -1, kernel, borderType=cv2.BORDER_CONSTANT)
        return alpha_blend(image, blurred / np.maximum(soft, 1e-4)[..., None], soft)
    if mode == "poisson":
        return poisson_paste(image, colour, mask)
    raise ValueError(f"unknown blend mode {mode!r}; known: {BLEND_MODES}")
