"""Whether a GPU measurement can run here: a CUDA device, and gsplat able to render on it."""
from __future__ import annotations

import torch

from stages.lib.gaussians.rasterize_gsplat import gsplat_unavailable


def gsplat_gpu_ready() -> bool:
    """True when gsplat can render on this machine's CUDA device. Without a CUDA device it prints "no CUDA device:
    skipped" and returns False (a benchmark's GPU part then ends quietly); SystemExit with the reason when there is
    a device but gsplat cannot run on it."""
    if not torch.cuda.is_available():
        print("no CUDA device: skipped")
        return False
    missing = gsplat_unavailable(torch.device("cuda"), torch.float32)
    if missing:
        raise SystemExit(f"the gsplat backend cannot run: {missing}")
    return True
