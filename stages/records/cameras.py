"""splat_train's output `cameras.json`: every registered frame's camera in the scene's frame.

Cameras follow stages/lib/geometry.py (OpenCV axes, world-to-camera viewmats). docs/stage_contracts.md,
section splat_train.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np

from stages.contract.errors import StageError
from stages.lib.file_checks import check_pixels, require_finite
from stages.records.files import MALFORMED, read_json, write_json


@dataclass
class CameraFrame:
    """One frame: its image file (relative to the sfm output's images/), intrinsics and pose."""

    file: str
    K: np.ndarray  # [3, 3] at the frame's original resolution
    viewmat: np.ndarray  # [4, 4] world-to-camera
    width: int
    height: int


@dataclass
class CamerasRecord:
    """The frames of a trained scene and which of them were held out of training."""

    width: int
    height: int
    frames: list[CameraFrame]
    held_out: list[str] = field(default_factory=list)  # files of the evaluation frames

    JSON: ClassVar[str] = "cameras.json"

    @property
    def viewmats(self) -> np.ndarray:
        """World-to-camera matrices [C, 4, 4] of all frames."""
        return np.stack([frame.viewmat for frame in self.frames]).reshape(-1, 4, 4)

    def write(self, folder: Path) -> None:
        """Write cameras.json into `folder`."""
        write_json(Path(folder) / self.JSON, {
            "width": int(self.width), "height": int(self.height),
            "frames": [{"file": f.file, "K": np.asarray(f.K).tolist(), "viewmat": np.asarray(f.viewmat).tolist(),
                        "width": int(f.width), "height": int(f.height)} for f in self.frames],
            "held_out": list(self.held_out)}, indent=1)

    @classmethod
    def exists(cls, folder: Path) -> bool:
        """Whether `folder` holds a cameras.json."""
        return (Path(folder) / cls.JSON).is_file()

    @classmethod
    def read(cls, folder: Path) -> "CamerasRecord":
        """Read cameras.json of a splat_train folder. StageError naming the file when it is missing or
        malformed (e.g. a viewmat that is not 4x4)."""
        path = Path(folder) / cls.JSON
        info = read_json(path, "splat_train")
        try:
            frames = [CameraFrame(str(f["file"]), _matrix(f["K"], 3), _matrix(f["viewmat"], 4), int(f["width"]),
                                  int(f["height"])) for f in info["frames"]]
            record = cls(int(info["width"]), int(info["height"]), frames, [str(name) for name in info["held_out"]])
        except MALFORMED as error:
            raise StageError(f"cannot read camera poses from {path}: {error!r}") from error
        require_finite(path, "camera record", K=[f.K for f in frames], viewmat=[f.viewmat for f in frames])
        for frame in [record, *frames]:
            check_pixels(path, "camera record", frame.width, frame.height)
        return record


def _matrix(value, size: int) -> np.ndarray:
    """A size x size float64 matrix from nested lists; ValueError for any other shape."""
    matrix = np.asarray(value, dtype=np.float64)
    if matrix.shape != (size, size):
        raise ValueError(f"expected a {size}x{size} matrix, got shape {matrix.shape}")
    return matrix
