"""Loading a background for composition: photo, camera, filtered depth and placement planes."""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from stages.composition.occlusion import filtered_background_depth
from stages.composition.placement import Plane
from stages.context import StageError
from stages.imageio import load_photo

DEFAULT_FOV_DEG = 55.0  # paper: assumed horizontal field of view of a background photo


@dataclass
class Background:
    """One background ready for placement (camera frame = world frame)."""

    bg_id: str
    image: np.ndarray  # [H, W, 3] float32 RGB in [0, 1]
    K: np.ndarray  # [3, 3]
    depth: np.ndarray | None  # [H, W] median-filtered depth, +inf = missing; None without depth
    planes: list[Plane] = field(default_factory=list)
    metric: bool = False
    plane_issue: str | None = None  # why plane placement is impossible here (None = possible)

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.image.shape[1], self.image.shape[0]


def default_intrinsics(width: int, height: int, fov_deg: float = DEFAULT_FOV_DEG) -> np.ndarray:
    """Pinhole K [3, 3] with the given horizontal field of view and a central principal point."""
    focal = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    return np.array([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])


def background_ids(inputs: dict[str, Path], stage: str) -> list[str]:
    """Background ids of the `background:<id>` inputs, sorted; StageError when there is none."""
    ids = sorted(key.split(":", 1)[1] for key in inputs if key.startswith("background:"))
    if not ids:
        raise StageError(f"{stage}: no `background:<id>` inputs")
    return ids


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise StageError(f"cannot read {path}: {err}") from err


def _read_planes(planes_dir: Path, width: int, height: int) -> tuple[list[Plane], bool, np.ndarray]:
    info = _read_json(planes_dir / "planes.json")
    if (int(info.get("width", width)), int(info.get("height", height))) != (width, height):
        raise StageError(f"{planes_dir / 'planes.json'} is for a {info.get('width')}x{info.get('height')} image, "
                         f"the background is {width}x{height}")
    planes = []
    for k, p in enumerate(info.get("planes", [])):
        points = np.asarray(p.get("points", []), dtype=np.float64).reshape(-1, 3)
        normal = np.asarray(p["normal"], dtype=np.float64)
        if len(points) == 0 or not np.isfinite(normal).all() or np.linalg.norm(normal) < 1e-6:
            raise StageError(f"{planes_dir / 'planes.json'}: plane {k} has no points or a bad normal")
        planes.append(Plane(normal / np.linalg.norm(normal), points, float(p.get("area", 0.0))))
    return planes, bool(info.get("metric", False)), np.asarray(info["K"], dtype=np.float64)


def _read_depth(depth_dir: Path, width: int, height: int) -> tuple[np.ndarray | None, dict]:
    info = _read_json(depth_dir / "depth.json")
    if info.get("provider", "none") == "none" or not (depth_dir / "depth.npy").is_file():
        return None, info
    depth = np.load(depth_dir / "depth.npy").astype(np.float32)
    if depth.shape != (height, width):
        raise StageError(f"{depth_dir / 'depth.npy'} has shape {depth.shape}, the background is {height}x{width}")
    return depth, info


def load_background(bg_id: str, image_path: Path, planes_dir: Path | None, depth_dir: Path | None,
                    median_size: int, image_size: tuple[int, int] | None = None) -> Background:
    """Read a background and its planes and depth; rescale everything to `image_size` (w, h) if given.

    Without depth, without planes, or with an empty plane list the background is still usable, with
    `plane_issue` saying why objects can only be placed at random.
    """
    rgb = load_photo(image_path)  # the loader bg_depth used, so pixels line up with depth.npy
    height, width = rgb.shape[:2]
    K, depth, planes, metric, issue = default_intrinsics(width, height), None, [], False, None
    if depth_dir is not None:
        depth, depth_info = _read_depth(depth_dir, width, height)
        if depth_info.get("K") is not None:
            K = np.asarray(depth_info["K"], dtype=np.float64)
    if planes_dir is not None:
        planes, metric, K = _read_planes(planes_dir, width, height)
    if depth is None:
        issue = "no depth"
    elif planes_dir is None:
        issue = "no planes input"
    elif not planes:
        issue = "no planes found"
    if image_size is not None and tuple(image_size) != (width, height):
        new_w, new_h = int(image_size[0]), int(image_size[1])
        K = np.diag([new_w / width, new_h / height, 1.0]) @ K
        rgb = cv2.resize(rgb, (new_w, new_h), interpolation=cv2.INTER_AREA)
        if depth is not None:
            depth = cv2.resize(depth, (new_w, new_h), interpolation=cv2.INTER_NEAREST)
    filtered = None if depth is None else filtered_background_depth(depth, median_size)
    return Background(bg_id, rgb.astype(np.float32) / 255.0, K, filtered, planes, metric, issue)
