"""Scenes whose first cut is wrong, for extract's self-check (stages/lib/objects/self_check.py), in metres, z up.

wall_scene: a box hanging on a wall, filmed in a half orbit, no floor under it (every check but the self-check
passes: the plane is the box's own base and the wall is kept). ring_scene: a ring lying on a floor around the
cameras' look-at point, a pebble inside it nearer that point than the ring (the nearest cluster is the pebble).
bridged_scene: an object joined to a box of clutter by a rod of points that DBSCAN bridges at its radius.
"""
from __future__ import annotations

import numpy as np

from stages.lib.geometry import look_at_viewmat
from tests.factories.splats import SyntheticScene


def _scene(parts: list[np.ndarray], object_part: int, eyes: np.ndarray, target: np.ndarray, normal: np.ndarray,
           height: float, rng: np.random.Generator) -> SyntheticScene:
    """A SyntheticScene of point parts [P_i, 3] (parts[object_part] is the object), opaque grey Gaussians of 3 mm,
    cameras at eyes [C, 3] looking at target [3]."""
    means = np.concatenate(parts)
    is_object = np.zeros(len(means), dtype=bool)
    start = sum(len(part) for part in parts[:object_part])
    is_object[start:start + len(parts[object_part])] = True
    viewmats = np.stack([look_at_viewmat(eye, target) for eye in eyes])
    return SyntheticScene(means.astype(np.float32), rng.uniform(0.5, 1.0, len(means)).astype(np.float32),
                          np.full((len(means), 3), 0.003, dtype=np.float32),
                          np.full((len(means), 3), 0.5, dtype=np.float32), viewmats, is_object, normal, height,
                          np.zeros(3))


def wall_scene(seed: int = 0) -> SyntheticScene:
    """A 30 x 12 x 30 cm box on a 3 x 2 m wall (the plane y = 0) at 1 m height, 24 cameras on a half orbit in
    front of it (0.9 m away), and sparse floaters in the room; no floor."""
    rng = np.random.default_rng(seed)
    wall = np.stack([rng.uniform(-1.5, 1.5, 20000), rng.normal(0, 0.002, 20000), rng.uniform(0, 2, 20000)], 1)
    box = rng.uniform([-0.15, 0.0, 0.85], [0.15, 0.12, 1.15], (4000, 3))  # [4000, 3] on its five visible faces
    face = rng.integers(0, 3, 4000)
    box[face == 0, 1] = 0.12
    box[face == 1, 0] = rng.choice([-0.15, 0.15], int((face == 1).sum()))
    box[face == 2, 2] = rng.choice([0.85, 1.15], int((face == 2).sum()))
    wall = wall[~((np.abs(wall[:, 0]) < 0.15) & (np.abs(wall[:, 2] - 1.0) < 0.15))]  # hidden behind the box
    floaters = rng.uniform([-1.5, 0.3, 0.0], [1.5, 1.5, 2.0], (4000, 3))
    target = np.array([0.0, 0.06, 1.0])
    angles = np.linspace(-1.2, 1.2, 24)
    eyes = target + 0.9 * np.stack([np.sin(angles), np.cos(angles), 0.2 + 0.1 * np.sin(3 * angles)], 1)
    return _scene([wall, box, floaters], 1, eyes, target, np.array([0.0, 1.0, 0.0]), 0.12, rng)


def ring_scene(seed: int = 0) -> SyntheticScene:
    """A ring (torus of radius 0.25 m, tube 4 cm) lying on a 1.5 m floor disc around the look-at point, and a 2 cm
    pebble inside it 12 cm from that point; 24 cameras orbiting at 0.8 m, 0.5 m up."""
    rng = np.random.default_rng(seed)
    radius, tube = 0.25, 0.04
    angle, distance = rng.uniform(0, 2 * np.pi, 20000), 1.5 * np.sqrt(rng.uniform(0, 1, 20000))
    floor = np.stack([distance * np.cos(angle), distance * np.sin(angle), rng.normal(0, 0.002, 20000)], 1)
    around, across = rng.uniform(0, 2 * np.pi, 5000), rng.uniform(0, 2 * np.pi, 5000)
    ring = np.stack([(radius + tube * np.cos(across)) * np.cos(around), (radius + tube * np.cos(across)) *
                     np.sin(around), tube + tube * np.sin(across)], 1)  # [5000, 3]
    direction = rng.normal(size=(600, 3))
    pebble = 0.02 * direction / np.linalg.norm(direction, axis=1, keepdims=True) + [0.12, 0.0, 0.02]
    hidden = (np.abs(np.hypot(floor[:, 0], floor[:, 1]) - radius) < tube) | (np.hypot(floor[:, 0] - 0.12, floor[:, 1])
                                                                             < 0.02)
    angles = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    eyes = np.stack([0.8 * np.cos(angles), 0.8 * np.sin(angles), 0.5 + 0.1 * np.sin(3 * angles)], 1)
    return _scene([floor[~hidden], ring, pebble], 1, eyes, np.array([0.0, 0.0, tube]), np.array([0.0, 0.0, 1.0]),
                  2 * tube, rng)


def bridged_scene(rod_step: float | None, seed: int = 0) -> SyntheticScene:
    """A cylinder (radius 8 cm, 25 cm high) on a 1.5 m floor disc, a 20 cm box of clutter 60 cm from it, and
    (rod_step given) a rod from the cylinder's side to the box 10 cm up, points every rod_step metres: furniture that
    DBSCAN may bridge to the object. 24 cameras orbiting at 0.8 m, 0.5 m up."""
    rng = np.random.default_rng(seed)
    angle, distance = rng.uniform(0, 2 * np.pi, 20000), 1.5 * np.sqrt(rng.uniform(0, 1, 20000))
    floor = np.stack([distance * np.cos(angle), distance * np.sin(angle), rng.normal(0, 0.002, 20000)], 1)
    floor = floor[(np.hypot(floor[:, 0], floor[:, 1]) > 0.08) & (np.abs(floor[:, 0] - 0.6) + np.abs(floor[:, 1]) > 0.1)]
    around = rng.uniform(0, 2 * np.pi, 4000)
    cylinder = np.stack([0.08 * np.cos(around), 0.08 * np.sin(around), rng.uniform(0, 0.25, 4000)], 1)
    box = rng.uniform([0.5, -0.1, 0.0], [0.7, 0.1, 0.2], (3000, 3))
    parts = [floor, cylinder, box]
    if rod_step is not None:
        along = np.arange(0.08, 0.5, rod_step)
        parts.append(np.stack([along, np.zeros_like(along), np.full_like(along, 0.1)], 1) +
                     rng.normal(0, 0.001, (len(along), 3)))
    angles = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    eyes = np.stack([0.8 * np.cos(angles), 0.8 * np.sin(angles), 0.5 + 0.1 * np.sin(3 * angles)], 1)
    return _scene(parts, 1, eyes, np.array([0.0, 0.0, 0.125]), np.array([0.0, 0.0, 1.0]), 0.25, rng)
