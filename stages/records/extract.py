"""extract's output `extract.json`: where the cut-out object stands in its model's frame.

docs/stage_contracts.md, section extract (object.ply beside it is a Gaussian PLY, stages/lib/gaussians/ply.py).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from stages.contract.errors import StageError
from stages.records.files import MALFORMED, read_json, write_json


@dataclass
class ExtractRecord:
    """The object's ground frame in model units and how extraction went."""

    normal: np.ndarray  # [3] unit, from the removed ground plane towards the object
    base_point: np.ndarray  # [3] on the plane under the object
    height: float  # object height along `normal`
    counts: dict[str, int] = field(default_factory=dict)  # Gaussians kept and removed per step
    scene_scale: float = 1.0  # model units per normalised unit
    scene_centre: np.ndarray = field(default_factory=lambda: np.zeros(3))  # [3] normalisation centre
    plane_source: str = ""  # "ransac" | "object_base" (stages/lib/objects/support.py)
    dbscan_eps: float = 0.0  # normalised units
    config: dict[str, Any] = field(default_factory=dict)  # the ExtractConfig used
    checks: dict[str, float] = field(default_factory=dict)  # the cut's checks: base_gap, layer, cut_density,
    #                                                          core_below, and each one's margin_<name> to its limit

    JSON: ClassVar[str] = "extract.json"

    def write(self, folder: Path) -> None:
        """Write extract.json into `folder`."""
        write_json(Path(folder) / self.JSON, {
            "normal": np.asarray(self.normal).tolist(), "base_point": np.asarray(self.base_point).tolist(),
            "height": float(self.height), "counts": self.counts, "scene_scale": float(self.scene_scale),
            "scene_centre": np.asarray(self.scene_centre).tolist(), "plane_source": self.plane_source,
            "dbscan_eps": float(self.dbscan_eps), "config": self.config, "checks": self.checks}, indent=2)

    @classmethod
    def read(cls, folder: Path) -> "ExtractRecord":
        """Read extract.json of an extract folder; the normal comes back unit length. StageError naming the
        file when it is missing or malformed, or its normal or height is degenerate."""
        path = Path(folder) / cls.JSON
        info = read_json(path, "extract")
        try:
            record = cls(np.asarray(info["normal"], dtype=np.float64), np.asarray(info["base_point"], dtype=np.float64),
                         float(info["height"]), dict(info["counts"]), float(info["scene_scale"]),
                         np.asarray(info["scene_centre"], dtype=np.float64), str(info["plane_source"]),
                         float(info["dbscan_eps"]), dict(info["config"]), dict(info["checks"]))
        except MALFORMED as error:
            raise StageError(f"{path}: malformed ({error!r}); expected an extract output folder") from error
        length = np.linalg.norm(record.normal)
        if record.normal.shape != (3,) or not np.isfinite(record.normal).all() or length < 1e-6 or not record.height > 0:
            raise StageError(f"{path} has a bad normal or height ({record.normal}, {record.height})")
        record.normal = record.normal / length
        return record
