"""Stage train_maskrcnn: train torchvision's Mask R-CNN on one COCO dataset.

inputs:  `dataset` (folder with images/ + annotations.json).
writes:  model.pt (state dict + model config + category names, see stages.lib.detection.model.load_detector),
         train.json (loss curve, seconds, iterations, seconds per iteration).

Checkpoints: the engine gives every run an empty output folder, so partial progress is kept in a
separate folder, `checkpoint_dir` from the config. Every
`checkpoint_every` iterations `last.pt` is written there; a later run with the same config finds it
and continues from its iteration (same weights, optimiser state, data order and random streams).
"""
from __future__ import annotations

import json
import logging
import math
import os
import time
from multiprocessing import get_all_start_methods, get_context
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Iterator

import numpy as np
import torch

from stages.contract.choices import plain
from stages.contract.errors import StageError
from stages.lib.detection.data import Augmentation, CocoInstances
from stages.lib.detection.model import build_maskrcnn, count_parameters, save_detector, to_device
from stages.lib.detection.model_config import model_config_of
from stages.lib.masks.dice import add_mask_dice
from stages.lib.torch_files import load_torch_file
from stages.train_maskrcnn.spec import TrainMaskrcnnConfig

if TYPE_CHECKING:  # the engine's object; not part of the stage's cache key
    from stages.engine.context import Context

log = logging.getLogger(__name__)
CHECKPOINT_NAME = "last.pt"
# Settings that do not change the result: a checkpoint made under other values still resumes.
NOT_RESULT_KEYS = ("checkpoint_every", "checkpoint_dir", "threads", "loader_workers")


def lr_at(cfg: TrainMaskrcnnConfig, iteration: int, iterations: int) -> float:
    """Learning rate of the given 0-based iteration of a run of `iterations`."""
    if iteration < cfg.warmup_iterations:
        alpha = iteration / cfg.warmup_iterations
        return cfg.lr * (0.001 * (1 - alpha) + alpha)
    if cfg.schedule == "step":
        return cfg.lr * 0.1 ** sum(iteration >= f * iterations for f in (0.7, 0.9))
    span = max(iterations - cfg.warmup_iterations, 1)  # cosine
    progress = (iteration - cfg.warmup_iterations) / span
    return cfg.lr * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * progress)))


def make_optimizer(cfg: TrainMaskrcnnConfig, model: torch.nn.Module) -> torch.optim.Optimizer:
    """SGD with momentum or AdamW over the trainable parameters."""
    params = [p for p in model.parameters() if p.requires_grad]
    if cfg.optimizer == "adamw":
        return torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay)
    return torch.optim.SGD(params, lr=cfg.lr, momentum=cfg.momentum, weight_decay=cfg.weight_decay)


def batch_indices(num_images: int, batch_size: int, iteration: int, seed: int) -> list[int]:
    """Image indices of one iteration: epochs of seeded permutations, so a resumed run sees the same order."""
    out = []
    for slot in range(iteration * batch_size, (iteration + 1) * batch_size):
        epoch, position = divmod(slot, num_images)
        out.append(int(np.random.default_rng([seed, epoch]).permutation(num_images)[position]))
    return out


def result_config(cfg: TrainMaskrcnnConfig) -> dict:
    """The config keys that determine the trained weights (for checkpoint matching)."""
    return {k: v for k, v in plain(asdict(cfg)).items() if k not in NOT_RESULT_KEYS}


def load_checkpoint(path: Path, cfg: TrainMaskrcnnConfig, seed: int) -> dict | None:
    """The checkpoint at `path` if it exists, reads (a crash may have cut it short) and was made with the same
    config and seed, else None."""
    if not path.exists():
        return None
    try:
        state = load_torch_file(path, "checkpoint")
    except StageError as error:
        log.warning("ignoring %s; training starts over", error)
        return None
    if state.get("config") != result_config(cfg) or state.get("seed") != seed:
        log.warning("ignoring checkpoint %s: made with another config or seed", path)
        return None
    log.info("resuming from %s at iteration %d", path, state["iteration"])
    return state


class BatchSource(torch.utils.data.Dataset):
    """The training batches of one run, indexed by iteration: the same batch whichever process builds it.

    Item i: a list of batch_size (image [3, h, w], target dict) pairs, augmented with the random
    stream of (seed, iteration).
    """

    def __init__(self, dataset: CocoInstances, cfg: TrainMaskrcnnConfig, seed: int):
        self.dataset, self.batch_size, self.seed = dataset, cfg.batch_size, seed
        self.augmentation = Augmentation(cfg.hflip, cfg.scale_min, cfg.scale_max, cfg.colour_jitter, cfg.train_crop,
                                         cfg.closeup_share, tuple(cfg.closeup_fill))

    def __getitem__(self, iteration: int) -> list[tuple[torch.Tensor, dict]]:
        rng = np.random.default_rng([self.seed, 1, iteration])
        return [self.dataset.sample(index, rng, self.augmentation)
                for index in batch_indices(len(self.dataset), self.batch_size, iteration, self.seed)]


def _as_is(batch):
    return batch


def batch_stream(source: BatchSource, iterations: range, workers: int) -> Iterator[list[tuple[torch.Tensor, dict]]]:
    """The batches of `iterations` in order; built by `workers` processes ahead of use when workers > 0."""
    if workers <= 0:
        return (source[i] for i in iterations)
    # forked, as torch's DataLoader does by default on Linux (its workers run one thread); named explicitly
    # because a joblib sweep worker's default context ("loky") cannot start them
    context = get_context("fork" if "fork" in get_all_start_methods() else "spawn")
    return iter(torch.utils.data.DataLoader(source, batch_size=None, sampler=iterations, num_workers=workers,
                                            collate_fn=_as_is, prefetch_factor=4, multiprocessing_context=context))


def train_detector(model: torch.nn.Module, dataset: CocoInstances, cfg: TrainMaskrcnnConfig, *, seed: int,
                   device: str = "cpu", checkpoint_path: Path | None = None, progress=lambda it, **kw: it) -> dict:
    """Train `model` in place for cfg's budget on `dataset`; returns the training record.

    record: loss_curve [{"iteration", "lr", "loss", <loss terms>}], seconds, iterations, epochs,
    seconds_per_iteration (this run's iterations only), resumed_from (iteration or 0).
    """
    to_device(model, device).train()
    if cfg.bf16 and device == "cpu" and not torch.ops.mkldnn._is_mkldnn_bf16_supported():
        log.warning("train_maskrcnn.bf16: this CPU (%s) has no native bfloat16 (AVX512-BF16 or AMX), so autocast "
                    "emulates it: a training step took ~9x longer on an AVX2 CPU; leave bf16 off here",
                    torch.backends.cpu.get_cpu_capability())
    optimizer = make_optimizer(cfg, model)
    iterations = cfg.iterations(len(dataset))
    start, curve = 0, []
    resumed = load_checkpoint(checkpoint_path, cfg, seed) if checkpoint_path else None
    if resumed:
        model.load_state_dict(resumed["model"])
        optimizer.load_state_dict(resumed["optimizer"])
        start, curve = resumed["iteration"], resumed["loss_curve"]
    started = time.perf_counter()
    batches = batch_stream(BatchSource(dataset, cfg, seed), range(start, iterations), cfg.loader_workers)
    bar = progress(range(start, iterations), initial=start, total=iterations)
    for iteration, batch in zip(bar, batches):
        torch.manual_seed(seed * 1_000_003 + iteration)  # proposal sampling in the heads
        images = [image.to(device) for image, _ in batch]
        targets = [{k: v.to(device) for k, v in target.items()} for _, target in batch]
        lr = lr_at(cfg, iteration, iterations)
        for group in optimizer.param_groups:
            group["lr"] = lr
        with torch.autocast(torch.device(device).type, dtype=torch.bfloat16, enabled=cfg.bf16):
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
        if checkpoint_path and cfg.checkpoint_every > 0 and done % cfg.checkpoint_every == 0 and done < iterations:
            save_checkpoint(checkpoint_path, model, optimizer, cfg, seed, done, curve)
    seconds = time.perf_counter() - started
    run_iterations = iterations - start
    return {"loss_curve": curve, "seconds": seconds, "iterations": iterations, "epochs": cfg.epochs,
            "seconds_per_iteration": seconds / run_iterations if run_iterations else None, "resumed_from": start}


def save_checkpoint(path: Path, model, optimizer, cfg: TrainMaskrcnnConfig, seed: int, iteration: int,
                    curve: list) -> None:
    """Write the resumable state atomically (a killed write never leaves a broken last.pt)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    torch.save({"model": model.state_dict(), "optimizer": optimizer.state_dict(), "iteration": iteration,
                "loss_curve": curve, "config": result_config(cfg), "seed": seed}, tmp)
    os.replace(tmp, path)


def checkpoint_file(cfg: TrainMaskrcnnConfig) -> Path | None:
    """Where checkpoints go: in cfg.checkpoint_dir, else nowhere."""
    return Path(cfg.checkpoint_dir) / CHECKPOINT_NAME if cfg.checkpoint_dir else None


def run(ctx: Context) -> dict:
    """Train on ctx.inputs["dataset"]; write model.pt and train.json into ctx.out."""
    cfg = ctx.typed(TrainMaskrcnnConfig)
    torch.set_num_threads(cfg.threads or os.cpu_count() or 1)
    folder = Path(ctx.inputs["dataset"])
    try:
        dataset = CocoInstances(folder, cfg.image_size)
        torch.manual_seed(ctx.seed)  # initial weights of the new layers
        model = add_mask_dice(build_maskrcnn(model_config_of(cfg), len(dataset.category_names)), cfg.mask_dice_weight)
    except (ValueError, FileNotFoundError) as err:
        raise StageError(f"train_maskrcnn[{ctx.item}]: {err}") from err
    log.info("training %s on %d images of %s (%s), %s parameters", cfg.backbone, len(dataset), folder,
             dataset.category_names, count_parameters(model))
    record = train_detector(model, dataset, cfg, seed=ctx.seed, device=ctx.device,
                            checkpoint_path=checkpoint_file(cfg), progress=ctx.progress)
    save_detector(ctx.out / "model.pt", model.cpu(), model_config_of(cfg), dataset.category_names)
    record.update({"backbone": cfg.backbone, "images": len(dataset), "categories": dataset.category_names,
                   "device": ctx.device, "threads": torch.get_num_threads(), "parameters": count_parameters(model)})
    (ctx.out / "train.json").write_text(json.dumps(record, indent=1))
    tail = [c["loss"] for c in record["loss_curve"][-10:]]
    return {"final_loss": float(np.mean(tail)), "seconds": record["seconds"], "iterations": record["iterations"],
            "seconds_per_iteration": record["seconds_per_iteration"]}
