"""Test photos: 1-3 objects standing on tables and floors in furnished rooms, sometimes partly hidden
behind furniture or each other. Camera A is the capture camera; camera B has another lens, defocus,
sensor noise, a colour cast and sometimes a flash."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.lib.geometry import camera_centres, fov_intrinsics, look_at_viewmat

from .backgrounds import camera_inside
from .capture import CAPTURE_HFOV_DEG
from .meshes import Mesh, rotation_z
from .objects import footprint_radius
from .photo import auto_exposure, defocus, develop, sensor
from .raytrace import TracedScene, probe, render
from .rooms import Room, clutter_item, flash, scene_lighting

CAMERA_B_HFOV_DEG = 44.0
MIN_VISIBLE_FRACTION = 0.3
MAX_TRIES = 60


@dataclass
class Placed:
    """One object instance in a test scene: class index, meshes (label = instance id), support kind."""

    class_index: int
    meshes: list[Mesh]
    support: str


def class_sets(num_images: int, num_classes: int, seed: int) -> list[list[int]]:
    """The object classes of each test image (1-3 distinct classes); shared by test A and test B."""
    sets = []
    for i in range(num_images):
        rng = np.random.default_rng([seed, 41, i])
        count = int(rng.integers(1, min(3, num_classes) + 1))
        sets.append(sorted(int(c) for c in rng.choice(num_classes, size=count, replace=False)))
    return sets


def camera_k(camera: str, width: int, height: int, rng: np.random.Generator | None = None) -> np.ndarray:
    """K of test camera "a" (the capture camera) or "b" (longer lens, slightly off-centre principal point)."""
    if camera == "a":
        return fov_intrinsics(width, height, CAPTURE_HFOV_DEG)
    offset = (0.0, 0.0) if rng is None else tuple(rng.uniform(-0.015, 0.015, 2) * width)
    return fov_intrinsics(width, height, CAMERA_B_HFOV_DEG, offset)


def _place_objects(room: Room, rng, models: list[list[Mesh]], classes: list[int]) -> list[Placed] | None:
    """Stand the objects on one table top or on a patch of free floor, close together; None if they do not fit."""
    use_table = bool(room.tables) and rng.uniform() < 0.5
    top = room.tables[int(rng.integers(len(room.tables)))] if use_table else None
    placed, boxes = [], []
    anchor = None
    for instance, cls in enumerate(classes, start=1):
        model = models[cls]
        radius, obj_h = footprint_radius(model), max(m.vertices[:, 2].max() for m in model)
        for _ in range(30):
            if top is not None:
                if top[1] - top[0] < 2 * radius + 0.04 or top[3] - top[2] < 2 * radius + 0.04:
                    return None
                xy = np.array([rng.uniform(top[0] + radius + 0.02, top[1] - radius - 0.02),
                               rng.uniform(top[2] + radius + 0.02, top[3] - radius - 0.02)])
                z = top[4]
            else:
                xy = (np.array([rng.uniform(-room.half_x, room.half_x), rng.uniform(-room.half_y, room.half_y)])
                      if anchor is None else anchor + rng.uniform(-0.5, 0.5, 2))
                z = 0.0
            aabb = np.array([[xy[0] - radius, xy[1] - radius, z], [xy[0] + radius, xy[1] + radius, z + obj_h]])
            clear_of_others = all(np.any(aabb[0] >= b[1] + [0.01, 0.01, -1]) or np.any(aabb[1] <= b[0] - [0.01, 0.01, -1]) for b in boxes)
            if room.free(aabb, 0.02) and clear_of_others:
                rotation = rotation_z(rng.uniform(0, 2 * np.pi))
                meshes = [m.transformed(rotation, [xy[0], xy[1], z]).with_material(label=instance) for m in model]
                placed.append(Placed(cls, meshes, "table" if top is not None else "floor"))
                boxes.append(aabb)
                anchor = xy if anchor is None else anchor
                break
        else:
            return None
    return placed


def _aim_camera(room: Room, rng, placed: list[Placed], focal_px: float, width: int, zoom_out: float) -> np.ndarray | None:
    """A viewpoint looking at the object group from 10-50 degrees above, up to `zoom_out` times farther than
    needed to frame it; None if no free spot is found."""
    points = np.concatenate([m.vertices for p in placed for m in p.meshes])
    lo, hi = points.min(0), points.max(0)
    target = (lo + hi) / 2
    extent = max(float(np.linalg.norm(hi[:2] - lo[:2])), float(hi[2] - lo[2]) * 1.3)
    for _ in range(20):
        distance = np.clip(focal_px * extent / (0.45 * width) * rng.uniform(1.0, zoom_out), 0.35, 4.0)
        azimuth, elevation = rng.uniform(0, 2 * np.pi), np.radians(rng.uniform(10, 50))
        eye = target + distance * np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
        if camera_inside(room, eye, 0.2):
            aim = target + rng.uniform(-0.25, 0.25, 3) * extent
            return look_at_viewmat(eye, aim, roll_deg=rng.uniform(-5, 5))
    return None


def _occluder(rng, placed: list[Placed], eye: np.ndarray) -> list[Mesh]:
    """An item standing between the camera and one object, about half the object's height."""
    target = placed[int(rng.integers(len(placed)))]
    vertices = np.concatenate([m.vertices for m in target.meshes])
    base = np.array([*vertices[:, :2].mean(0), vertices[:, 2].min()])
    obj_h = vertices[:, 2].max() - base[2]
    ground_dir = eye[:2] - base[:2]
    spot = base[:2] + ground_dir * rng.uniform(0.2, 0.45)
    size = np.clip(obj_h * rng.uniform(0.8, 1.4), 0.05, 0.5)
    return clutter_item(rng, spot, base[2], size)[0]


def visible_fractions(traced: TracedScene, objects_only: TracedScene, K, viewmat, width, height, count: int,
                      step: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per instance 1..count: visible pixels [count], unoccluded pixels [count], and the label map [H/step, W/step]."""
    label = probe(traced, K, viewmat, width, height, step).label
    alone = probe(objects_only, K, viewmat, width, height, step).label
    visible = np.bincount(label.ravel(), minlength=count + 1)[1:count + 1]
    full = np.bincount(alone.ravel(), minlength=count + 1)[1:count + 1]
    return visible, full, label


def render_test_image(room: Room, models: list[list[Mesh]], classes: list[int], camera: str, rng: np.random.Generator,
                      width: int, height: int, supersample: int) -> dict:
    """One test photo with camera "a" or "b".

    Returns {"image": uint8 [H, W, 3], "label": int32 [H, W] (instance ids), "instances": [{"class_index",
    "visible_fraction", "support"}], "K": [3, 3], "viewmat": [4, 4], "flash": bool}.
    """
    K = camera_k(camera, width, height, rng)
    min_pixels = 0.0008 * width * height
    for attempt in range(MAX_TRIES):
        relaxed = attempt >= MAX_TRIES // 2  # late tries: no occluder, tighter framing
        placed = _place_objects(room, rng, models, classes)
        viewmat = None if placed is None else _aim_camera(room, rng, placed, K[0, 0], width, 1.2 if relaxed else 2.2)
        if viewmat is None:
            continue
        eye = camera_centres(viewmat)
        extra = _occluder(rng, placed, eye) if rng.uniform() < 0.35 and not relaxed else []
        object_meshes = [m for p in placed for m in p.meshes]
        traced = TracedScene(room.meshes + extra + object_meshes)
        objects_only = TracedScene(object_meshes)
        visible, full, _ = visible_fractions(traced, objects_only, K, viewmat, width, height, len(placed), 4)
        if np.all(visible * 16 >= min_pixels) and np.all(visible >= MIN_VISIBLE_FRACTION * np.maximum(full, 1)):
            break
    else:
        raise RuntimeError(f"could not compose a test image with classes {classes} after {MAX_TRIES} tries")
    visible, full, label = visible_fractions(traced, objects_only, K, viewmat, width, height, len(placed))
    lighting = scene_lighting(room, rng)
    use_flash = camera == "b" and rng.uniform() < 0.35
    eye = camera_centres(viewmat)
    if use_flash:
        target_depth = float(np.median(probe(traced, K, viewmat, width, height, 4).depth))
        lighting = flash(lighting, eye, target_depth)
    view = render(traced, lighting, K, viewmat, width, height, supersample)
    exposure = auto_exposure(view.radiance)
    if camera == "a":
        image = develop(view.radiance, exposure)
    else:
        object_depths = view.depth[label > 0]
        focus = float(np.median(object_depths)) * (rng.uniform(0.5, 2.0) if rng.uniform() < 0.4 else 1.0)
        blurred = defocus(view.radiance, view.depth, focus, rng.uniform(2.0, 8.0))
        cast = rng.uniform(0.85, 1.15, 3)
        image = sensor(blurred, exposure, rng, cast / cast.mean(), rng.uniform(0.002, 0.01))
    instances = [{"class_index": p.class_index, "visible_fraction": float(v / max(f, 1)), "support": p.support}
                 for p, v, f in zip(placed, visible, full)]
    return {"image": image, "label": label, "instances": instances, "K": K, "viewmat": viewmat, "flash": use_flash}
