"""The 3DGS training loss: (1 - lambda) L1 + lambda D-SSIM of a rendered image and its photo.

On the CPU (float32, the C++ extension built) the loss and its gradient come from one fused kernel
(csrc/loss.cpp), several times faster than the autograd graph of the same formula; elsewhere (CUDA, other
dtypes, images smaller than the window) kornia's SSIM with PyTorch's autograd. Both compute kornia's SSIM: an
11-tap Gaussian window of sigma 1.5, separable, reflect padding ('same'), C1 = 0.01^2, C2 = 0.03^2.
"""
from __future__ import annotations

import kornia
import torch

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5


def ssim_window(dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> torch.Tensor:
    """kornia's SSIM window [SSIM_WINDOW]: a normalised Gaussian of sigma SSIM_SIGMA."""
    return kornia.filters.get_gaussian_kernel1d(SSIM_WINDOW, SSIM_SIGMA, device=device, dtype=dtype).reshape(-1)


def photometric_loss(prediction: torch.Tensor, target: torch.Tensor, lambda_dssim: float) -> torch.Tensor:
    """(1 - lambda) L1 + lambda (1 - SSIM) of images [H, W, 3] (3DGS training loss), a scalar differentiable
    w.r.t. the prediction: the fused C++ kernel where it applies (module docstring), else kornia's SSIM."""
    if _fused_applies(prediction, target):
        from stages.lib.gaussians.native import photometric_loss_cpp

        return photometric_loss_cpp(prediction, target, ssim_window(), lambda_dssim)
    return photometric_loss_reference(prediction, target, lambda_dssim)


def photometric_loss_reference(prediction: torch.Tensor, target: torch.Tensor, lambda_dssim: float) -> torch.Tensor:
    """The same loss through kornia and PyTorch's autograd (any device and dtype; gradients to both images)."""
    l1 = (prediction - target).abs().mean()
    ssim = kornia.metrics.ssim(prediction.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None],
                               SSIM_WINDOW).mean()
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
