"""A walk through the sample's in-domain rooms (the test rooms, without objects): in each room in turn, a camera at
eye height goes along an arc around the room's middle, turning between the way it walks and the room's middle and
far side, looking down at the floor, the furniture and the table tops. Each frame is a pure function of (seed, room,
frame), so the walk renders in pieces, in any order and any process, with its own random streams."""
from __future__ import annotations

import numpy as np

from stages.lib.geometry import look_at_viewmat

from .backgrounds import camera_inside
from .photo import auto_exposure, develop
from .raytrace import Lighting, TracedScene, render
from .rooms import Room

EYE_HEIGHT_M = (1.45, 1.7)
ARC_RADIUS = (0.35, 0.6)  # the arc's radius as a fraction of the room's half sizes
ARC_DEG = (150.0, 240.0)  # how far around the room's middle one room's walk goes
TURN_DEG = (10.0, 80.0)  # how far the view turns from the walking direction towards the room's middle, swaying
PITCH_DEG = (-30.0, -16.0)  # how far it looks down
MAX_PATH_TRIES = 40
CHUNK = 8  # frames rendered by one job


def room_frames(count: int, rooms: int) -> list[range]:
    """The frame indices [count] of each room's part of the walk: in order, split as evenly as possible."""
    return [range(r * count // rooms, (r + 1) * count // rooms) for r in range(rooms)]


def chunks(count: int, rooms: int) -> list[tuple[int, range]]:
    """(room, frame indices) of the walk's render jobs: each room's part cut into pieces of at most CHUNK frames."""
    return [(room, frames[start:start + CHUNK]) for room, frames in enumerate(room_frames(count, rooms))
            for start in range(0, len(frames), CHUNK)]


def room_walk(room: Room, rng: np.random.Generator, count: int) -> list[np.ndarray]:
    """Viewmats [count] x [4, 4] of one room's walk: eyes along an elliptic arc at eye height, all inside the room and
    clear of its furniture (re-drawn until they are), looking down and across the room. RuntimeError when no
    arc fits after MAX_PATH_TRIES."""
    s = np.linspace(0.0, 1.0, max(count, 1))  # [count] progress along the walk
    for _ in range(MAX_PATH_TRIES):
        radius, height = rng.uniform(*ARC_RADIUS), rng.uniform(*EYE_HEIGHT_M)
        start, arc = rng.uniform(0, 2 * np.pi), np.radians(rng.uniform(*ARC_DEG)) * rng.choice([-1.0, 1.0])
        sway, pitch, phase = rng.uniform(0.5, 1.5), rng.uniform(*PITCH_DEG), rng.uniform(0, 2 * np.pi)
        angle = start + arc * s  # [count]
        a, b = radius * room.half_x, radius * room.half_y
        eyes = np.stack([a * np.cos(angle), b * np.sin(angle), np.full(len(s), height)], axis=1)  # [count, 3]
        if all(camera_inside(room, eye, 0.3) for eye in eyes):
            break
    else:
        raise RuntimeError(f"no walk fits in the room after {MAX_PATH_TRIES} tries")
    along = np.sign(arc) * np.stack([-a * np.sin(angle), b * np.cos(angle)], axis=1)  # [count, 2] walking direction
    along /= np.linalg.norm(along, axis=1, keepdims=True)
    inward = -np.stack([b * np.cos(angle), a * np.sin(angle)], axis=1)  # [count, 2] towards the room's middle
    inward /= np.linalg.norm(inward, axis=1, keepdims=True)
    wave = np.sin(2 * np.pi * sway * s + phase)  # [count] in [-1, 1]
    turn = np.radians(TURN_DEG[0] + (TURN_DEG[1] - TURN_DEG[0]) * (wave + 1) / 2)
    heading = np.cos(turn)[:, None] * along + np.sin(turn)[:, None] * inward  # [count, 2]
    down = np.radians(pitch + 4.0 * wave)
    views = np.concatenate([np.cos(down)[:, None] * heading, np.sin(down)[:, None]], axis=1)  # [count, 3]
    return [look_at_viewmat(eye, eye + view, roll_deg=2.0 * w) for eye, view, w in zip(eyes, views, wave)]


def render_frame(traced: TracedScene, lighting: Lighting, K: np.ndarray, viewmat: np.ndarray, width: int,
                 height: int, supersample: int) -> tuple[np.ndarray, np.ndarray]:
    """One frame of the walk: the image uint8 [H, W, 3] (exposed on its own, as a camera's auto exposure) and its
    depth float32 [H, W] (camera z in metres, 0 = none)."""
    view = render(traced, lighting, K, viewmat, width, height, supersample)
    return develop(view.radiance, auto_exposure(view.radiance)), view.depth
