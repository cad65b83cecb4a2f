"""Where the `sample` stage puts each file of the embedded sample, relative to its output folder.

The sample stage writes through these names and the pipeline points its nodes at them (docs/stage_contracts.md,
section sample); nothing else spells a path of the sample.
"""
from __future__ import annotations

import math
from typing import Any

from stages.records.bg_frames import depth_frame

BACKGROUND_FOLDERS = {"generic": "backgrounds", "indomain": "indomain"}  # background kind -> folder
WALK_FOLDER = "walk"  # the walk video through the in-domain rooms, its per-frame depth and its camera
ID_PREFIXES = {"generic": "bg", "indomain": "in"}
COUNT_SETTINGS = {"generic": "num_backgrounds", "indomain": "num_indomain"}  # SampleConfig field of each kind
TEST_CAMERAS = ("a", "b")
SUMMARY = "sample.json"


def object_folder(name: str) -> str:
    """The folder of one object's capture: video.mp4, gt.json, object_points.npy, masks/."""
    return f"objects/{name}"


def video(name: str) -> str:
    """One object's capture video."""
    return f"{object_folder(name)}/video.mp4"


def capture_masks(name: str) -> str:
    """The folder of one object's true masks, masks/%04d.png per video frame."""
    return f"{object_folder(name)}/masks"


def background_folder(kind: str) -> str:
    """The folder of the generic ("generic") or in-domain ("indomain") background photos."""
    if kind not in BACKGROUND_FOLDERS:
        raise ValueError(f"background kind must be one of {sorted(BACKGROUND_FOLDERS)}, not {kind!r}")
    return BACKGROUND_FOLDERS[kind]


def background_ids(cfg: Any, kind: str) -> list[str]:
    """Photo ids of the generic or in-domain backgrounds of a sample config (a SampleConfig or its DictConfig)."""
    background_folder(kind)
    return [f"{ID_PREFIXES[kind]}{i:04d}" for i in range(int(getattr(cfg, COUNT_SETTINGS[kind])))]


def closeup_indices(count: int, fraction: float) -> set[int]:
    """Which of `count` backgrounds are wall close-ups: ceil(count * fraction) of them, spread evenly."""
    return {i for i in range(count) if math.ceil((i + 1) * fraction - 1e-9) > math.ceil(i * fraction - 1e-9)}


def photo(kind: str, photo_id: str) -> str:
    """A background photo (PNG)."""
    return f"{background_folder(kind)}/{photo_id}.png"


def depth(kind: str, photo_id: str) -> str:
    """A background photo's depth sidecar: uint16 millimetres of camera z, 0 = none."""
    return f"{background_folder(kind)}/{photo_id}.depth.png"


def support(kind: str, photo_id: str) -> str:
    """A background photo's true support map: uint8, 255 = a horizontal surface objects may stand on."""
    return f"{background_folder(kind)}/{photo_id}.support.png"


def intrinsics(kind: str, photo_id: str) -> str:
    """A background photo's camera and metadata JSON ({"K": 3x3, "viewmat", ...})."""
    return f"{background_folder(kind)}/{photo_id}.json"


def walk_frames(cfg: Any) -> int:
    """How many frames the walk video of a sample config (a SampleConfig or its DictConfig) has: walk_seconds at fps."""
    return max(0, round(float(cfg.walk_seconds) * float(cfg.fps)))


def walk_video() -> str:
    """The walk through the in-domain rooms (mp4v), rendered after everything else."""
    return f"{WALK_FOLDER}/walk.mp4"


def walk_depth_folder() -> str:
    """The walk's per-frame depth: one file per video frame, depth_frame(index) (uint16 millimetres of camera z)."""
    return f"{WALK_FOLDER}/depth"


def walk_depth(index: int) -> str:
    """The depth file of the walk's frame `index`."""
    return f"{walk_depth_folder()}/{depth_frame(index)}"


def walk_camera() -> str:
    """The walk's camera JSON ({"K": 3x3, "width", "height", "fps", "frames": [{"index", "viewmat", "room"}]}), also
    the intrinsics file of every frame slot taken from it."""
    return f"{WALK_FOLDER}/walk.json"


def test_set(camera: str) -> str:
    """The COCO test set folder of camera "a" or "b" (images/ + annotations.json)."""
    if camera not in TEST_CAMERAS:
        raise ValueError(f"test camera must be one of {TEST_CAMERAS}, not {camera!r}")
    return f"test_{camera}"
