"""planes' output `planes.json`: the horizontal placement planes of one background photo.

Coordinates are in the photo's camera frame (OpenCV axes); `pixels` are continuous pixel coordinates
in the K convention (top-left pixel centre at (0.5, 0.5)). docs/stage_contracts.md, section planes.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np

from stages.contract.errors import StageError
from stages.lib.file_checks import require_finite
from stages.records.files import MALFORMED, check_image_size, read_json, write_json


@dataclass
class PlacementPlane:
    """One horizontal surface an object can stand on."""

    normal: np.ndarray  # [3] unit, pointing up
    center: np.ndarray  # [3]
    area: float  # visible area, depth units squared
    points: np.ndarray  # [M, 3] placement points on the plane
    pixels: np.ndarray  # [M, 2] their (u, v) pixel coordinates


@dataclass
class PlanesRecord:
    """The placement planes of a photo, with its camera and up axis."""

    K: np.ndarray  # [3, 3]
    width: int
    height: int
    up: np.ndarray  # [3] camera frame
    metric: bool  # depth units are metres
    planes: list[PlacementPlane] = field(default_factory=list)

    JSON: ClassVar[str] = "planes.json"

    def write(self, folder: Path) -> None:
        """Write planes.json into `folder` (coordinates rounded to 5 decimals, normals to 6, pixels to 2)."""
        write_json(Path(folder) / self.JSON, {
            "K": np.asarray(self.K).tolist(), "width": int(self.width), "height": int(self.height),
            "up": _rounded(self.up, 6), "metric": bool(self.metric),
            "planes": [{"normal": _rounded(p.normal, 6), "center": _rounded(p.center, 5), "area": round(float(p.area), 6),
                        "points": _rounded(p.points, 5), "pixels": _rounded(p.pixels, 2)} for p in self.planes]})

    @classmethod
    def read(cls, folder: Path) -> "PlanesRecord":
        """Read planes.json of a planes folder; normals come back unit length. StageError naming the file
        when it is missing or malformed, or a plane has no points or a degenerate normal."""
        path = Path(folder) / cls.JSON
        info = read_json(path, "planes")
        try:
            record = cls(np.asarray(info["K"], dtype=np.float64).reshape(3, 3), int(info["width"]),
                         int(info["height"]), np.asarray(info["up"], dtype=np.float64), bool(info["metric"]))
            for k, plane in enumerate(info["planes"]):
                points = np.asarray(plane["points"], dtype=np.float64).reshape(-1, 3)
                normal = np.asarray(plane["normal"], dtype=np.float64)
                if len(points) == 0 or not np.isfinite(normal).all() or np.linalg.norm(normal) < 1e-6:
                    raise StageError(f"{path}: plane {k} has no points or a bad normal")
                record.planes.append(PlacementPlane(normal / np.linalg.norm(normal),
                                                    np.asarray(plane["center"], dtype=np.float64),
                                                    float(plane["area"]), points,
                                                    np.asarray(plane["pixels"], dtype=np.float64).reshape(-1, 2)))
        except MALFORMED as error:
            raise StageError(f"{path}: malformed ({error!r}); expected a planes output folder") from error
        require_finite(path, "planes record", K=record.K)
        return record

    def check_size(self, folder: Path, width: int, height: int) -> None:
        """StageError unless this record is for a width x height photo."""
        check_image_size(Path(folder) / self.JSON, (self.width, self.height), (width, height), "background")


def _rounded(values: np.ndarray, decimals: int) -> list:
    """Nested lists of `values` rounded to `decimals`."""
    return np.round(np.asarray(values, dtype=np.float64), decimals).tolist()
