"""From linear radiance to a photo: exposure, tone curve and camera B's lens and sensor effects."""
from __future__ import annotations

import cv2
import numpy as np

from .textures import linear_to_srgb

WHITE_POINT = 2.5
BLUR_SIGMAS = (0.0, 1.2, 2.5, 4.5)  # pixel sigmas of the defocus layers at width 640


def auto_exposure(radiance: np.ndarray, target: float = 0.22) -> float:
    """Exposure scale that brings the median luminance of `radiance` [H, W, 3] to `target`."""
    luminance = radiance @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    return float(np.clip(target / max(float(np.median(luminance)), 1e-4), 0.2, 50.0))


def develop(radiance: np.ndarray, exposure: float) -> np.ndarray:
    """Exposed, tone-mapped (extended Reinhard) sRGB image uint8 [H, W, 3] from linear radiance [H, W, 3]."""
    x = np.maximum(radiance * exposure, 0)
    mapped = x * (1 + x / WHITE_POINT**2) / (1 + x)
    return np.round(linear_to_srgb(mapped) * 255).astype(np.uint8)


def defocus(radiance: np.ndarray, depth: np.ndarray, focus_m: float, strength: float) -> np.ndarray:
    """Depth-dependent blur of radiance [H, W, 3]: circle of confusion ~ strength * |1/z - 1/focus| (pixels).

    Blends a few Gaussian-blurred layers per pixel; depth [H, W] in metres (0 = far).
    """
    scale = radiance.shape[1] / 640
    z = np.where(depth > 0, depth, 100.0)
    coc = strength * scale * np.abs(1 / z - 1 / focus_m)  # [H, W] blur sigma in pixels
    sigmas = np.array(BLUR_SIGMAS) * scale
    layers = [radiance] + [cv2.GaussianBlur(radiance, (0, 0), s) for s in sigmas[1:]]
    position = np.interp(coc, sigmas, np.arange(len(sigmas)))
    low = np.clip(np.floor(position).astype(int), 0, len(sigmas) - 2)
    frac = (position - low)[..., None].astype(np.float32)
    stack = np.stack(layers)  # [L, H, W, 3]
    rows, cols = np.indices(depth.shape)
    return stack[low, rows, cols] * (1 - frac) + stack[low + 1, rows, cols] * frac


def sensor(radiance: np.ndarray, exposure: float, rng: np.random.Generator, cast: np.ndarray,
           noise: float) -> np.ndarray:
    """A cheaper sensor: colour cast (per-channel gains [3]), vignetting and signal-dependent noise,
    then the tone curve -> uint8 [H, W, 3]."""
    h, w = radiance.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((xx - w / 2) ** 2 + (yy - h / 2) ** 2) / (w / 2) ** 2
    x = radiance * exposure * cast[None, None].astype(np.float32) * (1 - 0.25 * r2)[..., None].astype(np.float32)
    x = x + rng.standard_normal(x.shape).astype(np.float32) * np.sqrt(noise * np.maximum(x, 0) + (0.1 * noise) ** 2)
    return develop(x, 1.0)
