"""The "gsplat" rasterizer backend: gsplat's CUDA kernels (the field's standard 3DGS rasterizer) behind
`rasterize()`, for float32 CUDA tensors. Imported lazily: gsplat is an optional dependency (the `[gpu]`
extra, pinned) and compiles its CUDA code at its first call (about 1-2 minutes, once per machine).

Picked when gsplat imports and has its CUDA code built or can build it (the PyPI wheel is pure Python and
compiles with the CUDA toolkit's nvcc at its first call). Only gsplat's documented functions are called, for
one camera (C = 1): `fully_fused_projection` (packed=False), `isect_tiles`, `isect_offset_encode` and
`rasterize_to_pixels`. Not `rasterization()`: that one hands back means2d as [C, N, 2] with no [N, 2] tensor
on the gradient's path, and the densification strategy (strategy.py) reads `RenderOutput.means2d.grad` [N, 2].

Same as our projection (projection.py) and compositing (rasterize_torch.py): pixel (u, v) is sampled at
(u + 0.5, v + 0.5) in K's pixel frame (gsplat's kernels and ours); EWA projection with the 0.3 px low-pass
(eps2d) and near plane 0.01; a Gaussian is culled when it is behind the near plane, its opacity is below
1/255 or its alpha >= 1/255 footprint misses the image; 16 px tiles; front-to-back compositing that skips
alpha < 1/255 and stops a pixel before its transmittance falls to 1e-4; the camera z composited with the
colours (gsplat's "RGB+D": depth is alpha-weighted z); colours come precomputed (gaussian_colors, the
`sh_view_dir` augmentation included), so gsplat evaluates no SH; the background is composited by the caller.

Different (what the tolerances of tests/gaussians/test_rasterize_gsplat.py allow for):
- alpha is capped at 0.999 (ours, like the original 3DGS, at 0.99): differs where a Gaussian's opacity is
  above 0.99 at its centre;
- the Jacobian of the projection is evaluated at a position clamped to 0.15 x width / fx outside the image
  (3DGS's 1.3 x tan(fov / 2)); ours clamps at 0.3 x width / fx. Only Gaussians centred outside the image
  differ, in the shape of their footprint;
- gsplat's culling box is its footprint's half-sizes rounded up to whole pixels (ours: not rounded), so a
  Gaussian whose footprint ends within a pixel of the image border may count as visible here only;
- not differentiable w.r.t. K; gradients are summed with atomic adds (not bit-reproducible across runs).

Mapping to RenderOutput: gsplat's means2d [C, N, 2] -> its [N, 2] row for our camera, which is the tensor
the rasterizer reads, so its `.grad` is the view-space gradient of the other backends (gsplat's `absgrad`,
AbsGS's sum of absolute per-pixel gradients, is not used: the strategy's thresholds are for the plain
gradient). gsplat's radii [C, N, 2] (per axis, opacity-aware) -> our [N] int32 3-sigma radius of the 2D
covariance's largest eigenvalue (projection.py's rule, from gsplat's conics), 0 where gsplat culled;
means2d is 0 where culled (ours projects every Gaussian; only visible ones are read).
"""
from __future__ import annotations

import importlib.util
import shutil
from pathlib import Path

import torch

from stages.lib.gaussians.binning import TILE_SIZE
from stages.lib.gaussians.projection import tile_grid

EPS2D = 0.3  # the 0.3 px low-pass filter of 3DGS (project_gaussians' default)
NEAR_PLANE = 0.01  # project_gaussians' default near plane


def gsplat_unavailable(device: torch.device, dtype: torch.dtype) -> str | None:
    """Why gsplat cannot render tensors of `device` and `dtype` here, or None when it can."""
    if device.type != "cuda":
        return f"gsplat renders CUDA tensors only, these are on the {device.type}"
    if dtype != torch.float32:
        return f"gsplat renders float32 tensors only, these are {dtype}"
    try:
        import gsplat  # noqa: F401  (3-4 s the first time)
    except ImportError as error:
        return f"gsplat cannot be imported ({error}); install it with pip install -e \".[gpu]\""
    if importlib.util.find_spec("gsplat.csrc") is None and not _nvcc_found():
        return ("gsplat imports but has no built CUDA code and finds no CUDA toolkit (nvcc) to build it at its "
                "first call; install the CUDA toolkit matching torch.version.cuda or set CUDA_HOME")
    return None


def _nvcc_found() -> bool:
    """Whether the CUDA compiler gsplat builds its code with at its first call is here (as gsplat looks for
    it: in CUDA_HOME as torch finds it, else on PATH)."""
    from torch.utils.cpp_extension import CUDA_HOME

    return (CUDA_HOME is not None and (Path(CUDA_HOME) / "bin" / "nvcc").is_file()) or shutil.which("nvcc") is not None


def three_sigma_radii(conics: torch.Tensor, culled: torch.Tensor) -> torch.Tensor:
    """Our screen radius [N] int32: ceil(3 sqrt(largest eigenvalue)) of the 2D covariance whose inverse is
    `conics` [N, 3] (a, b, c), 0 where `culled` [N] (bool)."""
    with torch.no_grad():
        a, b, c = conics.unbind(-1)
        det_conic = a * c - b * b
        safe = torch.where(culled | (det_conic <= 0), torch.ones_like(det_conic), det_conic)
        cov_xx, cov_yy = c / safe, a / safe
        mid = 0.5 * (cov_xx + cov_yy)
        lambda_max = mid + torch.sqrt(torch.clamp(mid * mid - 1.0 / safe, min=0.1))
        radii = torch.ceil(3.0 * torch.sqrt(lambda_max))
        return torch.where(culled, torch.zeros_like(radii), radii).to(torch.int32)


def rasterize_gsplat(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                     colors: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor, width: int,
                     height: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Project and composite with gsplat (float32 CUDA tensors).

    means [N, 3], quats [N, 4] (w, x, y, z), scales [N, 3], opacities [N], colors [N, 3], viewmat [4, 4]
    world-to-camera, K [3, 3]. Returns (image [H, W, 4]: colour and camera z composited without background,
    transmittance [H, W], radii [N] int32, means2d [N, 2] whose .grad after backward is the view-space
    gradient). Differentiable w.r.t. means, quats, scales, opacities, colors and viewmat.
    """
    from gsplat import fully_fused_projection, isect_offset_encode, isect_tiles, rasterize_to_pixels

    radii_xy, means2d_cam, depths, conics, _ = fully_fused_projection(
        means, None, quats, scales, viewmat[None], K[None], width, height, eps2d=EPS2D, near_plane=NEAR_PLANE,
        packed=False, opacities=opacities)  # [1, N, 2] int32, [1, N, 2], [1, N], [1, N, 3]
    culled = ~(radii_xy[0] > 0).all(dim=-1)  # [N]; gsplat leaves the culled rows of its outputs unset
    # [N, 2], 0 where culled: the tensor the rasterizer reads below, so its gradient is retained here
    means2d = torch.where(culled[:, None], torch.zeros_like(means2d_cam[0]), means2d_cam[0])
    if means2d.requires_grad:
        means2d.retain_grad()
    tiles_x, tiles_y = tile_grid(width, height, TILE_SIZE)
    _, isect_ids, flatten_ids = isect_tiles(means2d[None], radii_xy, depths, TILE_SIZE, tiles_x, tiles_y)
    isect_offsets = isect_offset_encode(isect_ids, 1, tiles_x, tiles_y)  # [1, tiles_y, tiles_x]
    features = torch.cat([colors, depths[0, :, None]], dim=-1)  # [N, 4]
    image, alphas = rasterize_to_pixels(means2d[None], conics, features[None], opacities[None], width, height,
                                        TILE_SIZE, isect_offsets, flatten_ids)  # [1, H, W, 4], [1, H, W, 1]
    return image[0], 1.0 - alphas[0, ..., 0], three_sigma_radii(conics[0], culled), means2d
