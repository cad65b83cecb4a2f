"""bg_depth's output: `depth.json` (provider, metric flag, intrinsics, size, and how the depth was obtained: the
sidecar's encoding, the model, the recovery of relative depth) and `depth.npy` (the map).

A photo without depth (provider "none") has depth.json only. docs/stage_contracts.md, section bg_depth. Records
written before `sidecar_format`, `model` and `recovery` existed read with them None.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from stages.contract.errors import StageError
from stages.lib.file_checks import load_npy, require_finite
from stages.records.files import MALFORMED, check_image_size, read_json, write_json


@dataclass
class DepthRecord:
    """A background photo's depth map and camera."""

    provider: str  # "sidecar" | "model" | "none" (records of older runs: "onnx")
    metric: bool  # depth in metres (relative depth: metres by the recovery's scale)
    K: np.ndarray  # [3, 3] intrinsics
    width: int
    height: int
    depth: np.ndarray | None = None  # [H, W] float32, 0 = missing; None for provider "none"
    sidecar_format: str | None = None  # the sidecar's encoding (stages/lib/depth/formats.py)
    model: dict | None = None  # {"name", "kind", "repo", "revision", "licence" | "path", "output"} of the model used
    recovery: dict | None = None  # relative depth: shift and scale and what they came from (stages/lib/depth/recovery.py)

    JSON: ClassVar[str] = "depth.json"
    ARRAY: ClassVar[str] = "depth.npy"

    def write(self, folder: Path) -> None:
        """Write depth.json (and depth.npy when there is a map) into `folder`."""
        if self.depth is not None:
            np.save(Path(folder) / self.ARRAY, self.depth)
        write_json(Path(folder) / self.JSON, {"provider": self.provider, "metric": bool(self.metric),
                                              "K": np.asarray(self.K).tolist(), "width": int(self.width),
                                              "height": int(self.height), "sidecar_format": self.sidecar_format,
                                              "model": self.model, "recovery": self.recovery}, indent=2)

    @classmethod
    def read(cls, folder: Path) -> "DepthRecord":
        """Read a bg_depth folder: depth.json and, unless the provider is "none", depth.npy of the size
        depth.json states (non-finite or negative values become 0 = missing). StageError naming the file
        when either is missing or malformed, or the map holds no valid depth."""
        record_path, depth_path = Path(folder) / cls.JSON, Path(folder) / cls.ARRAY
        info = read_json(record_path, "bg_depth")
        try:
            record = cls(str(info["provider"]), bool(info["metric"]),
                         np.asarray(info["K"], dtype=np.float64).reshape(3, 3), int(info["width"]), int(info["height"]),
                         None, info.get("sidecar_format"), info.get("model"), info.get("recovery"))
        except MALFORMED as error:
            raise StageError(f"depth record {record_path}: malformed ({error!r}); expected a bg_depth output "
                             "folder") from error
        require_finite(record_path, "depth record", K=record.K)
        if record.provider == "none":
            return record
        depth = load_npy(depth_path, "depth map")
        if depth.shape != (record.height, record.width):
            raise StageError(f"depth map {depth_path}: shape {depth.shape} does not match the size in "
                             f"{cls.JSON} ({record.height}, {record.width})")
        record.depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0).astype(np.float32)
        if not (record.depth > 0).any():
            raise StageError(f"depth map {depth_path}: no valid depth (all zero)")
        return record

    def check_size(self, folder: Path, width: int, height: int) -> None:
        """StageError unless this record is for a width x height photo."""
        check_image_size(Path(folder) / self.JSON, (self.width, self.height), (width, height), "photo")
