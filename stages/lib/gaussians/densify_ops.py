"""Edits of the optimised Gaussian parameters that keep Adam's state in step: keep and append rows,
clone rows, split rows, reset opacities.

`params` maps each parameter name to its torch.nn.Parameter ([N, ...], rows = Gaussians) and is edited in
place, like `optimizer`, an Adam whose param groups hold one parameter each, named by "name".
"""
from __future__ import annotations

import math

import torch

from stages.lib.gaussians.model import inverse_sigmoid, quat_to_rotmat

SPLIT_COUNT = 2
SPLIT_SHRINK = 0.8 * SPLIT_COUNT  # 3DGS: children get the parent's scales / (0.8 * N)


def edit_rows(params: dict[str, torch.nn.Parameter], optimizer: torch.optim.Optimizer, keep: torch.Tensor,
              extra: dict[str, torch.Tensor]) -> None:
    """Keep the rows in `keep` (bool [N]) of every parameter and its Adam moments, then append `extra`
    ([M, ...] per name; their moments start at zero)."""
    for group in optimizer.param_groups:
        name, old = group["name"], group["params"][0]
        state = optimizer.state.pop(old, {})
        value = torch.cat([old.detach()[keep], extra[name]])
        moments = {k: torch.cat([v[keep], torch.zeros_like(extra[name])]) for k, v in state.items() if k != "step"}
        new = torch.nn.Parameter(value.contiguous())
        group["params"][0] = new
        params[name] = new
        if state:
            optimizer.state[new] = {"step": state["step"], **moments}


def clone_rows(params: dict[str, torch.nn.Parameter], index: torch.Tensor) -> dict[str, torch.Tensor]:
    """Copies of the Gaussians in `index` [M]; the copies and their originals both get the opacity
    1 - sqrt(1 - o), so the pair composites like the original (Bulo et al. 2024) and a densification
    does not brighten the image."""
    logits = params["opacity_logits"].detach()
    halved = inverse_sigmoid(1.0 - torch.sqrt((1.0 - torch.sigmoid(logits[index])).clamp_min(1e-6)))
    logits[index] = halved
    return {name: value.detach()[index].clone() for name, value in params.items()}


def split_rows(params: dict[str, torch.nn.Parameter], index: torch.Tensor,
               generator: torch.Generator) -> dict[str, torch.Tensor]:
    """SPLIT_COUNT children per Gaussian in `index` [M], drawn from it (CPU `generator`), with scales
    shrunk by 1 / (0.8 * SPLIT_COUNT)."""
    rows = {name: value.detach()[index].repeat_interleave(SPLIT_COUNT, dim=0) for name, value in params.items()}
    stds = torch.exp(rows["log_scales"])  # [M * SPLIT_COUNT, 3]
    noise = torch.randn(stds.shape, generator=generator).to(stds.device) * stds
    rotations = quat_to_rotmat(rows["quats"])  # [M * SPLIT_COUNT, 3, 3]
    rows["means"] = rows["means"] + (rotations @ noise[..., None])[..., 0]
    rows["log_scales"] = rows["log_scales"] - math.log(SPLIT_SHRINK)
    return rows


def reset_opacity(params: dict[str, torch.nn.Parameter], optimizer: torch.optim.Optimizer, value: float) -> None:
    """Clamp opacities to at most `value` and clear their Adam moments (3DGS opacity reset)."""
    logits = params["opacity_logits"].detach()
    reset = torch.minimum(logits, inverse_sigmoid(torch.tensor(value, device=logits.device)))
    params["opacity_logits"].data.copy_(reset)
    state = optimizer.state.get(params["opacity_logits"], {})
    for key in ("exp_avg", "exp_avg_sq"):
        if key in state:
            state[key].zero_()
