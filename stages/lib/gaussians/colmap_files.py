"""The binary files of a COLMAP model folder walked within bounds before COLMAP reads them.

COLMAP's reader (pycolmap.Reconstruction) trusts every count: a truncated images.bin makes it append the name of an
image forever, a lying count loops 10^19 times or reserves terabytes. `check_colmap_binary` walks cameras.bin,
images.bin, points3D.bin and the optional rigs.bin and frames.bin (COLMAP 3.12+) record by record, checks every
count against the bytes left before using it, every image name's end, every camera (PINHOLE, a size under the pixel
limit, finite positive focal lengths), and the references between them (an image's camera, a point's images and
their keypoints), so that COLMAP is only given files it reads in bounded time and memory. Little endian, as COLMAP
writes them: ids u32 (points u64), sizes u64, poses 7 doubles (quaternion w x y z, translation).
"""
from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np

from stages.contract.errors import StageError
from stages.lib.file_checks import check_pixels, regular_file

PINHOLE = 1  # COLMAP's camera model id of PINHOLE (fx, fy, cx, cy)
POSE = "7d"  # quaternion w x y z, translation x y z
TRACK = np.dtype([("image_id", "<u4"), ("point2D_idx", "<u4")])


class BinaryFile:
    """A cursor over the bytes of one COLMAP binary file: each read checked against the bytes left."""

    def __init__(self, path: Path):
        regular_file(path, "COLMAP model file")
        self.path, self.data, self.at = path, path.read_bytes(), 0

    def take(self, fmt: str) -> tuple:
        """The values of struct format `fmt` (little endian) at the cursor, which moves past them."""
        size = struct.calcsize("<" + fmt)
        if self.at + size > len(self.data):
            raise StageError(f"COLMAP model file {self.path}: truncated at byte {self.at} (needs {size} more bytes)")
        values = struct.unpack_from("<" + fmt, self.data, self.at)
        self.at += size
        return values

    def count(self, min_record: int, what: str) -> int:
        """A u64 count of records of at least `min_record` bytes, checked against the bytes left."""
        (count,) = self.take("Q")
        left = len(self.data) - self.at
        if count * min_record > left:
            raise StageError(f"COLMAP model file {self.path}: declares {count} {what} of at least {min_record} bytes, "
                             f"but {left} bytes follow; it is truncated or its header is wrong")
        return count

    def array(self, count: int, dtype: np.dtype, what: str) -> np.ndarray:
        """`count` records of `dtype` at the cursor, checked against the bytes left."""
        size = count * dtype.itemsize
        if self.at + size > len(self.data):
            raise StageError(f"COLMAP model file {self.path}: declares {count} {what}, more than the file holds")
        values = np.frombuffer(self.data, dtype, count, self.at)
        self.at += size
        return values

    def name(self) -> str:
        """A zero-terminated UTF-8 name at the cursor."""
        end = self.data.find(b"\0", self.at)
        if end < 0:
            raise StageError(f"COLMAP model file {self.path}: an image name at byte {self.at} has no end")
        try:
            name = self.data[self.at:end].decode("utf-8")
        except UnicodeDecodeError as error:
            raise StageError(f"COLMAP model file {self.path}: the image name at byte {self.at} is not UTF-8") from error
        self.at = end + 1
        return name


def _check_rigs(path: Path) -> None:
    """rigs.bin: rigs of sensors, each sensor past the first with an optional finite pose."""
    rigs = BinaryFile(path)
    for _ in range(rigs.count(8, "rigs")):
        rig_id, sensors = rigs.take("II")
        if sensors:
            rigs.take("iI")
        for _ in range(max(sensors - 1, 0)):
            if rigs.take("iIB")[2]:
                _finite_pose(path, f"a sensor of rig {rig_id}", rigs.take(POSE))


def _check_cameras(path: Path) -> set[int]:
    """cameras.bin: PINHOLE cameras of a size under the pixel limit with finite positive focal lengths; their ids."""
    cameras, ids = BinaryFile(path), set()
    for _ in range(cameras.count(24, "cameras")):
        camera_id, model, width, height = cameras.take("IiQQ")
        if model != PINHOLE:
            raise StageError(f"COLMAP model file {path}: camera {camera_id} has model id {model}, not PINHOLE "
                             f"({PINHOLE}); splat_train needs the sfm stage's undistorted PINHOLE cameras")
        check_pixels(path, f"COLMAP camera {camera_id} of", width, height)
        params = cameras.take("4d")
        if not all(math.isfinite(p) for p in params) or min(params[:2]) <= 0:
            raise StageError(f"COLMAP model file {path}: camera {camera_id} has parameters {params}, not finite "
                             "positive focal lengths and a finite principal point")
        ids.add(camera_id)
    return ids


def _finite_pose(path: Path, what: str, pose: tuple[float, ...]) -> None:
    """StageError unless the 7 values of a pose are finite."""
    if not all(math.isfinite(value) for value in pose):
        raise StageError(f"COLMAP model file {path}: {what} has a pose that is not finite: {pose}")


def _check_frames(path: Path) -> None:
    """frames.bin: frames of a rig with a finite pose and their data ids."""
    frames = BinaryFile(path)
    for _ in range(frames.count(68, "frames")):
        frame_id, _, *pose = frames.take("II" + POSE)
        _finite_pose(path, f"frame {frame_id}", tuple(pose))
        (data_ids,) = frames.take("I")
        frames.array(data_ids, np.dtype([("type", "<i4"), ("sensor", "<u4"), ("id", "<u8")]), "data ids")


def _check_images(path: Path, cameras: set[int]) -> dict[int, int]:
    """images.bin: images of known cameras with finite poses, names and keypoints; {image id: number of keypoints}."""
    images, keypoints = BinaryFile(path), {}
    for _ in range(images.count(73, "images")):
        image_id, *pose, camera_id = images.take("I" + POSE + "I")
        _finite_pose(path, f"image {image_id}", tuple(pose))
        if camera_id not in cameras:
            raise StageError(f"COLMAP model file {path}: image {image_id} names camera {camera_id}, which "
                             "cameras.bin does not hold")
        images.name()
        (points,) = images.take("Q")
        images.array(points, np.dtype([("xy", "<f8", 2), ("point3D_id", "<u8")]), "keypoints")
        keypoints[image_id] = points
    return keypoints


def _check_points(path: Path, keypoints: dict[int, int]) -> None:
    """points3D.bin: points whose tracks name images of images.bin and keypoints they have."""
    points = BinaryFile(path)
    for _ in range(points.count(51, "points")):
        point_id = points.take("Q3d3Bd")[0]
        (length,) = points.take("Q")
        for image_id, index in points.array(length, TRACK, "track elements").tolist():
            if index >= keypoints.get(image_id, 0):
                raise StageError(f"COLMAP model file {path}: point {point_id} is seen by keypoint {index} of image "
                                 f"{image_id}, which images.bin does not hold")


def check_colmap_binary(sparse_dir: Path) -> None:
    """Walk the binary model in `sparse_dir` (cameras.bin, images.bin, points3D.bin; rigs.bin and frames.bin when
    there); StageError naming the file and what is wrong."""
    sparse_dir = Path(sparse_dir)
    for optional, check in (("rigs.bin", _check_rigs), ("frames.bin", _check_frames)):
        if (sparse_dir / optional).exists():
            check(sparse_dir / optional)
    keypoints = _check_images(sparse_dir / "images.bin", _check_cameras(sparse_dir / "cameras.bin"))
    _check_points(sparse_dir / "points3D.bin", keypoints)
