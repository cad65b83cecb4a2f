"""Object capture: the object on a floor or table in a furnished room, filmed on a two-ring orbit."""
from __future__ import annotations

import zlib
from dataclasses import dataclass
import numpy as np

from stages.lib.geometry import fov_intrinsics

from .cameras import orbit
from .meshes import Mesh, sample_surface
from .objects import build_object, footprint_radius
from .photo import auto_exposure, develop
from .raytrace import Lighting, TracedScene, render
from .rooms import capture_lighting, clutter_item, make_room

CAPTURE_HFOV_DEG = 60.0
OBJECT_FILL = 0.45  # object height as a fraction of the image height
ELEVATIONS_DEG = (22.0, 48.0)


@dataclass
class CaptureScene:
    """A capture set-up in world coordinates where the object's support plane is z = 0.

    meshes: room + clutter + object (label 1); object_meshes: the object alone; target: orbit centre [3].
    """

    meshes: list[Mesh]
    object_meshes: list[Mesh]
    lighting: Lighting
    radius: float
    target: np.ndarray
    support: str


def capture_rng(seed: int, name: str) -> np.random.Generator:
    """The Generator of one object's capture scene."""
    return np.random.default_rng([seed, 11, zlib.crc32(name.encode())])


def orbit_radius(height_m: float, radius_m: float, focal_px: float, image_height: int) -> float:
    """Camera distance at which the object fills OBJECT_FILL of the image height."""
    return focal_px * max(height_m, 1.5 * radius_m) / (OBJECT_FILL * image_height)


def build_capture_scene(name: str, height_m: float, seed: int, focal_px: float, image_height: int) -> CaptureScene:
    """The room, clutter, lights and object of one capture (deterministic in seed and name)."""
    rng = capture_rng(seed, name)
    obj = build_object(name, height_m, seed, label=1)
    obj_radius = footprint_radius(obj)
    radius = orbit_radius(height_m, obj_radius, focal_px, image_height)
    on_table = rng.uniform() < 0.4
    room = make_room(rng, keep_out=radius + 0.3, centre_table=on_table)
    support_z = room.tables[0][4] if on_table else 0.0
    shift = np.array([0.0, 0.0, -support_z])
    meshes = [m.transformed(np.eye(3), shift) for m in room.meshes]
    reach = min(0.75 * radius, 0.35) if on_table else 0.75 * radius
    placed: list[tuple[np.ndarray, float]] = []
    for _ in range(int(rng.integers(3, 6))):
        for _ in range(10):
            size = rng.uniform(0.3, 0.8) * min(height_m, 0.2) + 0.03
            rho = rng.uniform(obj_radius + size + 0.03, max(reach, obj_radius + size + 0.05))
            phi = rng.uniform(0, 2 * np.pi)
            xy = rho * np.array([np.cos(phi), np.sin(phi)])
            if all(np.linalg.norm(xy - p) > s + size for p, s in placed):
                placed.append((xy, size))
                meshes += clutter_item(rng, xy, 0.0, size)[0]
                break
    lighting = capture_lighting(room, rng)
    for light in lighting.lights:
        light.position = light.position + shift
    return CaptureScene(meshes + obj, obj, lighting, radius, np.array([0, 0, 0.45 * height_m]),
                        "table" if on_table else "floor")


def render_capture(name: str, height_m: float, seed: int, width: int, height: int, num_frames: int,
                   supersample: int) -> dict:
    """Render the capture video frames of one object.

    Returns {"frames": list of uint8 [H, W, 3], "masks": list of bool [H, W] (visible object),
    "K": [3, 3], "viewmats": list of [4, 4], "object_points": float32 [M, 3], "scene": CaptureScene}.
    """
    K = fov_intrinsics(width, height, CAPTURE_HFOV_DEG)
    scene = build_capture_scene(name, height_m, seed, K[1, 1], height)
    traced = TracedScene(scene.meshes)
    rng = capture_rng(seed, name + "/orbit")
    viewmats = orbit(num_frames, scene.radius, scene.target, ELEVATIONS_DEG, rng, jitter=0.06)
    frames, masks, exposure = [], [], None
    for viewmat in viewmats:
        view = render(traced, scene.lighting, K, viewmat, width, height, supersample)
        exposure = auto_exposure(view.radiance) if exposure is None else exposure
        frames.append(develop(view.radiance, exposure))
        masks.append(view.label == 1)
    points = sample_surface(scene.object_meshes, 20000, capture_rng(seed, name + "/points"))
    return {"frames": frames, "masks": masks, "K": K, "viewmats": viewmats, "object_points": points, "scene": scene}
