"""Densification of a 3DGS scene as a strategy beside the optimiser (after gsplat's `strategy/`): clone or
split Gaussians with high view-space gradients, prune faint and oversized ones, reset opacities.

"Model no more than a scene needs": densification is limited to `max_gaussians` (the highest gradients
win). Within `focus_radius` (a fraction of the mean camera distance) of the point the cameras look at (the
captured object) Gaussians densify above `grad_threshold` and oversized ones are pruned; the background
densifies above its own `background_grad_threshold` and is never size-pruned (its few large Gaussians
draw whole walls). A textured background (the sample plant's striped wall) otherwise stays a blur that
caps the held-out PSNR whatever the object looks like.

The trainer calls two hooks per iteration: `step_pre_backward` (keep the view-space gradients) and
`step_post_backward` (after the backward pass and the optimiser step: gather gradient statistics,
densify and prune every `densify_every` iterations, reset opacities every `opacity_reset_every`).
"""
from __future__ import annotations

import logging

import torch

from stages.lib.gaussians.densify_ops import clone_rows, edit_rows, reset_opacity, split_rows
from stages.lib.gaussians.rasterize import RenderOutput
from stages.lib.gaussians.train_config import DensifyConfig

log = logging.getLogger(__name__)

RESET_OPACITY = 0.01


class DensifyStrategy:
    """The densification of one scene: its settings, the scene's scale and focus region, and the
    per-Gaussian statistics gathered between densifications (grad_accum, grad_count, max_radii, [N])."""

    def __init__(self, cfg: DensifyConfig, num: int, extent: float, focus_centre: torch.Tensor | None,
                 focus_radius: float, device: str = "cpu", seed: int = 0):
        """num: the initial Gaussian count; extent: the 3DGS scene radius; focus_centre [3] and focus_radius
        (world units) the object's region; seed: the generator of split children."""
        self.cfg, self.extent, self.device = cfg, extent, device
        self.focus_centre, self.focus_radius = focus_centre, focus_radius
        self.generator = torch.Generator(device="cpu").manual_seed(seed)
        self._ndc_scales: dict[tuple[int, int], torch.Tensor] = {}
        self.reset_stats(num)

    def reset_stats(self, num: int) -> None:
        """Zero the statistics of `num` Gaussians."""
        self.grad_accum = torch.zeros(num, device=self.device)
        self.grad_count = torch.zeros(num, device=self.device)
        self.max_radii = torch.zeros(num, device=self.device)

    # ------------------------------------------------------------------------------------------ hooks
    def step_pre_backward(self, out: RenderOutput) -> None:
        """Before the backward pass: keep the gradient of the projected means (out.means2d [N, 2])."""
        if out.means2d.requires_grad and not out.means2d.is_leaf:
            out.means2d.retain_grad()

    def step_post_backward(self, params: dict[str, torch.nn.Parameter], optimizer: torch.optim.Optimizer,
                           iteration: int, iterations: int, out: RenderOutput, width: int, height: int) -> None:
        """After the backward pass and the optimiser step of `iteration` (of `iterations`) on a width x height
        view: gather the statistics, densify and prune, reset opacities when their schedules say so."""
        cfg = self.cfg
        self.accumulate(out.means2d.grad, out.radii, width, height)
        densifying = cfg.densify_from < iteration <= cfg.densify_until
        if densifying and iteration % cfg.densify_every == 0:
            self.densify_and_prune(params, optimizer, iteration, max(width, height))
        # Reset only while densifying and with at least half a reset period left to recover.
        last_reset = min(cfg.densify_until, iterations - cfg.opacity_reset_every // 2)
        if cfg.opacity_reset_every > 0 and iteration % cfg.opacity_reset_every == 0 and iteration <= last_reset:
            reset_opacity(params, optimizer, RESET_OPACITY)

    # ------------------------------------------------------------------------------------------ steps
    def accumulate(self, means2d_grad: torch.Tensor | None, radii: torch.Tensor, width: int, height: int) -> None:
        """Add one view's NDC-scaled view-space gradient norms (means2d_grad [N, 2]) of the Gaussians it
        sees (radii [N] > 0), and their largest screen radius.

        Written without a mask's indexing: selecting the visible rows (a boolean index, `.any()`) makes the
        host wait for a GPU every step. Adding 0 to the unseen rows' sums leaves them as they were (the sums are
        never negative), and an unseen row's radius is 0, so the maximum keeps its largest."""
        if means2d_grad is None:
            return
        visible = radii > 0  # [N]
        grad_norm = (means2d_grad * self._ndc_scale(width, height)).norm(dim=-1)  # [N]
        self.grad_accum += torch.where(visible, grad_norm, 0.0)
        self.grad_count += visible
        self.max_radii = torch.maximum(self.max_radii, radii.float())

    def _ndc_scale(self, width: int, height: int) -> torch.Tensor:
        """[2] (width / 2, height / 2) on the model's device, copied there once per image size."""
        if (width, height) not in self._ndc_scales:
            self._ndc_scales[(width, height)] = torch.tensor([width / 2.0, height / 2.0], device=self.device)
        return self._ndc_scales[(width, height)]

    def densify_and_prune(self, params: dict[str, torch.nn.Parameter], optimizer: torch.optim.Optimizer,
                          iteration: int, image_long_side: int) -> None:
        """Prune weak / oversized Gaussians, then clone (small) or split (large) high-gradient ones."""
        cfg = self.cfg
        num = params["means"].shape[0]
        max_scale = torch.exp(params["log_scales"].detach()).max(dim=1).values  # [N]
        focused = torch.ones(num, dtype=torch.bool, device=self.device)  # [N]
        if self.focus_centre is not None and self.focus_radius > 0:
            focused = (params["means"].detach() - self.focus_centre).norm(dim=1) <= self.focus_radius
        # Size pruning only near the object: the far background is drawn by few large Gaussians, and
        # removing them leaves holes that cost several dB.
        oversized = max_scale > cfg.prune_scale * self.extent
        if cfg.opacity_reset_every > 0 and iteration > cfg.opacity_reset_every:
            oversized |= self.max_radii > cfg.prune_screen * image_long_side
        prune = torch.sigmoid(params["opacity_logits"].detach()) < cfg.prune_opacity
        prune |= oversized & focused
        mean_grad = self.grad_accum / self.grad_count.clamp_min(1)  # [N]
        candidates = torch.where(focused, mean_grad >= cfg.grad_threshold,
                                 (mean_grad >= cfg.background_grad_threshold) & (cfg.background_grad_threshold > 0))
        candidates &= ~prune
        budget = max(min(cfg.max_gaussians - int((~prune).sum()), int(cfg.max_growth * num)), 0)
        chosen = torch.nonzero(candidates).squeeze(1)
        if chosen.numel() > budget:
            chosen = chosen[torch.argsort(mean_grad[chosen], descending=True)[:budget]]
        large = max_scale[chosen] > cfg.percent_dense * self.extent
        clone_idx, split_idx = chosen[~large], chosen[large]
        clones = clone_rows(params, clone_idx)
        children = split_rows(params, split_idx, self.generator)
        keep = ~prune
        keep[split_idx] = False  # split parents are replaced by their children
        edit_rows(params, optimizer, keep, {name: torch.cat([clones[name], children[name]]) for name in params})
        self.reset_stats(params["means"].shape[0])
        log.debug("iteration %d: densify %d -> %d (clone %d, split %d, pruned %d)", iteration, num,
                  params["means"].shape[0], clone_idx.numel(), split_idx.numel(), int(prune.sum()))

    # ------------------------------------------------------------------------------------- checkpoints
    def state_dict(self) -> dict:
        """The statistics and the split generator's state (for an exact resume)."""
        return {"grad_accum": self.grad_accum.cpu(), "grad_count": self.grad_count.cpu(),
                "max_radii": self.max_radii.cpu(), "generator": self.generator.get_state()}

    def load_state_dict(self, state: dict) -> None:
        """Restore a `state_dict`."""
        self.generator.set_state(state["generator"])
        self.grad_accum = state["grad_accum"].to(self.device)
        self.grad_count = state["grad_count"].to(self.device)
        self.max_radii = state["max_radii"].to(self.device)
