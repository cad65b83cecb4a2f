"""The torch device a run uses: `run.device` (auto | cpu | cuda) checked against the machine."""
from __future__ import annotations

import torch

DEVICES = ("auto", "cpu", "cuda")


def choose_device(requested: str) -> str:
    """"cuda" when asked for or (auto) when a GPU is present, else "cpu"; ValueError naming the choices for
    anything else, and for cuda on a machine without a CUDA GPU."""
    if requested not in DEVICES:
        raise ValueError(f"run.device={requested!r} is not one of {', '.join(DEVICES)}")
    if requested == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if requested == "cuda" and not torch.cuda.is_available():
        raise ValueError("run.device=cuda but no CUDA GPU is available; use run.device=auto or cpu")
    return requested
