"""Background photos with depth and placement planes: a metric floor seen by a level camera (with an object
to compose onto it), and a textured photo with an optional corner-wall depth sidecar."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from stages.compose import run as compose
from stages.contract.fan_in import fan_in
from stages.lib.gaussians.ply import write_ply
from stages.records.depth import DepthRecord
from stages.records.extract import ExtractRecord
from stages.records.planes import PlacementPlane, PlanesRecord
from tests.factories.splats import make_blob

WIDTH, HEIGHT = 160, 120
K = np.array([[150.0, 0.0, 80.0], [0.0, 150.0, 60.0], [0.0, 0.0, 1.0]])
CAMERA_HEIGHT = 1.0  # metres above the floor; the camera looks horizontally (floor: y = +1)
FLOOR_NORMAL = np.array([0.0, -1.0, 0.0])  # up in the camera frame


def floor_depth() -> np.ndarray:
    """Depth [H, W] of the floor seen from the camera, a wall at 8 m above the floor's far edge."""
    v = np.arange(HEIGHT, dtype=np.float64) + 0.5
    rows = np.where(v > K[1, 2], CAMERA_HEIGHT * K[1, 1] / np.maximum(v - K[1, 2], 1e-9), np.inf)
    return np.repeat(np.minimum(rows, 8.0)[:, None], WIDTH, axis=1).astype(np.float32)


def write_floor_scene(root: Path, with_planes: bool = True) -> dict[str, Path]:
    """compose's inputs for one object (make_blob) and one photo of the floor (noise, metric depth, one
    placement plane unless `with_planes` is false), written under `root`."""
    obj_dir, bg_path = root / "extract", root / "bg.png"
    obj_dir.mkdir(parents=True)
    write_ply(obj_dir / "object.ply", make_blob(view_dependent=True))
    ExtractRecord(np.array([0.0, 0.0, 1.0]), np.zeros(3), 2.0).write(obj_dir)
    rng = np.random.default_rng(1)
    cv2.imwrite(str(bg_path), rng.integers(0, 255, (HEIGHT, WIDTH, 3), dtype=np.uint8))
    depth_dir, planes_dir = root / "depth", root / "planes"
    depth_dir.mkdir()
    DepthRecord("sidecar", True, K, WIDTH, HEIGHT, floor_depth()).write(depth_dir)
    xs, zs = np.meshgrid(np.linspace(-0.8, 0.8, 9), np.linspace(2.8, 5.5, 10))
    points = np.stack([xs.ravel(), np.full(xs.size, CAMERA_HEIGHT), zs.ravel()], axis=1)
    planes_dir.mkdir()
    pixels = points @ K.T
    planes = [PlacementPlane(FLOOR_NORMAL, points.mean(0), 4.3, points, pixels[:, :2] / pixels[:, 2:])] if with_planes else []
    PlanesRecord(K, WIDTH, HEIGHT, FLOOR_NORMAL, True, planes).write(planes_dir)
    return {**fan_in({"blob": {"object": obj_dir}}, compose.INPUTS.object_kinds),
            **fan_in({"floor": {"background": bg_path, "planes": planes_dir, "depth": depth_dir}}, compose.INPUTS.photo_kinds)}


def corner_wall_depth(width: int, height: int, K: np.ndarray, corner_distance: float = 3.0) -> np.ndarray:
    """Depth [H, W] (metres) of a room corner seen from inside: two vertical walls at +-45 degrees
    meeting `corner_distance` ahead, no floor or other horizontal surface in view.

    Walls z = corner_distance -+ x; a pixel ray (x', y', 1) hits the nearer one at z = d / (1 + |x'|).
    """
    u = np.arange(width) + 0.5
    x_over_z = (u - K[0, 2]) / K[0, 0]                                   # [W]
    depth_row = corner_distance / (1.0 + np.abs(x_over_z))
    return np.repeat(depth_row[None, :], height, axis=0).astype(np.float32)


def write_background(folder: Path, name: str, width: int, height: int, with_wall_depth: bool) -> dict[str, Path]:
    """A textured photo `<name>.png` with `<name>.json` intrinsics and, optionally, a corner-wall
    `<name>.depth.npy` sidecar. Returns bg_depth's inputs {"image", ["depth"], "intrinsics"}."""
    folder.mkdir(parents=True, exist_ok=True)
    K = np.array([[0.9 * width, 0.0, width / 2], [0.0, 0.9 * width, height / 2], [0.0, 0.0, 1.0]])
    rng = np.random.default_rng(3)
    photo = cv2.resize(rng.integers(40, 220, (height // 8, width // 8, 3), dtype=np.uint8), (width, height),
                       interpolation=cv2.INTER_CUBIC)
    inputs = {"image": folder / f"{name}.png", "intrinsics": folder / f"{name}.json"}
    cv2.imwrite(str(inputs["image"]), photo)
    inputs["intrinsics"].write_text(json.dumps({"K": K.tolist()}))
    if with_wall_depth:
        inputs["depth"] = folder / f"{name}.depth.npy"
        np.save(inputs["depth"], corner_wall_depth(width, height, K))
    return inputs
