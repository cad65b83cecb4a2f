"""Stage train_maskrcnn: train torchvision's Mask R-CNN on one COCO dataset.

inputs:  `dataset` (folder with images/ + annotations.json), optional `resume` (a checkpoint folder).
writes:  model.pt (state dict + model config + category names, see stages.detection.model.load_detector),
         train.json (loss curve, seconds, iterations, seconds per iteration).

Checkpoints: the engine gives every run an empty output folder, so partial progress is kept in a
separate folder: `checkpoint_dir` from the config, else `ctx.inputs["resume"]`. Every
`checkpoint_every` iterations `last.pt` is written there; a later run with the same config finds it
and continues from its iteration (same weights, optimiser state, data order and random streams).
"""
from __future__ import annotations

import json
import logging
import math
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from stages.context import Context, StageError
from stages.detection.data import Augmentation, CocoInstances
from stages.detection.model import ModelConfig, build_maskrcnn, count_parameters, model_config_of, save_detector

log = logging.getLogger(__name__)
CHECKPOINT_NAME = "last.pt"
# Settings that do not change the result: a checkpoint made under other values still resumes.
NOT_RESULT_KEYS = ("checkpoint_every", "checkpoint_dir", "threads")


@dataclass
class TrainMaskrcnnConfig(ModelConfig):
    """Detector (ModelConfig fields) plus training settings, sized for a 2-core CPU.

    The default run (lite0, 320 px, batch 2, 250 iterations) took 3.8 minutes with 2 threads on an
    idle CPU (benchmarks/results/detector.md); expect several times more on a loaded machine.
    lr schedule: linear warm-up from lr * 0.001 over `warmup_iterations`, then `schedule`
    "cosine" (to lr * 0.05) or "step" (x0.1 at 70 % and 90 % of the budget).
    threads: torch CPU threads, 0 = all cores.
    """

    iterations: int = 250
    batch_size: int = 2
    optimizer: str = "sgd"
    lr: float = 0.02
    momentum: float = 0.9
    weight_decay: float = 1e-4
    warmup_iterations: int = 30
    schedule: str = "cosine"
    grad_clip: float = 5.0
    hflip: bool = True
    scale_min: float = 0.75
    scale_max: float = 1.25
    colour_jitter: float = 0.2
    checkpoint_every: int = 50
    checkpoint_dir: str = ""
    threads: int = 0


def lr_at(cfg: TrainMaskrcnnConfig, iteration: int) -> float:
    """Learning rate of the given 0-based iteration."""
    if iteration < cfg.warmup_iterations:
        alpha = iteration / cfg.warmup_iterations
        return cfg.lr * (0.001 * (1 - alpha) + alpha)
    if cfg.schedule == "cosine":
        span = max(cfg.iterations - cfg.warmup_iterations, 1)
        progress = (iteration - cfg.warmup_iterations) / span
        return cfg.lr * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * progress)))
    if cfg.schedule == "step":
        return cfg.lr * 0.1 ** sum(iteration >= f * cfg.iterations for f in (0.7, 0.9))
    raise ValueError(f"schedule must be 'cosine' or 'step', got {cfg.schedule!r}")


def make_optimizer(cfg: TrainMaskrcnnConfig, model: torch.nn.Module) -> torch.optim.Optimizer:
    """SGD with momentum or AdamW over the trainable parameters."""
    params = [p for p in model.parameters() if p.requires_grad]
    if cfg.optimizer == "sgd":
        return torch.optim.SGD(params, lr=cfg.lr, momentum=cfg.momentum, weight_decay=cfg.weight_decay)
    if cfg.optimizer == "adamw":
        return torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay)
    raise ValueError(f"optimizer must be 'sgd' or 'adamw', got {cfg.optimizer!r}")


def batch_indices(num_images: int, batch_size: int, iteration: int, seed: int) -> list[int]:
    """Image indices of one iteration: epochs of seeded permutations, so a resumed run sees the same order."""
    out = []
    for slot in range(iteration * batch_size, (iteration + 1) * batch_size):
        epoch, position = divmod(slot, num_images)
        out.append(int(np.random.default_rng([seed, epoch]).permutation(num_images)[position]))
    return out


def result_config(cfg: TrainMaskrcnnConfig) -> dict:
    """The config keys that determine the trained weights (for checkpoint matching)."""
    return {k: v for k, v in asdict(cfg).items() if k not in NOT_RESULT_KEYS}


def load_checkpoint(path: Path, cfg: TrainMaskrcnnConfig, seed: int) -> dict | None:
    """The checkpoint at `path` if it exists and was made with the same config and seed, else None."""
    if not path.is_file():
        return None
    state = torch.load(path, map_location="cpu", weights_only=True)
    if state.get("config") != result_config(cfg) or state.get("seed") != seed:
        log.warning("ignoring checkpoint %s: made with another config or seed", path)
        return None
    log.info("resuming from %s at iteration %d", path, state["iteration"])
    return state


def train_detector(model: torch.nn.Module, dataset: CocoInstances, cfg: TrainMaskrcnnConfig, *, seed: int,
                   device: str = "cpu", checkpoint_path: Path | None = None, progress=lambda it, **kw: it) -> dict:
    """Train `model` in place for cfg.iterations; returns the training record.

    record: loss_curve [{"iteration", "lr", "loss", <loss terms>}], seconds, iterations,
    seconds_per_iteration (this run's iterations only), resumed_from (iteration or 0).
    """
    model.to(device).train()
    optimizer = make_optimizer(cfg, model)
    augmentation = Augmentation(cfg.hflip, cfg.scale_min, cfg.scale_max, cfg.colour_jitter)
    start, curve = 0, []
    resumed = load_checkpoint(checkpoint_path, cfg, seed) if checkpoint_path else None
    if resumed:
        model.load_state_dict(resumed["model"])
        optimizer.load_state_dict(resumed["optimizer"])
        start, curve = resumed["iteration"], resumed["loss_curve"]
    started = time.perf_counter()
    bar = progress(range(start, cfg.iterations), initial=start, total=cfg.iterations)
    for iteration in bar:
        rng = np.random.default_rng([seed, 1, iteration])
        torch.manual_seed(seed * 1_000_003 + iteration)  # proposal sampling in the heads
        images, targets = [], []
        for index in batch_indices(len(dataset), cfg.batch_size, iteration, seed):
            image, target = dataset.sample(index, rng, augmentation)
            images.append(image.to(device))
            targets.append({k: v.to(device) for k, v in target.items()})
        lr = lr_at(cfg, iteration)
        for group in optimizer.param_groups:
            group["lr"] = lr
        losses = model(images, targets)
        loss = sum(losses.values())
        if not torch.isfinite(loss):
            raise StageError(f"train_maskrcnn: loss became {loss.item()} at iteration {iteration} "
                             f"(lr {lr:g}); lower lr or raise warmup_iterations")
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_([p for p in model.parameters() if p.requires_grad], cfg.grad_clip)
        optimizer.step()
        curve.append({"iteration": iteration, "lr": lr, "loss": loss.item(),
                      **{k: v.item() for k, v in losses.items()}})
        if hasattr(bar, "set_postfix"):
            bar.set_postfix(loss=f"{loss.item():.3f}", mask=f"{losses['loss_mask'].item():.3f}")
        done = iteration + 1
        if checkpoint_path and cfg.checkpoint_every > 0 and done % cfg.checkpoint_every == 0 and done < cfg.iterations:
            save_checkpoint(checkpoint_path, model, optimizer, cfg, seed, done, curve)
    seconds = time.perf_counter() - started
    run_iterations = cfg.iterations - start
    return {"loss_curve": curve, "seconds": seconds, "iterations": cfg.iterations,
            "seconds_per_iteration": seconds / run_iterations if run_iterations else None, "resumed_from": start}


def save_checkpoint(path: Path, model, optimizer, cfg: TrainMaskrcnnConfig, seed: int, iteration: int,
                    curve: list) -> None:
    """Write the resumable state atomically (a killed write never leaves a broken last.pt)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    torch.save({"model": model.state_dict(), "optimizer": optimizer.state_dict(), "iteration": iteration,
                "loss_curve": curve, "config": result_config(cfg), "seed": seed}, tmp)
    os.replace(tmp, path)


def checkpoint_file(cfg: TrainMaskrcnnConfig, ctx: Context) -> Path | None:
    """Where checkpoints go: cfg.checkpoint_dir, else ctx.inputs["resume"], else nowhere."""
    folder = cfg.checkpoint_dir or ctx.inputs.get("resume")
    return Path(folder) / CHECKPOINT_NAME if folder else None


def run(ctx: Context) -> dict:
    """Train on ctx.inputs["dataset"]; write model.pt and train.json into ctx.out."""
    cfg = TrainMaskrcnnConfig(**ctx.params)
    torch.set_num_threads(cfg.threads or os.cpu_count() or 1)
    folder = Path(ctx.inputs["dataset"])
    try:
        dataset = CocoInstances(folder, cfg.image_size)
        torch.manual_seed(ctx.seed)  # initial weights of the new layers
        model = build_maskrcnn(model_config_of(cfg), len(dataset.category_names))
    except (ValueError, FileNotFoundError) as err:
        raise StageError(f"train_maskrcnn[{ctx.item}]: {err}") from err
    log.info("training %s on %d images of %s (%s), %s parameters", cfg.backbone, len(dataset), folder,
             dataset.category_names, count_parameters(model))
    record = train_detector(model, dataset, cfg, seed=ctx.seed, device=ctx.device,
                            checkpoint_path=checkpoint_file(cfg, ctx), progress=ctx.progress)
    save_detector(ctx.out / "model.pt", model.cpu(), model_config_of(cfg), dataset.category_names)
    record.update({"backbone": cfg.backbone, "images": len(dataset), "categories": dataset.category_names,
                   "device": ctx.device, "threads": torch.get_num_threads(), "parameters": count_parameters(model)})
    (ctx.out / "train.json").write_text(json.dumps(record, indent=1))
    tail = [c["loss"] for c in record["loss_curve"][-10:]]
    return {"final_loss": float(np.mean(tail)), "seconds": record["seconds"], "iterations": record["iterations"],
            "seconds_per_iteration": record["seconds_per_iteration"]}
