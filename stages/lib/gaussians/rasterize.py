"""Public differentiable Gaussian renderer: `render(g, viewmat, K, width, height, ...)`.

Backends: "torch" (pure-PyTorch reference, any device and dtype), "cpp" (C++/OpenMP CPU kernels of the SH
colours, the projection, the binning and the compositor, float32), "cuda" (the PyTorch path on the GPU: 54-264
ms per 256x256 training iteration for 10k-200k Gaussians on an H100), "gsplat" (gsplat's CUDA kernels, float32
CUDA tensors, the `[gpu]` extra: 2.6-3.4 ms there; rasterize_gsplat.py says what it computes differently),
"auto" (for CUDA tensors gsplat when it imports and can build its CUDA code, else cuda; on the CPU cpp, and an
error saying why when it cannot be built: the cache keys name the kernels' results, which torch's differ from).
The choice and its reason are logged once per process (per request, device and dtype). Our backends share the
rules of the projection and the tile binning (cpp computes them in C++, the others in PyTorch) and the SH colours,
so they composite the same per-tile lists (up to the order of Gaussians of equal depth); gsplat gets the same
colours. Every backend samples pixel (u, v) at (u + 0.5, v + 0.5) in K's pixel
frame.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import torch

from stages.lib.gaussians.binning import bin_gaussians
from stages.lib.gaussians.model import Gaussians
from stages.lib.gaussians.projection import project_gaussians
from stages.lib.gaussians.rasterize_torch import rasterize_tiles_torch
from stages.lib.gaussians.sh import eval_sh
from stages.lib.gaussians.train_config import BACKENDS
from stages.lib.geometry import camera_centres

log = logging.getLogger(__name__)
_chosen: dict[tuple[str, str, torch.dtype], str] = {}  # (request, device type, dtype) -> backend, logged once


@dataclass
class RenderOutput:
    """One rendered view, the same fields from every backend. Pixel (u, v) is sampled at (u + 0.5, v + 0.5)
    in K's pixel frame (gsplat's convention too; the original 3DGS samples at integer coordinates)."""

    rgb: torch.Tensor  # [H, W, 3], background composited
    alpha: torch.Tensor  # [H, W] accumulated opacity 1 - T
    depth: torch.Tensor  # [H, W] alpha-weighted camera z (divide by alpha for expected depth)
    radii: torch.Tensor  # [N] int32 screen radius in pixels (3 sigma); 0 = not visible
    means2d: torch.Tensor  # [N, 2] pixel positions; .grad after backward = view-space gradient


def choose_backend(backend: str, device: torch.device, dtype: torch.dtype) -> str:
    """The backend that renders tensors of `device` and `dtype` when `backend` (one of BACKENDS) is asked
    for; ValueError saying why when it cannot. The first choice for each (request, device type, dtype) is
    logged with its reason (a warning when a GPU falls back to the slow PyTorch path)."""
    if backend not in BACKENDS:
        raise ValueError(f"unknown rasterizer backend {backend!r}; choose one of {BACKENDS}")
    key = (backend, device.type, dtype)
    if key not in _chosen:
        chosen, level, why = _resolve_backend(backend, device, dtype)
        log.log(level, "rasterizer backend %r for %s %s tensors: %s", chosen, device.type,
                str(dtype).removeprefix("torch."), why)
        _chosen[key] = chosen
    return _chosen[key]


def _resolve_backend(backend: str, device: torch.device, dtype: torch.dtype) -> tuple[str, int, str]:
    """(backend, log level, why) for a request; ValueError when the requested backend cannot render here."""
    from stages.lib.gaussians.rasterize_gsplat import gsplat_unavailable

    if backend == "auto" and device.type == "cuda":
        missing = gsplat_unavailable(device, dtype)
        if missing is None:
            return "gsplat", logging.INFO, ("auto: gsplat imports (its CUDA code compiles at the first call, "
                                            "1-2 minutes once per machine)")
        return "cuda", logging.WARNING, f"auto: the PyTorch path, 20-90x slower than gsplat: {missing}"
    if backend == "auto":
        from stages.lib.gaussians.native import extension_or_error

        try:
            extension_or_error()
        except RuntimeError as error:  # no silent fallback: the PyTorch path's results differ in the last bits
            raise ValueError(f"{error}; the C++ kernels need a C++ compiler (g++), ninja and the Python headers, "
                             "or ask for the PyTorch rasterizer (the stage's backend setting: torch, 10-50x "
                             "slower)") from None
        return "cpp", logging.INFO, "auto: the C++ extension is built"
    if backend == "cpp" and device.type != "cpu":
        raise ValueError("backend 'cpp' needs CPU tensors; use 'gsplat', 'cuda' or 'torch' on a GPU")
    if backend == "cuda" and device.type != "cuda":
        raise ValueError("backend 'cuda' needs CUDA tensors")
    if backend == "gsplat" and (missing := gsplat_unavailable(device, dtype)) is not None:
        raise ValueError(f"backend 'gsplat' cannot render here: {missing}")
    return backend, logging.INFO, "as configured"


def rasterize(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
              opacities: torch.Tensor, colors: torch.Tensor, viewmat: torch.Tensor,
              K: torch.Tensor, width: int, height: int, *, background: torch.Tensor | None = None,
              backend: str = "auto") -> RenderOutput:
    """Render Gaussians with fixed per-Gaussian colours (the raw-tensor entry point).

    means [N, 3], quats [N, 4] (w, x, y, z), scales [N, 3], opacities [N] in (0, 1),
    colors [N, 3], viewmat [4, 4] world-to-camera (OpenCV axes), K [3, 3], background [3] or None
    (black). Differentiable w.r.t. all tensor arguments (with gsplat: all but K). `backend`: one of
    BACKENDS (module docstring); ValueError when it cannot render these tensors.
    """
    device, dtype = means.device, means.dtype
    background = (torch.zeros(3, device=device, dtype=dtype) if background is None
                  else torch.as_tensor(background, device=device, dtype=dtype))
    viewmat = torch.as_tensor(viewmat, device=device, dtype=dtype)
    K = torch.as_tensor(K, device=device, dtype=dtype)
    chosen = choose_backend(backend, device, dtype)
    if chosen == "gsplat":
        from stages.lib.gaussians.rasterize_gsplat import rasterize_gsplat

        image, trans, radii, means2d = rasterize_gsplat(means, quats, scales, opacities, colors, viewmat, K,
                                                        width, height)
    else:
        image, trans, radii, means2d = _rasterize_tiles(chosen, means, quats, scales, opacities, colors,
                                                        viewmat, K, width, height)
    return RenderOutput(rgb=image[..., :3] + trans[..., None] * background, alpha=1.0 - trans,
                        depth=image[..., 3], radii=radii, means2d=means2d)


def _rasterize_tiles(chosen: str, means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                     opacities: torch.Tensor, colors: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor,
                     width: int, height: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Our backends ("torch", "cuda", "cpp"): the projection and the binning (cpp: their C++ twins for float32
    where the camera needs no gradient), then the tile compositor.
    Returns (image [H, W, 4] colour and camera z without background, transmittance [H, W], radii [N],
    means2d [N, 2] with its gradient retained)."""
    if chosen == "cpp" and means.dtype == torch.float32 and not (viewmat.requires_grad or K.requires_grad):
        from stages.lib.gaussians.native import bin_gaussians_cpp, project_gaussians_cpp

        proj = project_gaussians_cpp(means, quats, scales, opacities, viewmat, K, width, height)
        bins = bin_gaussians_cpp(proj, width, height)
    else:
        proj = project_gaussians(means, quats, scales, opacities, viewmat, K, width, height)
        bins = bin_gaussians(proj, width, height)
    if proj.means2d.requires_grad:
        proj.means2d.retain_grad()
    features = torch.cat([colors, proj.depths[:, None]], dim=-1)  # [N, 4]
    if chosen == "cpp":
        from stages.lib.gaussians.native import rasterize_tiles_cpp

        image, trans = rasterize_tiles_cpp(proj.means2d, proj.conics, opacities, features, bins,
                                           width, height)
        image, trans = image.to(means.dtype), trans.to(means.dtype)
    else:
        image, trans = rasterize_tiles_torch(proj.means2d, proj.conics, opacities, features, bins,
                                             width, height)
    return image, trans, proj.radii, proj.means2d


def gaussian_colors(g: Gaussians, viewmat: torch.Tensor, *, sh_degree: int | None = None,
                    sh_view_dir: torch.Tensor | None = None, backend: str = "torch") -> torch.Tensor:
    """3DGS colours clamp_min(0.5 + SH(d), 0) [N, 3] for the view `viewmat` [4, 4].

    d is the camera-to-Gaussian direction, or `sh_view_dir` [3] (a world direction, the same for
    all Gaussians: the paper's augmentation). sh_degree caps the bands used (default: all). With the
    rasterizer `backend` that resolves to "cpp", float32 colours at the camera's directions come from the C++
    kernel (the same values), with "gsplat" from gsplat's `spherical_harmonics` (the same basis); otherwise
    from PyTorch.
    """
    degree = g.sh_degree if sh_degree is None else min(sh_degree, g.sh_degree)
    if sh_view_dir is not None:
        dirs = torch.as_tensor(sh_view_dir, device=g.device, dtype=g.means.dtype).reshape(3)
        return torch.clamp_min(eval_sh(degree, g.sh, dirs) + 0.5, 0.0)
    viewmat = torch.as_tensor(viewmat, device=g.device, dtype=g.means.dtype)
    cam_centre = camera_centres(viewmat)  # [3]
    chosen = choose_backend(backend, g.device, g.means.dtype)
    if g.means.dtype == torch.float32 and chosen == "cpp":
        from stages.lib.gaussians.native import sh_colors_cpp

        return sh_colors_cpp(g.sh, g.means, cam_centre, degree)
    if chosen == "gsplat":  # one CUDA kernel each way, where eval_sh launches some forty
        from gsplat import spherical_harmonics

        return torch.clamp_min(spherical_harmonics(degree, g.means - cam_centre, g.sh) + 0.5, 0.0)
    return torch.clamp_min(eval_sh(degree, g.sh, g.means - cam_centre) + 0.5, 0.0)


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
        colors = gaussian_colors(g, viewmat, sh_degree=sh_degree, sh_view_dir=sh_view_dir, backend=backend)
    else:
        colors = torch.as_tensor(colors, device=g.device, dtype=g.means.dtype).expand(g.num, 3)
    return rasterize(g.means, g.quats, g.scales, g.opacities, colors, viewmat, K, width, height,
                     background=background, backend=backend)
