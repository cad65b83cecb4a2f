"""Stage `sample`: render the embedded mini-benchmark ("mini-IBSYD") with its own ray tracer.

Writes object capture videos with ground truth, background and in-domain photos with metric depth
and support maps, two COCO test sets (camera A like the capture, camera B another camera) and
contact sheets. Everything is a pure function of the config: regenerating gives identical files
(except the timings in sample.json). See docs/stage_contracts.md, section "sample".
"""
from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from stages.coco import CocoBuilder
from stages.context import Context, StageError
from stages.sample_scene.backgrounds import BACKGROUND_HFOV_DEG, render_background
from stages.sample_scene.cameras import intrinsics
from stages.sample_scene.capture import render_capture
from stages.sample_scene.contact import contact_sheet, depth_colour, overlay
from stages.sample_scene.objects import OBJECT_CLASSES, build_object
from stages.sample_scene.rooms import Room, make_room
from stages.sample_scene.testsets import camera_k, class_sets, render_test_image
from stages.sample_scene.videos import write_mp4

log = logging.getLogger(__name__)


def _default_objects() -> list[dict]:
    return [{"name": "bottle", "height_m": 0.25}, {"name": "eyedrops", "height_m": 0.09},
            {"name": "plant", "height_m": 0.30}, {"name": "soda_can", "height_m": 0.12},
            {"name": "vase", "height_m": 0.22}]


@dataclass
class SampleConfig:
    """Sizes of the embedded sample (defaults: the full mini-benchmark).

    objects: [{"name", "height_m"}] from the object classes bottle, eyedrops, plant, soda_can, vase;
    their order fixes the COCO category ids (1..n). supersample: sub-samples per axis on geometry
    edges (1 = off). wall_closeup_fraction: share of generic backgrounds that show no horizontal
    surface. photos_per_room: generic backgrounds per room; test_rooms: rooms shared by test A,
    test B and the in-domain backgrounds.
    """

    seed: int = 0
    objects: list[Any] = field(default_factory=_default_objects)
    width: int = 640
    height: int = 480
    num_frames: int = 60
    fps: float = 10.0
    supersample: int = 2
    num_backgrounds: int = 40
    num_indomain: int = 20
    num_test: int = 50
    wall_closeup_fraction: float = 0.15
    photos_per_room: int = 5
    test_rooms: int = 4


def background_ids(cfg: Any, kind: str) -> list[str]:
    """Photo ids of the generic ("generic") or in-domain ("indomain") backgrounds for a sample config."""
    if kind == "generic":
        return [f"bg{i:04d}" for i in range(int(cfg.num_backgrounds))]
    if kind == "indomain":
        return [f"in{i:04d}" for i in range(int(cfg.num_indomain))]
    raise ValueError(f"background kind must be 'generic' or 'indomain', not {kind!r}")


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
    for name in ("width", "height", "num_frames", "supersample", "photos_per_room", "test_rooms"):
        if int(getattr(cfg, name)) < 1:
            raise StageError(f"sample: {name} must be >= 1, got {getattr(cfg, name)}")
    for name in ("num_backgrounds", "num_indomain", "num_test"):
        if int(getattr(cfg, name)) < 0:
            raise StageError(f"sample: {name} must be >= 0, got {getattr(cfg, name)}")
    return objects


def closeup_indices(count: int, fraction: float) -> set[int]:
    """Which of `count` backgrounds are wall close-ups: ceil(count * fraction) of them, spread evenly."""
    return {i for i in range(count) if math.ceil((i + 1) * fraction - 1e-9) > math.ceil(i * fraction - 1e-9)}


def _write_png(path: Path, image: np.ndarray) -> None:
    """Write an RGB uint8 [H, W, 3] or a single-channel [H, W] image as PNG."""
    path.parent.mkdir(parents=True, exist_ok=True)
    data = image[..., ::-1] if image.ndim == 3 else image
    if not cv2.imwrite(str(path), np.ascontiguousarray(data)):
        raise StageError(f"sample: could not write {path}")


def _write_json(path: Path, data: Any) -> None:
    path.write_text(json.dumps(data, indent=1))


def _write_objects(ctx: Context, cfg: SampleConfig, objects: list[dict]) -> list[np.ndarray]:
    """Render and write every object's capture; returns contact thumbnails."""
    thumbs = []
    for spec in objects:
        name, height_m = spec["name"], float(spec["height_m"])
        folder = ctx.out / "objects" / name
        (folder / "masks").mkdir(parents=True)
        capture = render_capture(name, height_m, cfg.seed, cfg.width, cfg.height, cfg.num_frames, cfg.supersample,
                                 progress=lambda it, name=name: ctx.progress(it, desc=f"sample[{name}]"))
        write_mp4(folder / "video.mp4", capture["frames"], cfg.fps)
        for index, mask in enumerate(capture["masks"]):
            _write_png(folder / "masks" / f"{index:04d}.png", mask.astype(np.uint8) * 255)
        np.save(folder / "object_points.npy", capture["object_points"])
        _write_json(folder / "gt.json", {
            "name": name, "height_m": height_m, "K": capture["K"].tolist(), "width": cfg.width, "height": cfg.height,
            "fps": cfg.fps, "frames": [{"index": i, "viewmat": v.tolist()} for i, v in enumerate(capture["viewmats"])],
            "ground_normal": [0.0, 0.0, 1.0], "ground_point": [0.0, 0.0, 0.0],
            "object_points_file": "object_points.npy", "support": capture["scene"].support,
            "orbit_radius_m": capture["scene"].radius, "seed": cfg.seed})
        step = max(1, len(capture["frames"]) // 6)
        thumbs += [overlay(f, m.astype(np.int32)) for f, m in zip(capture["frames"][::step][:6], capture["masks"][::step][:6])]
    return thumbs


def _write_backgrounds(ctx: Context, cfg: SampleConfig, kind: str, rooms: list[Room], K: np.ndarray) -> tuple[list, int]:
    """Render and write the generic or in-domain backgrounds; returns (contact thumbnails, close-up count)."""
    folder = ctx.out / ("backgrounds" if kind == "generic" else "indomain")
    folder.mkdir(parents=True)
    ids = background_ids(cfg, kind)
    closeups = closeup_indices(len(ids), cfg.wall_closeup_fraction) if kind == "generic" else set()
    thumbs = []
    for i, photo_id in enumerate(ctx.progress(ids, desc=f"sample[{kind}]")):
        rng = np.random.default_rng([cfg.seed, 22 if kind == "generic" else 32, i])
        room_index = i % len(rooms)
        shot = render_background(rooms[room_index], rng, K, cfg.width, cfg.height, cfg.supersample, i in closeups)
        _write_png(folder / f"{photo_id}.png", shot["image"])
        _write_png(folder / f"{photo_id}.depth.png", np.clip(np.round(shot["depth"] * 1000), 0, 65535).astype(np.uint16))
        _write_png(folder / f"{photo_id}.support.png", shot["support"].astype(np.uint8) * 255)
        _write_json(folder / f"{photo_id}.json", {
            "K": K.tolist(), "width": cfg.width, "height": cfg.height, "viewmat": shot["viewmat"].tolist(),
            "depth_units": "millimetres of camera z (0 = none)", "kind": shot["kind"], "room": f"{kind}{room_index}"})
        if len(thumbs) < 24:
            thumbs += [shot["image"], depth_colour(shot["depth"]), overlay(shot["image"], shot["support"].astype(np.int32))]
    return thumbs, len(closeups)


def _write_testset(ctx: Context, cfg: SampleConfig, camera: str, rooms: list[Room], objects: list[dict]) -> tuple[list, dict]:
    """Render and write test set A or B with COCO annotations; returns (contact thumbnails, counts)."""
    folder = ctx.out / f"test_{camera}"
    (folder / "images").mkdir(parents=True)
    names = [o["name"] for o in objects]
    models = [build_object(o["name"], float(o["height_m"]), cfg.seed) for o in objects]
    builder = CocoBuilder(names, info={"description": f"embedded sample, test set {camera.upper()}", "seed": cfg.seed})
    thumbs, instances, flashes = [], 0, 0
    for i, classes in enumerate(ctx.progress(class_sets(cfg.num_test, len(objects), cfg.seed), desc=f"sample[test_{camera}]")):
        rng = np.random.default_rng([cfg.seed, 42 if camera == "a" else 43, i])
        room_index = i % len(rooms)
        shot = render_test_image(rooms[room_index], models, classes, camera, rng, cfg.width, cfg.height, cfg.supersample)
        file_name = f"{i:04d}.png"
        _write_png(folder / "images" / file_name, shot["image"])
        image_id = builder.add_image(file_name, cfg.width, cfg.height, K=shot["K"].tolist(), viewmat=shot["viewmat"].tolist(),
                                     room=f"test{room_index}", flash=shot["flash"])
        for instance_id, inst in enumerate(shot["instances"], start=1):
            builder.add_instance(image_id, inst["class_index"] + 1, shot["label"] == instance_id,
                                 visible_fraction=round(inst["visible_fraction"], 4), support=inst["support"])
        instances += len(shot["instances"])
        flashes += int(shot["flash"])
        if len(thumbs) < 24:
            thumbs.append(overlay(shot["image"], shot["label"]))
    builder.write(folder / "annotations.json")
    return thumbs, {"images": cfg.num_test, "instances": instances, "flash_images": flashes}


def _disk_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def run(ctx: Context) -> dict:
    """Render the whole sample into ctx.out; returns counts, timings and disk usage."""
    cfg = SampleConfig(**ctx.params)
    objects = _validate(cfg)
    timings: dict[str, float] = {}
    sheets: dict[str, list[np.ndarray]] = {}

    started = time.perf_counter()
    sheets["objects"] = _write_objects(ctx, cfg, objects)
    timings["objects"] = time.perf_counter() - started

    started = time.perf_counter()
    rooms = [make_room(np.random.default_rng([cfg.seed, 21, r]))
             for r in range(max(1, math.ceil(cfg.num_backgrounds / cfg.photos_per_room)))]
    test_rooms = [make_room(np.random.default_rng([cfg.seed, 31, r])) for r in range(cfg.test_rooms)]
    timings["rooms"] = time.perf_counter() - started

    started = time.perf_counter()
    sheets["backgrounds"], closeups = _write_backgrounds(
        ctx, cfg, "generic", rooms, intrinsics(cfg.width, cfg.height, BACKGROUND_HFOV_DEG))
    timings["backgrounds"] = time.perf_counter() - started
    started = time.perf_counter()
    sheets["indomain"], _ = _write_backgrounds(ctx, cfg, "indomain", test_rooms, camera_k("a", cfg.width, cfg.height))
    timings["indomain"] = time.perf_counter() - started

    counts = {}
    for camera in ("a", "b"):
        started = time.perf_counter()
        sheets[f"test_{camera}"], counts[f"test_{camera}"] = _write_testset(ctx, cfg, camera, test_rooms, objects)
        timings[f"test_{camera}"] = time.perf_counter() - started

    for part, thumbs in sheets.items():
        if thumbs:
            _write_png(ctx.out / f"contact_{part}.png", contact_sheet(thumbs))
    summary = {
        "objects": [o["name"] for o in objects], "frames_per_object": cfg.num_frames,
        "backgrounds": cfg.num_backgrounds, "wall_closeups": closeups, "indomain": cfg.num_indomain,
        **counts, "config": asdict(cfg) | {"objects": objects},
        "timings_s": {k: round(v, 2) for k, v in timings.items()}, "total_s": round(sum(timings.values()), 2),
    }
    summary["disk_bytes"] = _disk_bytes(ctx.out)
    _write_json(ctx.out / "sample.json", summary)
    log.info("sample: %d objects, %d backgrounds, %d test images per set in %.1f s, %.1f MB",
             len(objects), cfg.num_backgrounds, cfg.num_test, summary["total_s"], summary["disk_bytes"] / 1e6)
    return {k: summary[k] for k in ("wall_closeups", "test_a", "test_b", "timings_s", "total_s", "disk_bytes")}
