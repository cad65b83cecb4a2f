"""The torch device a run uses (`run.device`: auto | cpu | cuda, checked against the machine), and the settings
a stage takes on it (its `cuda` budget)."""
from __future__ import annotations

import glob
from dataclasses import fields
from pathlib import Path

DEVICES = ("auto", "cpu", "cuda")


def nvidia_driver_present() -> bool:
    """True when the machine has an NVIDIA driver loaded (then torch is asked whether CUDA works)."""
    return Path("/proc/driver/nvidia/version").is_file() or bool(glob.glob("/dev/nvidia[0-9]*"))


def choose_device(requested: str) -> str:
    """"cuda" when asked for or (auto) when a GPU is present, else "cpu"; ValueError naming the choices for
    anything else, and for cuda on a machine without a CUDA GPU. Without an NVIDIA driver it answers without
    loading torch (2-4 s)."""
    if requested not in DEVICES:
        raise ValueError(f"run.device={requested!r} is not one of {', '.join(DEVICES)}")
    if requested == "cpu":
        return "cpu"
    available = nvidia_driver_present() and _torch_sees_cuda()
    if requested == "cuda" and not available:
        raise ValueError("run.device=cuda but no CUDA GPU is available; use run.device=auto or cpu")
    return "cuda" if available else "cpu"


def _torch_sees_cuda() -> bool:
    import torch

    return torch.cuda.is_available()


def params_for_device(params: dict, device: str, config_class: type, stage_name: str) -> dict:
    """A stage's params for `device`: its `cuda` settings (a dict of the stage's own settings, its budget on a
    GPU) replace the others on "cuda" and are dropped elsewhere, so each device has its own cache keys.

    `config_class` is the stage's config dataclass: ValueError naming the unknown keys when `cuda` holds
    something that is not one of its settings. The values are checked with the node's other settings, at start
    (stages/engine/settings.py)."""
    overrides = dict(params.get("cuda") or {})
    known = {f.name for f in fields(config_class)} - {"cuda"}
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise ValueError(f"{stage_name}.cuda: unknown settings {unknown}; it may set any of {sorted(known)}")
    resolved = {k: v for k, v in params.items() if k != "cuda"}
    return {**resolved, **overrides} if device == "cuda" else resolved
