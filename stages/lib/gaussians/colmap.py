"""Read an sfm stage output (COLMAP sparse model + undistorted images) into plain arrays.

COLMAP's PINHOLE intrinsics put the centre of the top-left pixel at (0.5, 0.5), the convention of
our rasterizer, so K is used as is (scaled with the image when training at a lower resolution).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from stages.contract.errors import StageError
from stages.lib.file_checks import require_finite
from stages.lib.gaussians.colmap_files import check_colmap_binary


@dataclass
class ColmapFrame:
    """One registered image: file name (relative to images/), intrinsics and world-to-camera pose."""

    name: str
    K: np.ndarray  # [3, 3] float64
    viewmat: np.ndarray  # [4, 4] float64, world-to-camera (OpenCV axes)
    width: int
    height: int


@dataclass
class ColmapScene:
    """Registered frames (sorted by name) and the sparse points with their colours."""

    frames: list[ColmapFrame]
    points: np.ndarray  # [P, 3] float64
    colors: np.ndarray  # [P, 3] float32 in [0, 1]


def read_colmap_scene(sparse_dir: Path) -> ColmapScene:
    """Load cameras, registered images and points3D of a COLMAP binary model folder (PINHOLE cameras only), its
    files walked within bounds first (stages/lib/gaussians/colmap_files.py); StageError naming what is wrong, non-finite
    poses and points included."""
    sparse_dir = Path(sparse_dir)
    if not sparse_dir.is_dir():
        raise StageError(f"{sparse_dir}: COLMAP sparse model folder not found (expected the sfm stage's sparse/)")
    check_colmap_binary(sparse_dir)
    try:
        reconstruction = pycolmap.Reconstruction(str(sparse_dir))
    except Exception as error:  # noqa: BLE001 - pycolmap raises plain runtime errors on bad files
        raise StageError(f"{sparse_dir}: cannot read the COLMAP model: {error}") from error
    frames = []
    for image in reconstruction.images.values():
        if not image.has_pose:
            continue
        camera = reconstruction.cameras[image.camera_id]
        if camera.model.name != "PINHOLE":
            raise StageError(f"{sparse_dir}: camera {image.camera_id} of {image.name} is {camera.model.name}; "
                             "splat_train needs undistorted PINHOLE cameras (run the sfm stage's undistortion)")
        viewmat = np.eye(4)
        viewmat[:3] = image.cam_from_world().matrix()
        frames.append(ColmapFrame(image.name, np.asarray(camera.calibration_matrix(), dtype=np.float64),
                                  viewmat, int(camera.width), int(camera.height)))
    if not frames:
        raise StageError(f"{sparse_dir}: the COLMAP model has no registered images")
    frames.sort(key=lambda frame: frame.name)
    points3d = list(reconstruction.points3D.values())
    points = np.array([p.xyz for p in points3d], dtype=np.float64).reshape(-1, 3)
    colors = np.array([p.color for p in points3d], dtype=np.float32).reshape(-1, 3) / 255.0
    require_finite(sparse_dir, "COLMAP model", K=[f.K for f in frames], viewmat=[f.viewmat for f in frames],
                   points=points)
    return ColmapScene(frames, points, colors)
