"""splat_train stage: fit 3D Gaussians to an sfm output (COLMAP model + undistorted images).

Writes `scene.ply` (Inria PLY, in the COLMAP world frame), `cameras.json` (every registered frame at
its original resolution in that frame; `held_out` lists the evaluation frames) and
`train_stats.json` (held-out PSNR curve, Gaussian counts, seconds per iteration).

Initial Gaussians: the SfM points plus up to `seed_share x max_gaussians` grey points spread uniformly in a
ball around the point the cameras look at (the object). SfM triangulates few points on thin or plain
parts (the sample plant's leaves had 6), and densification alone grows them unreliably; where SfM already fills
the ball, fewer seeds or none (`seed_count`).
"""
from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import torch

from stages.contract.errors import StageError
from stages.lib.gaussians.colmap import ColmapFrame
from stages.lib.gaussians.model import Gaussians, inverse_sigmoid
from stages.lib.gaussians.ply import write_ply
from stages.lib.gaussians.trainer import GaussianTrainer, TrainView, scene_extent, train
from stages.lib.geometry import camera_centres, look_at_point
from stages.records.cameras import CameraFrame, CamerasRecord
from stages.records.sfm import SfmRecord
from stages.splat_train.spec import SplatTrainConfig

if TYPE_CHECKING:  # the engine's object; not part of the stage's cache key
    from stages.engine.context import Context

log = logging.getLogger(__name__)


def load_view(images_dir: Path, frame: ColmapFrame, long_side: int, device: str) -> TrainView:
    """Read one frame's image and scale it (and K) so its long side is at most `long_side`."""
    path = images_dir / frame.name
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise StageError(f"{path}: image of registered frame {frame.name} is missing or unreadable")
    if bgr.shape[:2] != (frame.height, frame.width):
        raise StageError(f"{path}: image is {bgr.shape[1]}x{bgr.shape[0]} but its COLMAP camera says "
                         f"{frame.width}x{frame.height}")
    factor = min(1.0, long_side / max(frame.width, frame.height))
    width, height = max(1, round(frame.width * factor)), max(1, round(frame.height * factor))
    if (width, height) != (frame.width, frame.height):
        bgr = cv2.resize(bgr, (width, height), interpolation=cv2.INTER_AREA)
    K = frame.K.copy()
    K[0] *= width / frame.width  # with pixel centres at +0.5 the continuous frame scales exactly
    K[1] *= height / frame.height
    rgb = torch.from_numpy(np.ascontiguousarray(bgr[:, :, ::-1])).float() / 255.0
    return TrainView(frame.name, rgb.to(device), torch.from_numpy(frame.viewmat).float().to(device),
                     torch.from_numpy(K).float().to(device))


def object_seed_points(centre: np.ndarray, radius: float, count: int, seed: int) -> np.ndarray:
    """`count` points [count, 3] uniform in the ball of `radius` around `centre` [3] (seeded): grey
    initial Gaussians where the object stands, for the parts SfM left empty. Those on the object are
    trained, those in free space fade and are pruned; those no camera sees (under the floor) keep their
    faint opacity, and extract leaves them out."""
    rng = np.random.default_rng(seed)
    direction = rng.normal(size=(count, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    return centre[None] + direction * radius * rng.uniform(0, 1, (count, 1)) ** (1 / 3)


def object_ball(viewmats: np.ndarray) -> tuple[np.ndarray | None, float]:
    """The point the cameras of viewmats [V, 4, 4] look at [3] (None where their axes do not meet) and their mean
    distance to it (0.0 then): the centre and the unit of the focus region and of the seed ball."""
    centre = look_at_point(viewmats)
    distance = 0.0 if centre is None else float(np.linalg.norm(camera_centres(viewmats) - centre, axis=1).mean())
    return centre, distance


def points_in_ball(points: np.ndarray, centre: np.ndarray, radius: float) -> int:
    """How many of points [N, 3] lie within `radius` of centre [3]."""
    return int((np.linalg.norm(points - centre, axis=1) <= radius).sum())


def seed_count(budget: int, in_ball: int, fade_from: int, fade_to: int) -> int:
    """How many grey seed points to add: all `budget` (seed_share x max_gaussians) while the SfM points within the
    seed ball (`in_ball`) number at most `fade_from`, fading linearly to none at `fade_to` (> fade_from). Seeds are for
    what SfM leaves empty (the 125 sample captures: 320-1241 points there); where SfM already fills the ball they
    only cost time and held-out PSNR (the real plush dog, 2847-3268 points there: without seeds 1.75x faster per step
    and +1.9 dB held out, benchmarks/results/opensplat.md)."""
    if fade_to <= fade_from:
        raise ValueError(f"splat_train.seed_fade_to ({fade_to}) must exceed seed_fade_from ({fade_from})")
    share = min(1.0, max(0.0, (fade_to - in_ball) / (fade_to - fade_from)))
    return round(budget * share)


def split_held_out(names: list[str], holdout_every: int) -> list[bool]:
    """Held-out flags: every holdout_every-th frame, starting with the first (3DGS's llffhold)."""
    if holdout_every <= 0:
        return [False] * len(names)
    return [i % holdout_every == 0 for i in range(len(names))]


def cameras_record(frames: list[ColmapFrame], held_out: list[bool]) -> CamerasRecord:
    """cameras.json: every frame's K and world-to-camera viewmat at original resolution."""
    return CamerasRecord(frames[0].width, frames[0].height,
                         [CameraFrame(f.name, f.K, f.viewmat, f.width, f.height) for f in frames],
                         [f.name for f, h in zip(frames, held_out) if h])


def run(ctx: Context) -> dict:
    """Train the scene of `ctx.inputs["sfm"]` and write scene.ply, cameras.json, train_stats.json."""
    cfg = ctx.typed(SplatTrainConfig)
    sfm = SfmRecord.read(ctx.inputs["sfm"])
    sparse_dir, images_dir = sfm.sparse_dir, sfm.images_dir
    scene = sfm.scene()
    if scene.points.shape[0] < 2:
        raise StageError(f"{sparse_dir}: the COLMAP model has {scene.points.shape[0]} 3D points; need at least 2")

    held_out = split_held_out([f.name for f in scene.frames], cfg.holdout_every)
    views = [load_view(images_dir, frame, cfg.train_long_side, ctx.device)
             for frame in ctx.progress(scene.frames, desc=f"load[{ctx.item}]")]
    train_views = [v for v, h in zip(views, held_out) if not h]
    test_views = [v for v, h in zip(views, held_out) if h] or train_views
    if not train_views:
        raise StageError(f"{sparse_dir}: all {len(views)} frames are held out; lower holdout_every")

    viewmats = np.stack([frame.viewmat for frame in scene.frames])  # [V, 4, 4]
    extent = scene_extent(viewmats)
    centre, distance = object_ball(viewmats)
    focus = cfg.focus_radius * distance
    log.info("%s: %d train / %d held-out views at %dx%d, %d SfM points, extent %.3f, focus %s r=%.3f",
             ctx.item, len(train_views), len(test_views) if any(held_out) else 0, views[0].width,
             views[0].height, scene.points.shape[0], extent, None if centre is None else centre.tolist(), focus)

    seeds = np.zeros((0, 3))
    if cfg.seed_radius > 0 and distance > 0:
        radius = cfg.seed_radius * distance
        in_ball = points_in_ball(scene.points, centre, radius)
        count = seed_count(round(cfg.seed_share * cfg.max_gaussians), in_ball, cfg.seed_fade_from, cfg.seed_fade_to)
        log.info("%s: %d SfM points in the seed ball, %d seed points added", ctx.item, in_ball, count)
        seeds = object_seed_points(centre, radius, count, ctx.seed)
    init = Gaussians.from_points(np.concatenate([scene.points, seeds]),
                                 np.concatenate([scene.colors, np.full_like(seeds, 0.5)]), sh_degree=cfg.sh_degree)
    init.opacity_logits[len(scene.points):] = inverse_sigmoid(torch.tensor(cfg.seed_opacity))
    trainer = GaussianTrainer(init, cfg, extent, centre, focus, device=ctx.device, seed=ctx.seed)
    checkpoint = None
    if cfg.checkpoint_dir:
        fingerprint = hashlib.sha256(json.dumps([ctx.item, [f.name for f in scene.frames],
                                                 scene.points.shape[0]]).encode()).hexdigest()[:16]
        checkpoint = Path(cfg.checkpoint_dir) / f"{ctx.item}-{fingerprint}.pt"
    stats = train(trainer, train_views, test_views, checkpoint,
                  progress=lambda it: ctx.progress(it, desc=f"splat_train[{ctx.item}]"))

    write_ply(ctx.out / "scene.ply", trainer.gaussians().detach())
    cameras_record(scene.frames, held_out).write(ctx.out)
    stats.update({"num_train_views": len(train_views), "num_held_out": sum(held_out),
                  "train_resolution": [views[0].width, views[0].height], "scene_extent": extent,
                  "focus_centre": None if centre is None else centre.tolist(), "focus_radius": focus,
                  "num_sfm_points": int(scene.points.shape[0]), "num_seed_points": len(seeds)})
    (ctx.out / "train_stats.json").write_text(json.dumps(stats, indent=1))
    return {key: stats[key] for key in ("final_psnr", "best_psnr", "num_gaussians", "iterations_run",
                                        "seconds_per_iteration", "stopped_early", "num_held_out")}
