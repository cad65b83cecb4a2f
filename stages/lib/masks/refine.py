"""Mask probabilities refined along the photo's own edges, at inference (a guided filter, He et al. 2010).

Mask R-CNN predicts each mask on a grid of 28x28 cells over its box and pastes it into the photo with bilinear
interpolation: an edge is only as sharp as one cell, 4-5 pixels of a 120 px object. A guided filter fits the pasted
probability, in each window of (2 radius + 1)^2 pixels, as a linear function of the photo's colours, so the mask's
edge moves onto the colour edge within `radius` pixels of it; where the photo is flat it only smooths the probability
(two box blurs of the window's size). The thin leaves of the sample's plant, one or two cells of the grid
wide, are where it gains most (benchmarks/results/plant_masks.md, "Masks refined along the photo's edges").
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

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
        window = mask[None, y0:y1, x0:x1]  # [1, h, w]
        refined[index, y0:y1, x0:x1] = guided_filter(image[:, y0:y1, x0:x1], window, radius, eps).clamp(0, 1)
    return refined


def box_mean(x: torch.Tensor, radius: int) -> torch.Tensor:
    """The mean of each channel over the (2 radius + 1)^2 window around each pixel, the border reflected (as kornia's
    box_blur): [C, H, W] -> [C, H, W]. Running sums down the columns, then along the rows: a window's sum is the
    difference of two of them, whatever the radius (the sums of values in [0, 1] over a window's row or column keep
    float32's error below 1e-6 of the mean)."""
    size = 2 * radius + 1
    padded = F.pad(x[None], (radius, radius, radius, radius), mode="reflect")[0]  # [C, H + 2r, W + 2r]
    down = F.pad(padded, (0, 0, 1, 0)).cumsum(-2)  # [C, H + 2r + 1, W + 2r]
    columns = down[:, size:] - down[:, :-size]  # [C, H, W + 2r]: each column's sum over the window's rows
    across = F.pad(columns, (1, 0)).cumsum(-1)  # [C, H, W + 2r + 1]
    return (across[..., size:] - across[..., :-size]) / size ** 2


def guided_filter(guide: torch.Tensor, source: torch.Tensor, radius: int, eps: float) -> torch.Tensor:
    """He et al.'s guided filter with a colour guide: `source` [1, H, W] fitted in each window as a linear function of
    `guide`'s colours [3, H, W], the fits averaged: [H, W]. The 3x3 covariance (plus eps on its diagonal) is
    inverted in closed form per pixel, and the window means are two batched box_means (kornia's guided_blur computes
    the same with a per-pixel solve and box kernels)."""
    rows, cols = torch.triu_indices(3, 3)  # the covariance's 6 distinct entries: 00 01 02 11 12 22
    means = box_mean(torch.cat([guide, source, guide * source, guide[rows] * guide[cols]]), radius)
    mean_colour, mean_p, mean_cp, mean_cc = means[:3], means[3], means[4:7], means[7:]  # [3, H, W], [H, W], ...
    cov_p = mean_cp - mean_colour * mean_p  # [3, H, W]
    s00, s01, s02, s11, s12, s22 = mean_cc - mean_colour[rows] * mean_colour[cols] + eps * (rows == cols)[:, None, None]
    c00, c01, c02 = s11 * s22 - s12 * s12, s02 * s12 - s01 * s22, s01 * s12 - s02 * s11  # cofactors (symmetric)
    c11, c12, c22 = s00 * s22 - s02 * s02, s01 * s02 - s00 * s12, s00 * s11 - s01 * s01
    det = s00 * c00 + s01 * c01 + s02 * c02  # [H, W]
    v0, v1, v2 = cov_p
    a = torch.stack([c00 * v0 + c01 * v1 + c02 * v2, c01 * v0 + c11 * v1 + c12 * v2,
                     c02 * v0 + c12 * v1 + c22 * v2]) / det  # [3, H, W]: the covariance's inverse times cov_p
    b = mean_p - (a * mean_colour).sum(0)  # [H, W]
    fitted = box_mean(torch.cat([a, b[None]]), radius)  # [4, H, W]
    return (fitted[:3] * guide).sum(0) + fitted[3]
