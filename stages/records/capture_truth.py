"""The sample's ground truth of one object capture, `objects/<name>/gt.json` (docs/stage_contracts.md,
section sample): the camera of every video frame, the support plane, and where the object's surface
points are. Benchmarks score sfm and extract against it."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from stages.contract.errors import StageError
from stages.lib.file_checks import load_npy, require_finite
from stages.records.files import MALFORMED, read_json, write_json


@dataclass
class CaptureTruth:
    """A capture's true cameras and scene (world units are metres)."""

    name: str
    height_m: float
    K: np.ndarray  # [3, 3] of the video frames
    width: int
    height: int
    fps: float
    viewmats: dict[int, np.ndarray]  # video frame index -> world-to-camera [4, 4]
    ground_normal: np.ndarray  # [3] unit, the support plane's normal (up)
    ground_point: np.ndarray  # [3] a point of the support plane
    object_points_file: str = ""  # [M, 3] float32 surface points beside gt.json ("" = none)
    support: str = ""  # what the object stands on ("floor" | "table")
    orbit_radius_m: float = 0.0
    seed: int = 0  # the sample seed the object and its capture were made with

    JSON: ClassVar[str] = "gt.json"

    def write(self, folder: Path) -> None:
        """Write gt.json into `folder`."""
        write_json(Path(folder) / self.JSON, {
            "name": self.name, "height_m": self.height_m, "K": np.asarray(self.K).tolist(), "width": self.width,
            "height": self.height, "fps": self.fps,
            "frames": [{"index": index, "viewmat": np.asarray(viewmat).tolist()} for index, viewmat in self.viewmats.items()],
            "ground_normal": np.asarray(self.ground_normal).tolist(), "ground_point": np.asarray(self.ground_point).tolist(),
            "object_points_file": self.object_points_file, "support": self.support,
            "orbit_radius_m": self.orbit_radius_m, "seed": self.seed}, indent=1)

    @classmethod
    def read(cls, folder: Path) -> "CaptureTruth":
        """Read gt.json of a sample object folder; StageError naming the file when it is missing or malformed."""
        path = Path(folder) / cls.JSON
        info = read_json(path, "sample")
        try:
            truth = cls(str(info["name"]), float(info["height_m"]), np.asarray(info["K"], dtype=np.float64).reshape(3, 3),
                       int(info["width"]), int(info["height"]), float(info["fps"]),
                       {int(f["index"]): np.asarray(f["viewmat"], dtype=np.float64).reshape(4, 4) for f in info["frames"]},
                       np.asarray(info["ground_normal"], dtype=np.float64), np.asarray(info["ground_point"], dtype=np.float64),
                       str(info["object_points_file"]), str(info["support"]), float(info["orbit_radius_m"]),
                       int(info["seed"]))
        except MALFORMED as error:
            raise StageError(f"{path}: malformed ({error!r}); expected a sample object folder") from error
        require_finite(path, "capture truth", K=truth.K, viewmats=list(truth.viewmats.values()) or [0.0])
        return truth

    def object_points(self, folder: Path) -> np.ndarray:
        """The object's surface points [M, 3] (metres, world frame) stored beside gt.json in `folder`."""
        return load_npy(Path(folder) / self.object_points_file, "object points")
