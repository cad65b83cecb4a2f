"""The training loss written with kornia's SSIM and PyTorch's autograd: the reference the fused C++ loss and the
stacked SSIM of stages/lib/gaussians/losses.py are checked against (and the step of 2026-11-25 in
benchmarks/train_step.py's ladder)."""
from __future__ import annotations

import kornia
import torch

from stages.lib.gaussians.losses import SSIM_WINDOW


def photometric_loss_reference(prediction: torch.Tensor, target: torch.Tensor, lambda_dssim: float) -> torch.Tensor:
    """(1 - lambda) L1 + lambda (1 - SSIM) of images [H, W, C] through kornia (any device and dtype; gradients to
    both images)."""
    l1 = (prediction - target).abs().mean()
    ssim = kornia.metrics.ssim(prediction.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None],
                               SSIM_WINDOW).mean()
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - ssim)
