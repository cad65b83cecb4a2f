"""sfm's output folder: `sparse/` (the undistorted COLMAP model, PINHOLE cameras, no `0/` folder),
`images/` (the undistorted frames, named as in the model) and `sfm.json` (the summary).

docs/stage_contracts.md, section sfm. The sfm stage writes through `SfmRecord.write`; splat_train, the
Cut-and-Paste cut-outs, benchmarks and tests read through `SfmRecord.read`.
"""
from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from stages.contract.errors import StageError
from stages.lib.gaussians.colmap import ColmapScene, read_colmap_scene
from stages.records.files import read_json, write_json

REQUIRED_KEYS = ("registered", "total", "camera", "source_camera")


@dataclass
class SfmRecord:
    """An sfm output folder: where its model and images are, and its summary (sfm.json)."""

    folder: Path
    summary: dict[str, Any]  # sfm.json: registered, total, camera, source_camera, seconds, attempts, ...

    JSON: ClassVar[str] = "sfm.json"
    SPARSE: ClassVar[str] = "sparse"
    IMAGES: ClassVar[str] = "images"

    @property
    def sparse_dir(self) -> Path:
        """The undistorted COLMAP model (cameras.bin, images.bin, points3D.bin)."""
        return self.folder / self.SPARSE

    @property
    def images_dir(self) -> Path:
        """The undistorted frames, named as in the model."""
        return self.folder / self.IMAGES

    @property
    def source_camera(self) -> dict[str, Any]:
        """The camera refined on the frames before undistortion: {"model", "width", "height", "params"}."""
        return self.summary["source_camera"]

    def image(self, name: str) -> Path:
        """The undistorted frame `name` (a registered image's name)."""
        return self.images_dir / name

    def scene(self) -> ColmapScene:
        """The registered frames (PINHOLE K, world-to-camera pose) and sparse points of the model."""
        return read_colmap_scene(self.sparse_dir)

    @classmethod
    def write(cls, folder: Path, summary: dict[str, Any], sparse: Path, images: Path) -> "SfmRecord":
        """Move an undistorted model folder and its images into `folder` and write sfm.json."""
        folder = Path(folder)
        shutil.move(str(sparse), str(folder / cls.SPARSE))
        shutil.move(str(images), str(folder / cls.IMAGES))
        write_json(folder / cls.JSON, summary, indent=1)
        return cls(folder, summary)

    @classmethod
    def read(cls, folder: Path) -> "SfmRecord":
        """The record of an sfm folder; StageError naming what is missing (sfm.json or its keys, sparse/,
        images/)."""
        folder = Path(folder)
        summary = read_json(folder / cls.JSON, "sfm")
        missing = [key for key in REQUIRED_KEYS if not isinstance(summary, dict) or key not in summary]
        if missing:
            raise StageError(f"{folder / cls.JSON}: malformed (no {', '.join(missing)}); expected an sfm output folder")
        for sub in (cls.SPARSE, cls.IMAGES):
            if not (folder / sub).is_dir():
                raise StageError(f"{folder / sub}: missing; expected an sfm output folder with {cls.SPARSE}/ and "
                                 f"{cls.IMAGES}/")
        return cls(folder, summary)
