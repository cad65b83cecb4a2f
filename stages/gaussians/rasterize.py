"""Public differentiable Gaussian renderer: `render(g, viewmat, K, width, height, ...)`.

Backends: "torch" (pure-PyTorch reference, any device and dtype), "cpp" (C++/OpenMP CPU
kernel, float32), "cuda" (the PyTorch path on the GPU: ~47 ms per 256x256 training iteration
with 20k Gaussians on an H100), "auto" (cuda for CUDA tensors; on the CPU cpp when it builds,
else torch). Projection, SH colours and tile binning are shared PyTorch code, so all backends
composite the same per-tile lists. gsplat is not used: it cannot be installed here to test it,
and its means2d (whose gradient densification reads) has another layout ([C, N, 2]).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from stages.gaussians.binning import bin_gaussians
from stages.gaussians.model import Gaussians
from stages.gaussians.projection import project_gaussians
from stages.gaussians.rasterize_torch import rasterize_tiles_torch
from stages.gaussians.sh import eval_sh
from stages.geometry import camera_centres

BACKENDS = ("auto", "torch", "cpp", "cuda")


@dataclass
class RenderOutput:
    """One rendered view. Pixel (u, v) is sampled at (u + 0.5, v + 0.5) in K's pixel frame."""

    rgb: torch.Tensor  # [H, W, 3], background composited
    alpha: torch.Tensor  # [H, W] accumulated opacity 1 - T
    depth: torch.Tensor  # [H, W] alpha-weighted camera z (divide by alpha for expected depth)
    radii: torch.Tensor  # [N] int32 screen radius in pixels (3 sigma); 0 = not visible
    means2d: torch.Tensor  # [N, 2] pixel positions; .grad after backward = view-space gradient


def _choose_backend(backend: str, device: torch.device) -> str:
    if backend not in BACKENDS:
        raise ValueError(f"unknown rasterizer backend {backend!r}; choose one of {BACKENDS}")
    if backend == "auto":
        if device.type == "cuda":
            return "cuda"
        from stages.gaussians.native import load_extension

        return "cpp" if load_extension() is not None else "torch"
    if backend == "cpp" and device.type != "cpu":
        raise ValueError("backend 'cpp' needs CPU tensors; use 'cuda' or 'torch' on a GPU")
    if backend == "cuda" and device.type != "cuda":
        raise ValueError("backend 'cuda' needs CUDA tensors")
    return backend


def rasterize(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
              opacities: torch.Tensor, colors: torch.Tensor, viewmat: torch.Tensor,
              K: torch.Tensor, width: int, height: int, *, background: torch.Tensor | None = None,
              backend: str = "auto") -> RenderOutput:
    """Render Gaussians with fixed per-Gaussian colours (the raw-tensor entry point).

    means [N, 3], quats [N, 4] (w, x, y, z), scales [N, 3], opacities [N] in (0, 1),
    colors [N, 3], viewmat [4, 4] world-to-camera (OpenCV axes), K [3, 3], background [3] or None
    (black). Differentiable w.r.t. all tensor arguments.
    """
    device, dtype = means.device, means.dtype
    background = (torch.zeros(3, device=device, dtype=dtype) if background is None
                  else torch.as_tensor(background, device=device, dtype=dtype))
    viewmat = torch.as_tensor(viewmat, device=device, dtype=dtype)
    K = torch.as_tensor(K, device=device, dtype=dtype)
    chosen = _choose_backend(backend, device)
    proj = project_gaussians(means, quats, scales, opacities, viewmat, K, width, height)
    if proj.means2d.requires_grad:
        proj.means2d.retain_grad()
    bins = bin_gaussians(proj, width, height)
    features = torch.cat([colors, proj.depths[:, None]], dim=-1)  # [N, 4]
    if chosen == "cpp":
        from stages.gaussians.native import rasterize_tiles_cpp

        image, trans = rasterize_tiles_cpp(proj.means2d, proj.conics, opacities, features, bins,
                                           width, height)
        image, trans = image.to(dtype), trans.to(dtype)
    else:
        image, trans = rasterize_tiles_torch(proj.means2d, proj.conics, opacities, features, bins,
                                             width, height)
    return RenderOutput(rgb=image[..., :3] + trans[..., None] * background, alpha=1.0 - trans,
                        depth=image[..., 3], radii=proj.radii, means2d=proj.means2d)


def gaussian_colors(g: Gaussians, viewmat: torch.Tensor, *, sh_degree: int | None = None,
                    sh_view_dir: torch.Tensor | None = None) -> torch.Tensor:
    """3DGS colours clamp_min(0.5 + SH(d), 0) [N, 3] for the view `viewmat` [4, 4].

    d is the camera-to-Gaussian direction, or `sh_view_dir` [3] (a world direction, the same for
    all Gaussians: the paper's augmentation). sh_degree caps the bands used (default: all).
    """
    degree = g.sh_degree if sh_degree is None else min(sh_degree, g.sh_degree)
    if sh_view_dir is not None:
        dirs = torch.as_tensor(sh_view_dir, device=g.device, dtype=g.means.dtype).reshape(3)
    else:
        viewmat = torch.as_tensor(viewmat, device=g.device, dtype=g.means.dtype)
        cam_centre = camera_centres(viewmat)  # [3]
        dirs = g.means - cam_centre  # [N, 3]
    return torch.clamp_min(eval_sh(degree, g.sh, dirs) + 0.5, 0.0)


def render(g: Gaussians, viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int, *,
           background: torch.Tensor | None = None, colors: torch.Tensor | None = None,
           sh_view_dir: torch.Tensor | None = None, sh_degree: int | None = None,
           backend: str = "auto") -> RenderOutput:
    """Render a Gaussians model from the camera (viewmat [4, 4] world-to-camera, K [3, 3]).

    background [3] (default black); colors [N, 3] overrides the SH colours (white gives the
    opacity map in rgb); sh_view_dir [3] evaluates SH with this world direction for every
    Gaussian instead of the camera-to-Gaussian directions; sh_degree caps the SH bands used.
    Differentiable w.r.t. every Gaussian parameter; see `rasterize` for backends.
    """
    if colors is None:
        colors = gaussian_colors(g, viewmat, sh_degree=sh_degree, sh_view_dir=sh_view_dir)
    else:
        colors = torch.as_tensor(colors, device=g.device, dtype=g.means.dtype).expand(g.num, 3)
    return rasterize(g.means, g.quats, g.scales, g.opacities, colors, viewmat, K, width, height,
                     background=background, backend=backend)
