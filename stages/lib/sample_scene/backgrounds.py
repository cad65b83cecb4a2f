"""Background photos of empty rooms with metric depth and horizontal-support ground truth."""
from __future__ import annotations

import numpy as np

from stages.lib.geometry import look_at_viewmat

from .photo import auto_exposure, develop
from .raytrace import TracedScene, probe, render
from .rooms import Room, scene_lighting

MAX_POSE_TRIES = 40


def camera_inside(room: Room, eye: np.ndarray, margin: float = 0.25) -> bool:
    """Whether `eye` [3] is inside the room by `margin` and outside every obstacle (grown by 0.1 m)."""
    if abs(eye[0]) > room.half_x - margin or abs(eye[1]) > room.half_y - margin or not 0.1 < eye[2] < room.height - 0.2:
        return False
    return not any(np.all(eye > o[0] - 0.1) and np.all(eye < o[1] + 0.1) for o in room.obstacles)


def room_view(room: Room, rng: np.random.Generator) -> np.ndarray:
    """A photographer's viewpoint aimed at a piece of furniture or a patch of floor, 1-3.5 m away,
    from 0.4-1.8 m high (pitch follows from the aim)."""
    for _ in range(MAX_POSE_TRIES):
        if room.obstacles and rng.uniform() < 0.75:
            lo, hi = room.obstacles[int(rng.integers(len(room.obstacles)))]
            target = np.array([rng.uniform(lo[0], hi[0]), rng.uniform(lo[1], hi[1]), rng.uniform(0.3, 1.0) * hi[2]])
        else:
            target = np.array([rng.uniform(-0.7, 0.7) * room.half_x, rng.uniform(-0.7, 0.7) * room.half_y, 0.0])
        azimuth, distance = rng.uniform(0, 2 * np.pi), rng.uniform(1.0, 3.5)
        eye = np.array([target[0] + distance * np.cos(azimuth), target[1] + distance * np.sin(azimuth), rng.uniform(0.4, 1.8)])
        if camera_inside(room, eye):
            break
    target = target + rng.uniform(-0.3, 0.3, 3)
    return look_at_viewmat(eye, target, roll_deg=rng.uniform(-4, 4))


def wall_view(room: Room, rng: np.random.Generator, attempt: int) -> np.ndarray:
    """A close-up of a wall seen nearly head-on (no floor or table in view); later attempts look higher."""
    wall = int(rng.integers(4))
    normal = np.array([[0, 1, 0], [0, -1, 0], [1, 0, 0], [-1, 0, 0]][wall], float)  # into the room
    half_along = room.half_x if wall < 2 else room.half_y
    half_across = room.half_y if wall < 2 else room.half_x
    along = rng.uniform(-0.7, 0.7) * half_along
    distance = rng.uniform(0.4, 0.8)
    point = np.array([along, -half_across, 0.0]) if wall == 0 else np.array([along, half_across, 0.0]) if wall == 1 else \
        np.array([-half_across, along, 0.0]) if wall == 2 else np.array([half_across, along, 0.0])
    eye = point + normal * distance + np.array([0, 0, rng.uniform(1.2, 2.0)])
    yaw = np.radians(rng.uniform(-20, 20))
    pitch = np.radians(rng.uniform(0, 10) + attempt * 2)
    forward = -normal
    side = np.cross(forward, [0, 0, 1.0])
    direction = np.cos(pitch) * (np.cos(yaw) * forward + np.sin(yaw) * side) + np.array([0, 0, np.sin(pitch)])
    return look_at_viewmat(eye, eye + direction, roll_deg=rng.uniform(-3, 3))


def render_background(room: Room, rng: np.random.Generator, K: np.ndarray, width: int, height: int,
                      supersample: int, wall_closeup: bool) -> dict:
    """One empty-room photo: {"image": uint8 [H, W, 3], "depth": float32 [H, W] m, "support": bool [H, W],
    "viewmat": [4, 4], "kind": "room" | "wall_closeup"}. Wall close-ups are re-posed until no support shows."""
    traced = TracedScene(room.meshes)
    lighting = scene_lighting(room, rng)
    for attempt in range(MAX_POSE_TRIES):
        viewmat = wall_view(room, rng, attempt) if wall_closeup else room_view(room, rng)
        if not wall_closeup or not probe(traced, K, viewmat, width, height, 4).support.any():
            view = render(traced, lighting, K, viewmat, width, height, supersample)
            if not wall_closeup or not view.support.any():
                break
    else:
        raise RuntimeError(f"no wall close-up without a support surface after {MAX_POSE_TRIES} tries")
    image = develop(view.radiance, auto_exposure(view.radiance))
    return {"image": image, "depth": view.depth, "support": view.support, "viewmat": viewmat,
            "kind": "wall_closeup" if wall_closeup else "room"}
