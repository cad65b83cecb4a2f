"""The C++/OpenMP CPU kernels, compiled at first use and wrapped as torch.autograd.Functions: the SH colours
(csrc/sh.cpp), the EWA projection (csrc/project.cpp), the tile binning (csrc/bin.cpp), the tile rasterizer
(csrc/kernel.cpp) and the photometric training loss (csrc/loss.cpp).

The extension is built with torch.utils.cpp_extension.load (ninja) into $CUT_AND_SPLAT_CACHE/ext/ (default
~/.cache/cut_and_splat/ext/), in a folder keyed by the sources, the compiler flags and the torch version. Which
build a process uses, and why every build gives the same bits on every CPU, is stages/lib/gaussians/kernel_builds.py's.
If the build fails, `load_extension()` returns None after a warning, and `extension_or_error()` says why.

Threading: the kernel runs torch.get_num_threads() OpenMP threads, in torch's libgomp; idle ones
sleep (OMP_WAIT_POLICY=PASSIVE, set by stages/__init__.py before torch loads).
"""
from __future__ import annotations

import hashlib
import logging
import os
from pathlib import Path

import torch

from stages.lib.gaussians.binning import TILE_SIZE, TileBins
from stages.lib.gaussians.kernel_builds import build_flags, requested_build
from stages.lib.gaussians.projection import Projection, tile_grid

log = logging.getLogger(__name__)

CSRC = Path(__file__).resolve().parent / "csrc"
SOURCES = [CSRC / name for name in ("rasterize.cpp", "sh.cpp", "project.cpp", "bin.cpp", "kernel.cpp", "loss.cpp")]
HEADERS = [CSRC / name for name in ("sh.h", "project.h", "bin.h", "kernel.h", "loss.h")]
_state: dict = {}  # build -> the loaded module, or the error that kept it from loading


def cache_root() -> Path:
    """Folder for compiled extensions: $CUT_AND_SPLAT_CACHE or ~/.cache/cut_and_splat."""
    env = os.environ.get("CUT_AND_SPLAT_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "cut_and_splat"


def _build(build: str):
    from torch.utils.cpp_extension import load

    cflags = build_flags(build)
    texts = [path.read_text() for path in SOURCES + HEADERS]
    key = hashlib.sha256("|".join(texts + [" ".join(cflags), torch.__version__]).encode()).hexdigest()[:16]
    build_dir = cache_root() / "ext" / f"rasterize_{key}"
    build_dir.mkdir(parents=True, exist_ok=True)
    return load(name=f"cut_and_splat_rasterize_{key}", sources=[str(path) for path in SOURCES],
                extra_cflags=cflags, extra_include_paths=[str(CSRC)], extra_ldflags=["-fopenmp"],
                build_directory=str(build_dir), verbose=False)


def load_extension(build: str | None = None):
    """The compiled extension module of `build` (default: this process's, kernel_builds.requested_build()), or
    None when it cannot be built (warned once per build)."""
    build = build or requested_build()
    if build not in _state:
        try:
            _state[build] = _build(build)
        except Exception as error:  # a compiler/ninja failure of any kind: said once, then None
            lines = str(error).strip().splitlines()
            _state[build] = RuntimeError(f"building the C++ kernels ({build}: {' '.join(build_flags(build))}) "
                                         f"failed: {lines[-1] if lines else type(error).__name__}")
            log.warning("%s", _state[build])
    found = _state[build]
    return None if isinstance(found, Exception) else found


def extension_or_error(build: str | None = None):
    """The extension module of `build` (as load_extension), or RuntimeError saying why it could not be built."""
    module = load_extension(build)
    if module is None:
        raise _state[build or requested_build()]
    return module


class _ShColorsCpp(torch.autograd.Function):
    """Differentiable wrapper: (sh, means) -> colours for one camera position."""

    @staticmethod
    def forward(ctx, sh, means, campos, degree, num_threads):
        ctx.save_for_backward(sh, means, campos)
        ctx.settings = (degree, num_threads)
        return load_extension().sh_colors_forward(sh, means, campos, degree, num_threads)

    @staticmethod
    def backward(ctx, grad_colors):
        degree, num_threads = ctx.settings
        grad_sh, grad_means = load_extension().sh_colors_backward(*ctx.saved_tensors, degree, grad_colors, num_threads)
        return grad_sh, grad_means, None, None, None


def sh_colors_cpp(sh: torch.Tensor, means: torch.Tensor, campos: torch.Tensor, degree: int) -> torch.Tensor:
    """C++ twin of rasterize.gaussian_colors for float32 CPU tensors and a camera centre: clamp_min(0.5 + SH, 0)
    [N, 3] of sh [N, K, 3] (bands 0..degree) at the directions from campos [3] to means [N, 3]; differentiable
    w.r.t. sh and means."""
    return _ShColorsCpp.apply(sh.contiguous(), means.contiguous(), campos.detach().float().contiguous(), int(degree),
                              torch.get_num_threads())


class _ProjectCpp(torch.autograd.Function):
    """Differentiable wrapper: (means, quats, scales) -> (means2d, conics, depths); radii and extents ride along."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmat, K, width, height, eps2d, near, num_threads):
        means2d, conics, depths, radii, extents = load_extension().project_forward(
            means, quats, scales, opacities, viewmat, K, width, height, eps2d, near, num_threads)
        ctx.save_for_backward(means, quats, scales, opacities, viewmat, K)
        ctx.settings = (width, height, eps2d, near, num_threads)
        ctx.mark_non_differentiable(radii, extents)
        return means2d, conics, depths, radii, extents

    @staticmethod
    def backward(ctx, grad_means2d, grad_conics, grad_depths, _grad_radii, _grad_extents):
        width, height, eps2d, near, num_threads = ctx.settings
        grads = load_extension().project_backward(*ctx.saved_tensors, width, height, eps2d, near, grad_means2d,
                                                  grad_conics, grad_depths, num_threads)
        return (*grads, None, None, None, None, None, None, None, None)


def project_gaussians_cpp(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                          viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int, *, eps2d: float = 0.3,
                          near: float = 0.01) -> Projection:
    """C++ twin of projection.project_gaussians for float32 CPU tensors (same arguments and rules: means [N, 3],
    quats [N, 4], scales [N, 3], opacities [N], viewmat [4, 4], K [3, 3]); differentiable w.r.t. means, quats
    and scales, not w.r.t. the camera."""
    def prep(t: torch.Tensor) -> torch.Tensor:
        return t.float().contiguous()

    means2d, conics, depths, radii, extents = _ProjectCpp.apply(
        prep(means), prep(quats), prep(scales), prep(opacities.detach()), prep(viewmat.detach()), prep(K.detach()),
        width, height, float(eps2d), float(near), torch.get_num_threads())
    return Projection(means2d=means2d, conics=conics, depths=depths, radii=radii, extents=extents)


def bin_gaussians_cpp(proj: Projection, width: int, height: int) -> TileBins:
    """C++ twin of binning.bin_gaussians for a float32 CPU projection (Gaussians of equal depth in index order)."""
    offsets, ids = load_extension().bin(proj.means2d.detach().contiguous(), proj.extents.contiguous(),
                                        proj.depths.detach().contiguous(), proj.radii.contiguous(), width, height)
    tiles_x, tiles_y = tile_grid(width, height, TILE_SIZE)
    return TileBins(offsets=offsets, gauss_ids=ids, tiles_x=tiles_x, tiles_y=tiles_y)


class _RasterizeCpp(torch.autograd.Function):
    """Differentiable wrapper: (means2d, conics, opacities, features) -> (features image, T)."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, offsets, gauss_ids, width, height,
                num_threads):
        ext = load_extension()
        image, trans, last = ext.forward(means2d, conics, opacities, features, offsets, gauss_ids,
                                         width, height, num_threads)
        ctx.save_for_backward(means2d, conics, opacities, features, offsets, gauss_ids, trans, last)
        ctx.size = (width, height, num_threads)
        return image, trans

    @staticmethod
    def backward(ctx, grad_image, grad_trans):
        width, height, num_threads = ctx.size
        grads = load_extension().backward(*ctx.saved_tensors, grad_image, grad_trans, width,
                                          height, num_threads)
        return (*grads, None, None, None, None, None)


def rasterize_tiles_cpp(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor,
                        features: torch.Tensor, bins: TileBins, width: int,
                        height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """C++ twin of rasterize_torch.rasterize_tiles_torch (float32 CPU; F = 4 feature channels).

    means2d [N, 2], conics [N, 3], opacities [N], features [N, 4]. Returns
    (image [H, W, 4] without background, transmittance [H, W]); inputs of another float dtype
    are cast to float32 (gradients flow back through the cast).
    """
    def prep(t: torch.Tensor) -> torch.Tensor:
        return t.float().contiguous()

    return _RasterizeCpp.apply(prep(means2d), prep(conics), prep(opacities), prep(features),
                               bins.offsets.contiguous(), bins.gauss_ids.contiguous(), width,
                               height, torch.get_num_threads())


class _PhotometricLossCpp(torch.autograd.Function):
    """(prediction, target, window, lambda) -> loss; the kernel computes the gradient with the loss."""

    @staticmethod
    def forward(ctx, prediction, target, window, lambda_dssim, num_threads):
        loss, grad = load_extension().photometric_loss(prediction, target, window, lambda_dssim, num_threads)
        ctx.save_for_backward(grad)
        return loss.to(prediction.dtype)

    @staticmethod
    def backward(ctx, grad_loss):
        (grad,) = ctx.saved_tensors
        return grad * grad_loss, None, None, None, None


def photometric_loss_cpp(prediction: torch.Tensor, target: torch.Tensor, window: torch.Tensor,
                         lambda_dssim: float) -> torch.Tensor:
    """(1 - lambda) L1 + lambda (1 - SSIM) of prediction and target [H, W, C] (float32 CPU; kornia's SSIM with the
    separable window [2 r + 1], 'same' reflect padding; H, W > r), differentiable w.r.t. the prediction only.
    Returns a float32 scalar."""
    return _PhotometricLossCpp.apply(prediction.contiguous(), target.detach().contiguous(), window.contiguous(),
                                     float(lambda_dssim), torch.get_num_threads())
