"""Pixel augmentations of a rendered object (paper: blur, colour adjustments, noise, tone curves).

Parameters are drawn from the caller's numpy Generator (so a composed image depends only on its
seed) and applied with kornia's functional ops. Only the object's colour changes; its opacity map
(and so its mask) does not.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import kornia
import numpy as np
import torch


@dataclass
class PixelAugStrengths:
    """Maximum strength of each augmentation (0 disables it) and the blur probability."""

    blur_prob: float = 0.3
    blur_sigma: float = 1.5  # max Gaussian blur sigma in pixels
    brightness: float = 0.15  # additive, +- this
    contrast: float = 0.2  # multiplicative factor in 1 +- this
    saturation: float = 0.3  # factor in 1 +- this
    hue: float = 0.03  # fraction of a full turn, +- this
    noise_std: float = 0.03  # max std of additive Gaussian noise
    tone_curve: float = 0.1  # std of the tone-curve control points around the identity


def tone_curve(x: torch.Tensor, low: float, high: float) -> torch.Tensor:
    """Cubic Bezier tone curve through (0, 0) and (1, 1) with control values `low`, `high`.

    x: any shape in [0, 1]. low = 1/3, high = 2/3 is the identity.
    """
    t = x
    return (3 * (1 - t) ** 2 * t * low + 3 * (1 - t) * t ** 2 * high + t ** 3).clamp(0.0, 1.0)


def augment_object(rgb: np.ndarray, alpha: np.ndarray, rng: np.random.Generator,
                   strengths: PixelAugStrengths) -> np.ndarray:
    """Augment a rendered object's colour; returns new premultiplied rgb [h, w, 3].

    rgb: [h, w, 3] premultiplied colour, alpha: [h, w]. Blur is a normalised convolution of the
    premultiplied colour and alpha, so no dark fringe comes in from the empty surroundings.
    """
    premul = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1)[None]  # [1, 3, h, w]
    opacity = torch.from_numpy(np.ascontiguousarray(alpha))[None, None]  # [1, 1, h, w]
    if strengths.blur_sigma > 0 and rng.random() < strengths.blur_prob:
        sigma = float(rng.uniform(0.3, strengths.blur_sigma))
        size = 2 * math.ceil(3 * sigma) + 1
        premul = kornia.filters.gaussian_blur2d(premul, size, (sigma, sigma), border_type="constant")
        blurred_alpha = kornia.filters.gaussian_blur2d(opacity, size, (sigma, sigma), border_type="constant")
        colour = premul / blurred_alpha.clamp_min(1e-4)
    else:
        colour = premul / opacity.clamp_min(1e-4)
    colour = colour.clamp(0.0, 1.0)
    colour = kornia.enhance.adjust_brightness(colour, float(rng.uniform(-1, 1) * strengths.brightness))
    colour = kornia.enhance.adjust_contrast(colour, float(1 + rng.uniform(-1, 1) * strengths.contrast))
    colour = kornia.enhance.adjust_saturation(colour, float(1 + rng.uniform(-1, 1) * strengths.saturation))
    colour = kornia.enhance.adjust_hue(colour, float(rng.uniform(-1, 1) * strengths.hue * 2 * math.pi))
    low, high = 1 / 3 + rng.normal(0, strengths.tone_curve), 2 / 3 + rng.normal(0, strengths.tone_curve)
    colour = tone_curve(colour, low, high)
    noise_std = float(rng.uniform(0, strengths.noise_std))
    noise = rng.normal(0.0, 1.0, size=colour.shape).astype(np.float32) * noise_std
    colour = (colour + torch.from_numpy(noise)).clamp(0.0, 1.0)
    return (colour * opacity)[0].permute(1, 2, 0).numpy().astype(np.float32)
