"""Loading a background for composition: photo, camera, filtered depth and placement planes."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from stages.contract.errors import StageError
from stages.contract.fan_in import fanned
from stages.lib.composition.occlusion import filtered_background_depth
from stages.lib.geometry import fov_intrinsics
from stages.lib.imageio import load_photo
from stages.records.bg_frames import BgFramesRecord
from stages.records.depth import DepthRecord
from stages.records.planes import PlacementPlane, PlanesRecord


@dataclass
class Background:
    """One background ready for placement (camera frame = world frame)."""

    bg_id: str
    image: np.ndarray  # [H, W, 3] float32 RGB in [0, 1]
    K: np.ndarray  # [3, 3]
    depth: np.ndarray | None  # [H, W] median-filtered depth, +inf = missing; None without depth
    planes: list[PlacementPlane] = field(default_factory=list)
    metric: bool = False
    plane_issue: str | None = None  # why plane placement is impossible here (None = possible)

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.image.shape[1], self.image.shape[0]


def plane_issue(has_depth: bool, planes: list[PlacementPlane] | None) -> str | None:
    """Why objects cannot stand on a background's planes (None: they can): "no depth", "no planes input"
    (planes None) or "no planes found"."""
    if not has_depth:
        return "no depth"
    if planes is None:
        return "no planes input"
    return None if planes else "no planes found"


def plane_issues(inputs: dict[str, Path]) -> dict[str, str]:
    """{photo id: plane_issue} of the `background` inputs without a placement plane (reads their records)."""
    planes, depth = fanned(inputs, "planes"), fanned(inputs, "depth")
    issues = {}
    for bg_id in fanned(inputs, "background"):
        has_depth = bg_id in depth and DepthRecord.read(depth[bg_id]).depth is not None
        issue = plane_issue(has_depth, PlanesRecord.read(planes[bg_id]).planes if bg_id in planes else None)
        if issue is not None:
            issues[bg_id] = issue
    return issues


def load_background(bg_id: str, image_path: Path, planes_dir: Path | None, depth_dir: Path | None,
                    median_size: int, image_size: tuple[int, int] | None = None) -> Background:
    """Read a background and its planes and depth; rescale everything to `image_size` (w, h) if given.

    Without depth, without planes, or with an empty plane list the background is still usable, with
    `plane_issue` saying why objects can only be placed at random.
    """
    rgb = load_photo(image_path)  # the loader bg_depth used, so pixels line up with depth.npy
    height, width = rgb.shape[:2]
    K, depth, planes, metric = fov_intrinsics(width, height), None, [], False
    if depth_dir is not None:
        depth_record = DepthRecord.read(depth_dir)
        depth_record.check_size(depth_dir, width, height)
        depth, K = depth_record.depth, depth_record.K
    if planes_dir is not None:
        planes_record = PlanesRecord.read(planes_dir)
        planes_record.check_size(planes_dir, width, height)
        planes, metric, K = planes_record.planes, planes_record.metric, planes_record.K
    issue = plane_issue(depth is not None, planes if planes_dir is not None else None)
    if image_size is not None and tuple(image_size) != (width, height):
        new_w, new_h = int(image_size[0]), int(image_size[1])
        K = np.diag([new_w / width, new_h / height, 1.0]) @ K
        rgb = cv2.resize(rgb, (new_w, new_h), interpolation=cv2.INTER_AREA)
        if depth is not None:
            depth = cv2.resize(depth, (new_w, new_h), interpolation=cv2.INTER_NEAREST)
    filtered = None if depth is None else filtered_background_depth(depth, median_size)
    return Background(bg_id, rgb.astype(np.float32) / 255.0, K, filtered, planes, metric, issue)


def empty_slots(inputs: dict[str, Path]) -> dict[str, str]:
    """{photo id: why} of the `background` inputs that are frame slots their video could not fill
    (stages/records/bg_frames.py). compose never gets one: their bg_depth nodes are empty, so the engine leaves their
    photos out; cut_and_paste, which reads the photo alone, leaves them out by this."""
    return {bg_id: why for bg_id, photo in fanned(inputs, "background").items()
            if not Path(photo).exists() and (why := BgFramesRecord.empty_reason(Path(photo)))}


def load_backgrounds(inputs: dict[str, Path], stage: str, median_size: int,
                     image_size: list[int] | None = None) -> list[Background]:
    """Every `background` input (but empty frame slots: empty_slots) with its `planes` and `depth` inputs when the
    stage has them, by photo id; rescaled to image_size [width, height] when given. StageError when there is no
    background."""
    empty = empty_slots(inputs)
    photos = {bg_id: photo for bg_id, photo in fanned(inputs, "background").items() if bg_id not in empty}
    if not photos:
        raise StageError(f"{stage}: no background inputs")
    planes, depth = fanned(inputs, "planes"), fanned(inputs, "depth")
    size = None if image_size is None else (int(image_size[0]), int(image_size[1]))
    return [load_background(bg_id, photo, planes.get(bg_id), depth.get(bg_id), median_size, size)
            for bg_id, photo in photos.items()]
