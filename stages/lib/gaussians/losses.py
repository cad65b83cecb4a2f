"""The 3DGS training loss: (1 - lambda) L1 + lambda D-SSIM of a rendered image and its photo.

On the CPU (float32, the C++ extension built) the loss and its gradient come from one fused kernel
(csrc/loss.cpp), several times faster than the autograd graph of the same formula; elsewhere (CUDA, other
dtypes) PyTorch's autograd over the five local moments blurred as one stack (`photometric_loss_stacked`: on a GPU
a handful of launches where kornia's SSIM makes some forty). All compute kornia's SSIM: an 11-tap Gaussian window
of sigma 1.5, separable, reflect padding ('same', so an image side must exceed the window's radius of 5 pixels, as
with kornia), C1 = 0.01^2, C2 = 0.03^2, eps = 1e-12 under the ratio.
"""
from __future__ import annotations

import functools

import kornia
import torch
import torch.nn.functional as F

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5


SSIM_C1, SSIM_C2, SSIM_EPS = 0.01 ** 2, 0.03 ** 2, 1e-12


@functools.lru_cache(maxsize=8)
def ssim_window(dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> torch.Tensor:
    """kornia's SSIM window [SSIM_WINDOW]: a normalised Gaussian of sigma SSIM_SIGMA (made once per dtype and
    device, as a normal tensor even when first asked for in inference mode, so autograd may save it; read only)."""
    with torch.inference_mode(False):
        return kornia.filters.get_gaussian_kernel1d(SSIM_WINDOW, SSIM_SIGMA, device=device, dtype=dtype).reshape(-1)


def photometric_loss(prediction: torch.Tensor, target: torch.Tensor, lambda_dssim: float) -> torch.Tensor:
    """(1 - lambda) L1 + lambda (1 - SSIM) of images [H, W, 3] (3DGS training loss), a scalar differentiable
    w.r.t. the prediction: the fused C++ kernel where it applies (module docstring), else the stacked SSIM."""
    if _fused_applies(prediction, target):
        from stages.lib.gaussians.native import photometric_loss_cpp

        return photometric_loss_cpp(prediction, target, ssim_window(), lambda_dssim)
    return photometric_loss_stacked(prediction, target, lambda_dssim)


def photometric_loss_stacked(prediction: torch.Tensor, target: torch.Tensor, lambda_dssim: float) -> torch.Tensor:
    """The same loss of images [H, W, C] (H and W larger than the window's radius) with kornia's SSIM written as
    one stack: the images, their squares and their product [1, 5C, H, W] padded once and blurred by the separable
    window as two grouped convolutions. Any device and dtype; gradients to both images."""
    channels = prediction.shape[-1]
    p, t = prediction.permute(2, 0, 1), target.permute(2, 0, 1)  # [C, H, W]
    stack = torch.cat([p, t, p * p, t * t, p * t])[None]  # [1, 5C, H, W]
    radius, groups = SSIM_WINDOW // 2, stack.shape[1]
    window = ssim_window(prediction.dtype, prediction.device)
    padded = F.pad(stack, (radius, radius, radius, radius), mode="reflect")
    rows = F.conv2d(padded, window.view(1, 1, 1, -1).expand(groups, 1, 1, SSIM_WINDOW), groups=groups)
    blurred = F.conv2d(rows, window.view(1, 1, -1, 1).expand(groups, 1, SSIM_WINDOW, 1), groups=groups)[0]
    mu1, mu2, e11, e22, e12 = blurred.split(channels)  # [C, H, W] each
    mu1_mu2, mu1_sq, mu2_sq = mu1 * mu2, mu1 * mu1, mu2 * mu2
    num = (2.0 * mu1_mu2 + SSIM_C1) * (2.0 * (e12 - mu1_mu2) + SSIM_C2)
    den = (mu1_sq + mu2_sq + SSIM_C1) * ((e11 - mu1_sq) + (e22 - mu2_sq) + SSIM_C2)
    ssim = (num / (den + SSIM_EPS)).mean()
    l1 = (prediction - target).abs().mean()
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - ssim)


def _fused_applies(prediction: torch.Tensor, target: torch.Tensor) -> bool:
    """Whether the C++ kernel computes this loss: float32 CPU images larger than the window's radius, no gradient
    wanted for the target, and the extension built."""
    if prediction.device.type != "cpu" or prediction.dtype != torch.float32 or target.dtype != torch.float32:
        return False
    if target.requires_grad or min(prediction.shape[0], prediction.shape[1]) <= SSIM_WINDOW // 2:
        return False
    from stages.lib.gaussians.native import load_extension

    return load_extension() is not None
