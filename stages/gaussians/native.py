"""The C++/OpenMP CPU rasterizer: compiled at first use, wrapped as a torch.autograd.Function.

The extension is built with torch.utils.cpp_extension.load (ninja) into
$CUT_AND_SPLAT_CACHE/ext/ (default ~/.cache/cut_and_splat/ext/), in a folder keyed by the
source, the compiler flags, the torch version and this CPU's instruction-set flags (-march=native
code must not be reused on another CPU). If the build fails, a warning is logged once and
`load_extension()` returns None so callers fall back to the PyTorch rasterizer.

Threading: the kernel runs torch.get_num_threads() OpenMP threads, in torch's libgomp; idle ones
sleep (OMP_WAIT_POLICY=PASSIVE, set by stages/__init__.py before torch loads).
"""
from __future__ import annotations

import hashlib
import logging
import os
import platform
from pathlib import Path

import torch

from stages.gaussians.binning import TileBins

log = logging.getLogger(__name__)

CSRC = Path(__file__).resolve().parent / "csrc"
SOURCES = [CSRC / "rasterize.cpp", CSRC / "kernel.cpp"]
HEADERS = [CSRC / "kernel.h"]
# -fno-trapping-math lets comparisons be vectorised; no -ffast-math (it changes results and, linked
# into a shared library with GCC 12, flushes denormals process-wide).
NATIVE_CFLAGS = ["-O3", "-march=native", "-fno-trapping-math", "-fopenmp"]
PORTABLE_CFLAGS = ["-O3", "-fopenmp"]
_state: dict = {}


def cache_root() -> Path:
    """Folder for compiled extensions: $CUT_AND_SPLAT_CACHE or ~/.cache/cut_and_splat."""
    env = os.environ.get("CUT_AND_SPLAT_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "cut_and_splat"


def _cpu_signature() -> str:
    """This CPU's model and instruction-set flags (what -march=native compiles for)."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
        return "".join(line for line in lines if line.startswith(("flags", "model name")))[:4096]
    except OSError:
        return platform.processor()


def _build(cflags: list[str]):
    from torch.utils.cpp_extension import load

    texts = [path.read_text() for path in SOURCES + HEADERS]
    key = hashlib.sha256("|".join(texts + [" ".join(cflags), torch.__version__,
                                           _cpu_signature()]).encode()).hexdigest()[:16]
    build_dir = cache_root() / "ext" / f"rasterize_{key}"
    build_dir.mkdir(parents=True, exist_ok=True)
    return load(name=f"cut_and_splat_rasterize_{key}", sources=[str(path) for path in SOURCES],
                extra_cflags=cflags, extra_include_paths=[str(CSRC)], extra_ldflags=["-fopenmp"],
                build_directory=str(build_dir), verbose=False)


def load_extension():
    """The compiled extension module, or None when it cannot be built (warned once)."""
    if "module" not in _state:
        module = None
        for cflags in (NATIVE_CFLAGS, PORTABLE_CFLAGS):
            try:
                module = _build(cflags)
                break
            except Exception as error:  # a compiler/ninja failure of any kind means: fall back
                log.warning("building the C++ rasterizer with %s failed (%s)", " ".join(cflags),
                            str(error).strip().splitlines()[-1] if str(error).strip() else error)
        if module is None:
            log.warning("C++ rasterizer unavailable: using the (much slower) PyTorch rasterizer")
        _state["module"] = module
    return _state["module"]


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
