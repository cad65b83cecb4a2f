"""3DGS optimisation: Adam with per-parameter learning rates, L1 + D-SSIM, SH degree ramp, held-out PSNR
with early stop on plateau, and checkpoints that resume bit-for-bit. Densification (clone / split,
pruning, opacity reset, the Gaussian budget and the focus region) is the strategy of
stages/lib/gaussians/strategy.py, called before and after each backward pass.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Iterable

import numpy as np
import torch
import torch.nn.functional as F

from stages.lib.gaussians.losses import photometric_loss
from stages.lib.gaussians.model import Gaussians
from stages.lib.gaussians.rasterize import render
from stages.lib.gaussians.strategy import DensifyStrategy
from stages.lib.gaussians.train_config import TrainConfig
from stages.lib.geometry import camera_centres

log = logging.getLogger(__name__)

PARAM_NAMES = ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")


@dataclass
class TrainView:
    """One posed image at training resolution."""

    name: str
    image: torch.Tensor  # [H, W, 3] float32 in [0, 1]
    viewmat: torch.Tensor  # [4, 4] world-to-camera
    K: torch.Tensor  # [3, 3]

    @property
    def width(self) -> int:
        return self.image.shape[1]

    @property
    def height(self) -> int:
        return self.image.shape[0]


def scene_extent(viewmats: np.ndarray) -> float:
    """3DGS scene radius of viewmats [V, 4, 4]: 1.1 x the largest camera distance from the cameras' mean
    (1.0 if degenerate)."""
    centres = camera_centres(np.asarray(viewmats, dtype=np.float64))  # [V, 3]
    radius = float(np.linalg.norm(centres - centres.mean(axis=0), axis=1).max()) * 1.1
    return radius if radius > 1e-6 else 1.0


def learning_rates(cfg: TrainConfig, extent: float) -> dict[str, float]:
    """Adam's starting learning rate of each parameter (PARAM_NAMES); the means' scale with the scene's extent."""
    return {"means": cfg.lr_means * extent, "log_scales": cfg.lr_scales, "quats": cfg.lr_quats,
            "opacity_logits": cfg.lr_opacity, "sh_dc": cfg.lr_sh_dc, "sh_rest": cfg.lr_sh_rest}


def psnr_of_mse(mse: float) -> float:
    """PSNR in dB of a mean squared error of images in [0, 1] (floored at 1e-10: 100 dB)."""
    return 10.0 * math.log10(1.0 / max(mse, 1e-10))


def psnr(prediction: torch.Tensor, target: torch.Tensor) -> float:
    """PSNR in dB of images in [0, 1] (any matching shapes). The mean is numpy's (one thread, pairwise in
    float64): torch's CPU mean splits the sum by thread count, and the early stop compares these values."""
    error = (prediction.detach().clamp(0, 1) - target).cpu().numpy().astype(np.float64)
    return psnr_of_mse(float(np.mean(np.square(error))))


class GaussianTrainer:
    """Owns the optimised parameters, the Adam state, the schedule and the densification strategy of one scene."""

    def __init__(self, init: Gaussians, cfg: TrainConfig, extent: float, focus_centre: np.ndarray | None,
                 focus_radius: float, device: str = "cpu", seed: int = 0):
        """extent: the 3DGS scene radius; focus_centre [3] (numpy or torch) and focus_radius: the region
        where the object is (stages/lib/gaussians/strategy.py); seed: the view order and the split children."""
        self.cfg, self.extent, self.device = cfg, extent, device
        self.seed = seed
        g = init.with_sh_degree(cfg.sh_degree).to(device)
        self.params = {name: torch.nn.Parameter(value.detach().clone().contiguous()) for name, value in zip(
            PARAM_NAMES, (g.means, g.log_scales, g.quats, g.opacity_logits, g.sh[:, :1], g.sh[:, 1:]))}
        base_lr = learning_rates(cfg, extent)
        self.optimizer = torch.optim.Adam(  # fused: one kernel per parameter instead of ~10 operations
            [{"params": [self.params[name]], "lr": base_lr[name], "name": name} for name in PARAM_NAMES],
            lr=0.0, eps=1e-15, fused=torch.device(device).type in ("cpu", "cuda"))
        centre = None if focus_centre is None else torch.as_tensor(focus_centre, dtype=torch.float32, device=device)
        self.strategy = DensifyStrategy(cfg, self.num, extent, centre, focus_radius, device, seed)
        self.iteration = 0
        self.active_sh_degree = 0

    # ------------------------------------------------------------------------------- model access
    @property
    def num(self) -> int:
        return self.params["means"].shape[0]

    def gaussians(self) -> Gaussians:
        """The current model (differentiable w.r.t. the parameters; quaternions normalised)."""
        p = self.params
        return Gaussians(p["means"], p["log_scales"], F.normalize(p["quats"], dim=-1), p["opacity_logits"],
                         torch.cat([p["sh_dc"], p["sh_rest"]], dim=1))

    # ------------------------------------------------------------------------------- one step
    def _means_lr(self) -> float:
        """Exponential decay from lr_means to lr_means_final over the run (x scene extent)."""
        t = min(self.iteration / max(self.cfg.iterations, 1), 1.0)
        return self.extent * math.exp((1 - t) * math.log(self.cfg.lr_means) + t * math.log(self.cfg.lr_means_final))

    def render(self, view: TrainView, gaussians: Gaussians | None = None):
        """Render the current model from a view at its resolution (black background)."""
        return render(gaussians or self.gaussians(), view.viewmat, view.K, view.width, view.height,
                      sh_degree=self.active_sh_degree, backend=self.cfg.backend)

    def step(self, view: TrainView) -> torch.Tensor:
        """One optimisation iteration on one view: render, loss, backward, Adam, then the strategy's
        densification. Returns the loss, a detached scalar tensor on the model's device: reading it (`float`)
        waits for the device, so on a GPU the caller reads it only when it reports."""
        cfg = self.cfg
        self.iteration += 1
        for group in self.optimizer.param_groups:
            if group["name"] == "means":
                group["lr"] = self._means_lr()
        if cfg.sh_degree_every > 0 and self.iteration % cfg.sh_degree_every == 0:
            self.active_sh_degree = min(self.active_sh_degree + 1, cfg.sh_degree)
        out = self.render(view)
        self.strategy.step_pre_backward(out)
        loss = photometric_loss(out.rgb, view.image, cfg.lambda_dssim)
        loss.backward()
        with torch.no_grad():
            self.optimizer.step()
            self.optimizer.zero_grad(set_to_none=True)
            self.strategy.step_post_backward(self.params, self.optimizer, self.iteration, cfg.iterations, out,
                                             view.width, view.height)
        return loss.detach()

    # ------------------------------------------------------------------------------- checkpoints
    def state_dict(self) -> dict:
        """Everything needed to continue training exactly (parameters, Adam, densification statistics, RNG)."""
        return {
            "iteration": self.iteration, "active_sh_degree": self.active_sh_degree,
            "params": {name: p.detach().cpu() for name, p in self.params.items()},
            "optimizer": self.optimizer.state_dict(), "densify": self.strategy.state_dict(),
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore a `state_dict` (the parameter count may differ from the initial model)."""
        self.iteration, self.active_sh_degree = state["iteration"], state["active_sh_degree"]
        for group in self.optimizer.param_groups:
            new = torch.nn.Parameter(state["params"][group["name"]].to(self.device))
            group["params"][0] = new
            self.params[group["name"]] = new
        self.optimizer.state.clear()
        self.optimizer.load_state_dict(state["optimizer"])
        self.strategy.load_state_dict(state["densify"])


def evaluate(trainer: GaussianTrainer, views: list[TrainView]) -> float:
    """Mean PSNR (dB) of the current model over views. On the CPU each view's error is averaged by `psnr`; on a GPU
    in float64 on the device and read back once for all views (a copy and a wait per view took longer than the
    renders: 14 ms a view at 739x492 on an H200)."""
    with torch.no_grad():
        g = trainer.gaussians().detach()
        if g.device.type == "cpu":
            return sum(psnr(trainer.render(view, g).rgb, view.image) for view in views) / len(views)
        errors = torch.stack([(trainer.render(view, g).rgb.clamp(0, 1) - view.image).double().square().mean()
                              for view in views])  # [V]
        return sum(psnr_of_mse(mse) for mse in errors.tolist()) / len(views)


def train(trainer: GaussianTrainer, train_views: list[TrainView], test_views: list[TrainView],
          checkpoint_path: Path | None = None,
          progress: Callable[[Iterable], Iterable] = lambda it: it) -> dict:
    """Run (or continue) optimisation to cfg.iterations; returns the statistics dict.

    The view order is a random permutation per epoch, a function of (seed, iteration), so a run resumed
    from a checkpoint replays the same views as an uninterrupted run. `checkpoint_path`, when
    given, is loaded if it exists and written every cfg.checkpoint_every iterations and at the end.
    """
    cfg = trainer.cfg
    stats = {"psnr_curve": [], "gaussian_curve": [], "loss_curve": [], "train_seconds": 0.0,
             "resumed_from": None, "stopped_early": False}
    if checkpoint_path is not None and Path(checkpoint_path).is_file():
        saved = torch.load(checkpoint_path, map_location="cpu", weights_only=False)
        trainer.load_state_dict(saved["trainer"])
        stats = saved["stats"]
        stats["resumed_from"] = trainer.iteration
        log.info("resumed from %s at iteration %d (%d Gaussians)", checkpoint_path, trainer.iteration, trainer.num)

    def save() -> None:
        if checkpoint_path is not None:
            Path(checkpoint_path).parent.mkdir(parents=True, exist_ok=True)
            tmp = Path(checkpoint_path).with_suffix(".tmp")
            torch.save({"trainer": trainer.state_dict(), "stats": stats}, tmp)
            tmp.replace(checkpoint_path)

    if trainer.iteration == 0:
        stats["psnr_curve"].append([0, evaluate(trainer, test_views)])
        stats["gaussian_curve"].append([0, trainer.num])
    losses: list[torch.Tensor] = []  # since the last evaluation, read then (one wait for a GPU, not one a step)
    for _ in progress(range(trainer.iteration, cfg.iterations)):
        view = train_views[view_index(trainer.seed, trainer.iteration, len(train_views))]
        started = time.perf_counter()
        losses.append(trainer.step(view))
        stats["train_seconds"] += time.perf_counter() - started
        it = trainer.iteration
        if it % cfg.eval_every == 0 or it == cfg.iterations:
            value = evaluate(trainer, test_views)
            stats["psnr_curve"].append([it, value])
            stats["gaussian_curve"].append([it, trainer.num])
            mean_loss = sum(torch.stack(losses).tolist()) / len(losses)  # one copy; torch's sum splits by thread count
            stats["loss_curve"].append([it, round(mean_loss, 6)])
            losses = []
            log.info("iteration %d: held-out PSNR %.2f dB, %d Gaussians", it, value, trainer.num)
            if _plateaued(stats["psnr_curve"], cfg):
                stats["stopped_early"] = True
                log.info("held-out PSNR plateaued; stopping at iteration %d", it)
                break
        if cfg.checkpoint_every > 0 and it % cfg.checkpoint_every == 0:
            save()
    save()
    stats.update({
        "iterations_run": trainer.iteration,
        "num_gaussians": trainer.num,
        "final_psnr": stats["psnr_curve"][-1][1] if stats["psnr_curve"] else None,
        "best_psnr": max((p for _, p in stats["psnr_curve"]), default=None),
        "seconds_per_iteration": stats["train_seconds"] / max(trainer.iteration, 1),
        "config": asdict(cfg),
    })
    return stats


def view_index(seed: int, iteration: int, num_views: int) -> int:
    """Training view for an iteration: position iteration % V of epoch iteration // V's permutation."""
    epoch, position = divmod(iteration, num_views)
    order = torch.randperm(num_views, generator=torch.Generator().manual_seed(seed * 1_000_003 + epoch))
    return int(order[position])


def _plateaued(curve: list[list[float]], cfg: TrainConfig) -> bool:
    """True when, after densification, the last plateau_patience evaluations gained less than
    plateau_min_delta over the best evaluation before them."""
    settled = [p for it, p in curve if it >= cfg.densify_until]
    if cfg.plateau_patience <= 0 or len(settled) <= cfg.plateau_patience:
        return False
    return max(settled[-cfg.plateau_patience:]) < max(settled[:-cfg.plateau_patience]) + cfg.plateau_min_delta
