"""Mask probabilities refined along the photo's own edges, at inference (a guided filter, He et al. 2010).

Mask R-CNN predicts each mask on a grid of 28x28 cells over its box and pastes it into the photo with bilinear
interpolation: an edge is only as sharp as one cell, 4-5 pixels of a 120 px object. A guided filter fits the pasted
probability, in each window of (2 radius + 1)^2 pixels, as a linear function of the photo's colours, so the mask's
edge moves onto the colour edge within `radius` pixels of it; where the photo is flat it only smooths the probability
(two box blurs of the window's size). The thin leaves of the sample's plant, one or two cells of the grid
wide, are where it gains most (benchmarks/results/plant_masks.md, "Masks refined along the photo's edges").
"""
from __future__ import annotations

import kornia
import torch

from stages.lib.masks.box import tensor_mask_box


def refine_radius(radius: float, image_shape: tuple[int, int], detector_size: int) -> int:
    """The filter's radius in the photo's pixels: `radius` pixels at the detector's input scale (the photo resized
    so its longer side is `detector_size`), scaled to the photo of `image_shape` (H, W) and rounded half up."""
    return int(radius * max(image_shape) / detector_size + 0.5)


def refine_masks(image: torch.Tensor, probability: torch.Tensor, radius: int, eps: float) -> torch.Tensor:
    """Each mask's probability guided-filtered by the image's colours: [N, H, W] in [0, 1].

    image: [3, H, W] float RGB in [0, 1]; probability: [N, H, W] pasted mask probabilities (zero away from their box);
    radius: the filter window's radius in pixels (0 returns `probability`); eps: the regulariser, in squared colour
    units (smaller keeps weaker colour edges).
    Each mask is filtered in the rectangle around its nonzero pixels grown by 2 radius + 1 pixels: the filter gives
    zero beyond 2 radius pixels of them, and inside the rectangle the same values as over the whole image.
    """
    if radius == 0 or len(probability) == 0:
        return probability
    height, width = probability.shape[-2:]
    refined = probability.clone()
    margin = 2 * radius + 1
    for index, mask in enumerate(probability):
        box = tensor_mask_box(mask)
        if box is None:
            continue
        x0, y0 = max(box[0] - margin, 0), max(box[1] - margin, 0)
        x1, y1 = min(box[2] + margin, width), min(box[3] + margin, height)
        window = mask[None, None, y0:y1, x0:x1]  # [1, 1, h, w]
        guide = image[None, :, y0:y1, x0:x1]  # [1, 3, h, w]
        refined[index, y0:y1, x0:x1] = kornia.filters.guided_blur(guide, window, 2 * radius + 1, eps)[0, 0].clamp(0, 1)
    return refined
