"""Stage `sample`: render the embedded mini-benchmark ("mini-IBSYD") with its own ray tracer.

Writes object capture videos with ground truth, background and in-domain photos with metric depth
and support maps, two COCO test sets (camera A like the capture, camera B another camera), a walk through
the in-domain rooms (a video with per-frame depth, rendered last from its own random streams, so that the other
files are the same with or without it; no test photo is one of its frames) and contact sheets. Everything is a pure
function of the config: regenerating gives identical files (except the timings in sample.json). See
docs/stage_contracts.md, section "sample".
"""
from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import asdict
from functools import lru_cache, partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from stages.contract.errors import StageError
from stages.lib.coco import CocoBuilder
from stages.lib.geometry import fov_intrinsics
from stages.lib.processes import spawn_pool
from stages.lib.sample_scene.backgrounds import render_background
from stages.lib.sample_scene.capture import render_capture
from stages.lib.sample_scene.contact import contact_sheet, depth_colour, overlay
from stages.lib.sample_scene.objects import OBJECT_CLASSES, build_object
from stages.lib.sample_scene.raytrace import RAY_THREADS, TracedScene
from stages.lib.sample_scene.rooms import Room, make_room, scene_lighting
from stages.lib.sample_scene.testsets import camera_k, class_sets, render_test_image
from stages.lib.sample_scene.videos import write_mp4
from stages.lib.sample_scene.walk import chunks as walk_chunks, render_frame, room_frames, room_walk
from stages.records import sample_layout as layout
from stages.records.capture_truth import CaptureTruth
from stages.sample.spec import SampleConfig

if TYPE_CHECKING:  # the engine's object; not part of the stage's cache key
    from stages.engine.context import Context

log = logging.getLogger(__name__)
THUMB_WIDTH = 213


def _validate(cfg: SampleConfig) -> list[dict]:
    """Check the config; returns the object specs as plain dicts. Raises StageError naming the field."""
    objects = [dict(o) for o in cfg.objects]
    for spec in objects:
        if spec.get("name") not in OBJECT_CLASSES:
            raise StageError(f"sample: objects entry {spec} has an unknown name; the sample renders {list(OBJECT_CLASSES)}")
        if not float(spec.get("height_m", 0)) > 0:
            raise StageError(f"sample: object {spec['name']!r} needs a positive height_m, got {spec.get('height_m')}")
    if len({o["name"] for o in objects}) != len(objects) or not objects:
        raise StageError(f"sample: objects must be a non-empty list of distinct names, got {[o['name'] for o in objects]}")
    for name in ("width", "height", "num_frames", "supersample", "photos_per_room", "test_rooms", "workers"):
        if int(getattr(cfg, name)) < 1:
            raise StageError(f"sample: {name} must be >= 1, got {getattr(cfg, name)}")
    for name in ("num_backgrounds", "num_indomain", "num_test", "walk_seconds"):
        if getattr(cfg, name) < 0:
            raise StageError(f"sample: {name} must be >= 0, got {getattr(cfg, name)}")
    return objects


def _write_png(path: Path, image: np.ndarray) -> None:
    """Write an RGB uint8 [H, W, 3] or a single-channel [H, W] image as PNG."""
    path.parent.mkdir(parents=True, exist_ok=True)
    data = image[..., ::-1] if image.ndim == 3 else image
    if not cv2.imwrite(str(path), np.ascontiguousarray(data)):
        raise StageError(f"sample: could not write {path}")


def _write_json(path: Path, data: Any) -> None:
    path.write_text(json.dumps(data, indent=1))


def _millimetres(depth: np.ndarray) -> np.ndarray:
    """Depth float32 [H, W] metres as a depth sidecar's uint16 [H, W] millimetres (0 = none)."""
    return np.clip(np.round(depth * 1000), 0, 65535).astype(np.uint16)


def _thumb(image: np.ndarray) -> np.ndarray:
    """A contact-sheet thumbnail (213 px wide) of an RGB uint8 image."""
    return cv2.resize(image, (THUMB_WIDTH, round(image.shape[0] * THUMB_WIDTH / image.shape[1])), interpolation=cv2.INTER_AREA)


@lru_cache(maxsize=None)
def _room(seed: int, family: str, index: int) -> Room:
    """Room `index` of a family ("generic" backgrounds or "test" rooms), cached per process."""
    return make_room(np.random.default_rng([seed, 21 if family == "generic" else 31, index]))


@lru_cache(maxsize=None)
def _models(seed: int, objects: tuple[tuple[str, float], ...]) -> list:
    """The object meshes of every class, cached per process."""
    return [build_object(name, height_m, seed) for name, height_m in objects]


def _object_job(cfg: SampleConfig, out: Path, spec: dict) -> dict:
    """Render and write one object's capture (video, masks, points, gt.json)."""
    name, height_m = spec["name"], float(spec["height_m"])
    folder = out / layout.object_folder(name)
    (out / layout.capture_masks(name)).mkdir(parents=True, exist_ok=True)
    capture = render_capture(name, height_m, cfg.seed, cfg.width, cfg.height, cfg.num_frames, cfg.supersample)
    write_mp4(out / layout.video(name), capture["frames"], cfg.fps)
    for index, mask in enumerate(capture["masks"]):
        _write_png(out / layout.capture_masks(name) / f"{index:04d}.png", mask.astype(np.uint8) * 255)
    np.save(folder / "object_points.npy", capture["object_points"])
    CaptureTruth(name, height_m, capture["K"], cfg.width, cfg.height, cfg.fps, dict(enumerate(capture["viewmats"])),
                 np.array([0.0, 0.0, 1.0]), np.zeros(3), "object_points.npy", capture["scene"].support,
                 capture["scene"].radius, cfg.seed).write(folder)
    step = max(1, len(capture["frames"]) // 6)
    pairs = list(zip(capture["frames"][::step], capture["masks"][::step]))[:6]
    return {"thumbs": [_thumb(overlay(f, m.astype(np.int32))) for f, m in pairs]}


def _background_job(cfg: SampleConfig, out: Path, kind: str, index: int) -> dict:
    """Render and write one generic or in-domain background with depth, support map and metadata."""
    family = "generic" if kind == "generic" else "test"
    photo_id = layout.background_ids(cfg, kind)[index]
    rooms = max(1, math.ceil(cfg.num_backgrounds / cfg.photos_per_room)) if kind == "generic" else cfg.test_rooms
    closeup = kind == "generic" and index in layout.closeup_indices(cfg.num_backgrounds, cfg.wall_closeup_fraction)
    K = fov_intrinsics(cfg.width, cfg.height) if kind == "generic" else camera_k("a", cfg.width, cfg.height)
    rng = np.random.default_rng([cfg.seed, 22 if kind == "generic" else 32, index])
    shot = render_background(_room(cfg.seed, family, index % rooms), rng, K, cfg.width, cfg.height, cfg.supersample, closeup)
    _write_png(out / layout.photo(kind, photo_id), shot["image"])
    _write_png(out / layout.depth(kind, photo_id), _millimetres(shot["depth"]))
    _write_png(out / layout.support(kind, photo_id), shot["support"].astype(np.uint8) * 255)
    _write_json(out / layout.intrinsics(kind, photo_id), {
        "K": K.tolist(), "width": cfg.width, "height": cfg.height, "viewmat": shot["viewmat"].tolist(),
        "depth_units": "millimetres of camera z (0 = none)", "kind": shot["kind"], "room": f"{family}{index % rooms}"})
    thumbs = [shot["image"], depth_colour(shot["depth"]), overlay(shot["image"], shot["support"].astype(np.int32))]
    return {"thumbs": [_thumb(t) for t in thumbs], "closeup": closeup}


def _test_job(cfg: SampleConfig, out: Path, camera: str, index: int) -> dict:
    """Render and write one test image; returns its instance label map and metadata for the COCO file."""
    objects = tuple((o["name"], float(o["height_m"])) for o in cfg.objects)
    classes = class_sets(cfg.num_test, len(objects), cfg.seed)[index]
    rng = np.random.default_rng([cfg.seed, 42 if camera == "a" else 43, index])
    room_index = index % cfg.test_rooms
    shot = render_test_image(_room(cfg.seed, "test", room_index), _models(cfg.seed, objects), classes, camera, rng,
                             cfg.width, cfg.height, cfg.supersample)
    _write_png(out / layout.test_set(camera) / "images" / f"{index:04d}.png", shot["image"])
    return {"thumbs": [_thumb(overlay(shot["image"], shot["label"]))], "label": shot["label"].astype(np.uint8),
            "instances": shot["instances"], "K": shot["K"].tolist(), "viewmat": shot["viewmat"].tolist(),
            "flash": shot["flash"], "room": f"test{room_index}"}


def _walk_job(cfg: SampleConfig, out: Path, chunk: int) -> dict:
    """Render one piece of the walk through the in-domain rooms (stages/lib/sample_scene/walk.py) and write its frames'
    depth files; returns its frames (RGB uint8 [H, W, 3]) and cameras for the video, written after everything else."""
    count = layout.walk_frames(cfg)
    room_index, frames = walk_chunks(count, cfg.test_rooms)[chunk]
    part = room_frames(count, cfg.test_rooms)[room_index]
    room = _room(cfg.seed, "test", room_index)
    walk = room_walk(room, np.random.default_rng([cfg.seed, 51, room_index]), len(part))  # the room's whole walk
    viewmats = walk[frames.start - part.start:frames.stop - part.start]
    lighting = scene_lighting(room, np.random.default_rng([cfg.seed, 52, room_index]))
    traced, K = TracedScene(room.meshes), camera_k("a", cfg.width, cfg.height)
    images = []
    for index, viewmat in zip(frames, viewmats):
        image, depth = render_frame(traced, lighting, K, viewmat, cfg.width, cfg.height, cfg.supersample)
        _write_png(out / layout.walk_depth(index), _millimetres(depth))
        images.append(image)
    return {"frames": images, "cameras": [{"index": i, "viewmat": v.tolist(), "room": f"test{room_index}"}
                                          for i, v in zip(frames, viewmats)], "thumbs": [_thumb(images[0])]}


def _write_walk(out: Path, cfg: SampleConfig, results: list[dict]) -> None:
    """The walk's video and camera file from its pieces' results (in order)."""
    write_mp4(out / layout.walk_video(), [frame for r in results for frame in r["frames"]], cfg.fps)
    _write_json(out / layout.walk_camera(), {
        "K": camera_k("a", cfg.width, cfg.height).tolist(), "width": cfg.width, "height": cfg.height, "fps": cfg.fps,
        "depth_units": "millimetres of camera z (0 = none)", "frames": [c for r in results for c in r["cameras"]]})


def render_job(cfg: SampleConfig, out: Path, job: tuple[str, int]) -> dict:
    """Render and write one item of the sample: ("object", k), ("generic" | "indomain", i), ("test_a" | "test_b", i)
    or ("walk", piece).

    A pure function of (cfg, job): results do not depend on which process runs it or in which order.
    Returns small things for the caller (thumbnails, label maps, flags) plus "seconds".
    """
    started = time.perf_counter()
    kind, index = job
    if kind == "object":
        result = _object_job(cfg, out, cfg.objects[index])
    elif kind in ("generic", "indomain"):
        result = _background_job(cfg, out, kind, index)
    elif kind == "walk":
        result = _walk_job(cfg, out, index)
    else:
        result = _test_job(cfg, out, kind[-1], index)
    return {**result, "seconds": time.perf_counter() - started}


def _single_thread_worker() -> None:
    """Worker-process initialiser: one ray-casting thread per process (the pool provides the parallelism)."""
    RAY_THREADS["count"] = 1


def _write_coco(out: Path, cfg: SampleConfig, camera: str, results: list[dict]) -> dict:
    """Write test set `camera`'s annotations.json from the per-image results; returns counts."""
    builder = CocoBuilder([o["name"] for o in cfg.objects],
                          info={"description": f"embedded sample, test set {camera.upper()}", "seed": cfg.seed})
    for index, result in enumerate(results):
        image_id = builder.add_image(f"{index:04d}.png", cfg.width, cfg.height, K=result["K"], viewmat=result["viewmat"],
                                     room=result["room"], flash=result["flash"])
        for instance_id, inst in enumerate(result["instances"], start=1):
            builder.add_instance(image_id, inst["class_index"] + 1, result["label"] == instance_id,
                                 visible_fraction=round(inst["visible_fraction"], 4), support=inst["support"])
    builder.dataset.write(out / layout.test_set(camera))
    return {"images": len(results), "instances": len(builder.dataset.annotations), "flash_images": sum(r["flash"] for r in results)}


def _disk_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def run(ctx: Context) -> dict:
    """Render the whole sample into ctx.out; returns counts, timings and disk usage."""
    cfg = ctx.typed(SampleConfig)
    cfg.objects = _validate(cfg)
    for folder in [*layout.BACKGROUND_FOLDERS.values(), *(f"{layout.test_set(c)}/images" for c in layout.TEST_CAMERAS)]:
        (ctx.out / folder).mkdir(parents=True)
    walk = walk_chunks(layout.walk_frames(cfg), cfg.test_rooms)  # rendered last, from its own random streams
    if walk:
        (ctx.out / layout.walk_depth_folder()).mkdir(parents=True)
    jobs = ([("object", k) for k in range(len(cfg.objects))] + [("generic", i) for i in range(cfg.num_backgrounds)]
            + [("indomain", i) for i in range(cfg.num_indomain)]
            + [(f"test_{c}", i) for c in ("a", "b") for i in range(cfg.num_test)]
            + [("walk", j) for j in range(len(walk))])
    started = time.perf_counter()
    try:
        if cfg.workers > 1:
            with spawn_pool(cfg.workers, _single_thread_worker) as pool:
                results = list(ctx.progress(pool.map(partial(render_job, cfg, ctx.out), jobs), total=len(jobs)))
        else:
            results = [render_job(cfg, ctx.out, job) for job in ctx.progress(jobs)]
    except RuntimeError as err:
        raise StageError(f"sample: rendering failed: {err} (try another seed)") from err
    finally:
        _room.cache_clear()
        _models.cache_clear()
    wall = time.perf_counter() - started
    by_kind: dict[str, list[dict]] = {}
    for (kind, _), result in zip(jobs, results):
        by_kind.setdefault(kind, []).append(result)
    counts = {f"test_{c}": _write_coco(ctx.out, cfg, c, by_kind.get(f"test_{c}", [])) for c in ("a", "b")}
    if walk:
        _write_walk(ctx.out, cfg, by_kind["walk"])
    for part, kind in (("objects", "object"), ("backgrounds", "generic"), ("indomain", "indomain"),
                       ("test_a", "test_a"), ("test_b", "test_b"), ("walk", "walk")):
        thumbs = [t for r in by_kind.get(kind, []) for t in r["thumbs"]][:36]
        if thumbs:
            _write_png(ctx.out / f"contact_{part}.png", contact_sheet(thumbs, columns=6, thumb_width=THUMB_WIDTH))
    summary = {
        "objects": [o["name"] for o in cfg.objects], "frames_per_object": cfg.num_frames,
        "backgrounds": cfg.num_backgrounds, "wall_closeups": sum(r["closeup"] for r in by_kind.get("generic", [])),
        "indomain": cfg.num_indomain, **counts, "walk_frames": layout.walk_frames(cfg), "config": asdict(cfg),
        "timings_s": {kind: round(sum(r["seconds"] for r in rs), 2) for kind, rs in by_kind.items()},
        "total_s": round(wall, 2),
    }
    summary["disk_bytes"] = _disk_bytes(ctx.out)
    _write_json(ctx.out / layout.SUMMARY, summary)
    log.info("sample: %d objects, %d backgrounds, %d test images per set in %.1f s with %d workers, %.1f MB",
             len(cfg.objects), cfg.num_backgrounds, cfg.num_test, wall, cfg.workers, summary["disk_bytes"] / 1e6)
    return {k: summary[k] for k in ("wall_closeups", "test_a", "test_b", "timings_s", "total_s", "disk_bytes")}
