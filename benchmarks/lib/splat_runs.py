"""Trained splats for the benchmarks: splat_train run into a fresh folder with its wall seconds per iteration, and a
trained scene's held-out PSNR rendered as splat_train evaluates it."""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Collection

import torch

from stages.engine.context import Context
from stages.lib.gaussians.ply import read_ply
from stages.lib.gaussians.rasterize import render
from stages.lib.gaussians.trainer import psnr
from stages.records.cameras import CamerasRecord
from stages.records.sfm import SfmRecord
from stages.splat_train import run as splat_train


@dataclass
class TimedContext(Context):
    """A Context that records, for every training iteration, the wall seconds from the start of the training
    loop to its end (held-out evaluations included): the x axis of PSNR-against-seconds curves."""

    iteration_ends: list[float] = field(default_factory=list)

    def progress(self, iterable, **kwargs):
        bar = super().progress(iterable, **kwargs)
        return self._timed(bar) if str(kwargs.get("desc", "")).startswith("splat_train") else bar

    def _timed(self, iterable):
        started = time.perf_counter()
        for item in iterable:
            yield item
            self.iteration_ends.append(time.perf_counter() - started)


def train_timed(sfm: Path, out: Path, params: dict, seed: int, device: str) -> dict:
    """Run splat_train into the new folder `out`; its wall seconds, figures and PSNR-against-seconds curve
    ([seconds, iteration, held-out PSNR] per evaluation). `seconds_per_iteration` is the training steps' own
    time (densification included, held-out evaluations not)."""
    out.mkdir(parents=True)
    ctx = TimedContext(stage="splat_train", item=out.name, params=params, inputs={"sfm": sfm}, out=out, seed=seed,
                       device=device)
    started = time.perf_counter()
    metrics = splat_train.run(ctx)
    wall = time.perf_counter() - started
    stats = json.loads((out / "train_stats.json").read_text())
    ends = ctx.iteration_ends
    curve = [[round(ends[it - 1] if 0 < it <= len(ends) else (0.0 if it == 0 else wall), 2), it, round(value, 3)]
             for it, value in stats["psnr_curve"]]
    return {"wall_s": round(wall, 1), "train_s": round(stats["train_seconds"], 1),
            "seconds_per_iteration": round(metrics["seconds_per_iteration"], 5),
            "iterations_run": metrics["iterations_run"], "num_gaussians": metrics["num_gaussians"],
            "train_resolution": stats["train_resolution"], "held_out_psnr": metrics["final_psnr"], "curve": curve}


def held_out_psnr(ply: Path, sfm: Path, held_out: Collection[str], long_side: int, device: str) -> float:
    """Mean PSNR of the Gaussians of `ply` (an Inria PLY in the COLMAP world frame of the sfm folder `sfm`) over
    the frames named in `held_out`, loaded with their long side at most `long_side` as splat_train loads them
    (black background, every SH band of the file)."""
    record = SfmRecord.read(sfm)
    gaussians = read_ply(ply).to(device)
    values = []
    for frame in (f for f in record.scene().frames if f.name in set(held_out)):
        view = splat_train.load_view(record.images_dir, frame, long_side, device)
        with torch.no_grad():
            values.append(psnr(render(gaussians, view.viewmat, view.K, view.width, view.height).rgb, view.image))
    if not values:
        raise ValueError(f"{sfm}: none of the {len(held_out)} held-out frames is registered there")
    return round(sum(values) / len(values), 3)


def run_held_out_psnr(out: Path, sfm: Path, long_side: int, device: str) -> float:
    """`held_out_psnr` of a splat_train folder `out` (its scene.ply, over the held-out frames of its cameras.json)."""
    return held_out_psnr(out / "scene.ply", sfm, CamerasRecord.read(out).held_out, long_side, device)
