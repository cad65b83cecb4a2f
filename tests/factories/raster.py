"""Small random Gaussian scenes in front of an identity camera, for comparing the rasterizer's backends and
kernels; `needs_cpp` gets the C++ extension or skips where no compiler exists."""
from __future__ import annotations

import shutil

import pytest
import torch

from stages.lib.gaussians.model import Gaussians
from stages.lib.gaussians.native import load_extension


def camera(width: int, height: int, focal: float, dtype=torch.float32):
    """Identity pose and an off-centre principal point. Returns (viewmat [4, 4], K [3, 3])."""
    K = torch.tensor([[focal, 0.0, 0.45 * width], [0.0, focal, 0.55 * height], [0.0, 0.0, 1.0]],
                     dtype=dtype)
    return torch.eye(4, dtype=dtype), K


def random_scene(n: int, seed: int, dtype=torch.float32, sh_degree: int = 1,
                 opacity_shift: float = 0.0, needles: bool = False) -> Gaussians:
    """n random Gaussians in front of an identity camera; needles: each 20-50x longer along one axis than across,
    turned at random (thin ellipses whose tile boxes hold rows they do not cross)."""
    gen = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=gen, dtype=dtype) * 0.5 + torch.tensor([0.0, 0.0, 3.0], dtype=dtype)
    log_scales = torch.randn(n, 3, generator=gen, dtype=dtype) * 0.4 - 2.8
    if needles:
        log_scales = torch.full((n, 3), -4.5, dtype=dtype)
        log_scales[:, 0] += 3.0 + torch.rand(n, generator=gen, dtype=dtype)
    return Gaussians(
        means=means,
        log_scales=log_scales,
        quats=torch.nn.functional.normalize(torch.randn(n, 4, generator=gen, dtype=dtype), dim=-1),
        opacity_logits=torch.randn(n, generator=gen, dtype=dtype) + opacity_shift,
        sh=torch.randn(n, (sh_degree + 1) ** 2, 3, generator=gen, dtype=dtype) * 0.5)


def requiring_grad(g: Gaussians) -> Gaussians:
    """A copy whose tensors are leaves requiring gradients."""
    return Gaussians(*(t.detach().clone().requires_grad_() for t in
                       (g.means, g.log_scales, g.quats, g.opacity_logits, g.sh)))


def needs_cpp():
    """The C++ extension, or skip when there is no compiler at all (a failed build with one fails)."""
    if shutil.which("c++") is None and shutil.which("g++") is None:
        pytest.skip("no C++ compiler: the C++ rasterizer cannot be built here")
    ext = load_extension()
    assert ext is not None, "the C++ rasterizer failed to build (see the logged warning)"
    return ext
