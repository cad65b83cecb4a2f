"""Valid small files of every format a user's input or a cache entry holds, written with the writers of their
libraries where they have one, and the byte-level edits of their headers the fuzz cases make
(tests/factories/fuzz_readers.py). None of them imports torch but `torch_file`."""
from __future__ import annotations

import io
import struct
import zlib
from pathlib import Path

import numpy as np
from numpy.lib import format as npy_format
from PIL import Image

PLY_COUNT = 20  # vertices of the seed PLY
PLY_NAMES = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(9)]
             + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])  # SH degree 1
WIDTH, HEIGHT = 64, 48  # the seed images and depth maps


def ply_values() -> np.ndarray:
    """The seed PLY's values: float32 [PLY_COUNT, len(PLY_NAMES)], a valid random scene."""
    values = np.random.default_rng(0).normal(0.0, 0.5, (PLY_COUNT, len(PLY_NAMES))).astype(np.float32)
    values[:, PLY_NAMES.index("rot_0")] += 1.0
    return values


def ply_bytes(header_lines: list[str] | None = None, values: np.ndarray | None = None) -> bytes:
    """A 3DGS PLY of PLY_COUNT Gaussians (SH degree 1): `header_lines` (default: the Inria header) and `values`
    float32 [PLY_COUNT, len(PLY_NAMES)] (default: ply_values())."""
    values = ply_values() if values is None else values
    if header_lines is None:
        header_lines = (["ply", "format binary_little_endian 1.0", f"element vertex {PLY_COUNT}"]
                        + [f"property float {name}" for name in PLY_NAMES] + ["end_header"])
    return ("\n".join(header_lines) + "\n").encode() + np.ascontiguousarray(values, "<f4").tobytes()


def ply_with_value(name: str, value: float) -> bytes:
    """The seed PLY with property `name` of its first vertex set to `value`."""
    values = ply_values()
    values[0, PLY_NAMES.index(name)] = value
    return ply_bytes(values=values)


SPLAT_RECORD = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])


def splat_bytes(position: float = 0.1, scale: float = 0.05) -> bytes:
    """20 .splat records; the first one's position x and scale x are `position` and `scale`."""
    records = np.zeros(20, SPLAT_RECORD)
    records["position"] = np.random.default_rng(0).normal(0, 0.5, (20, 3))
    records["scale"] = 0.05
    records["rgba"] = 200
    records["rot"] = (255, 128, 128, 128)
    records["position"][0, 0], records["scale"][0, 0] = position, scale
    return records.tobytes()


def png_bytes(array: np.ndarray, mode: str | None = None) -> bytes:
    """`array` ([H, W] or [H, W, 3]) as a PNG (16-bit for uint16)."""
    buffer = io.BytesIO()
    image = Image.fromarray(array, mode) if mode else Image.fromarray(array)
    image.save(buffer, format="PNG")
    return buffer.getvalue()


def depth_png() -> bytes:
    """A 16-bit PNG depth sidecar [HEIGHT, WIDTH] of millimetres (1.5 to 2.5 m)."""
    rng = np.random.default_rng(0)
    return png_bytes(rng.integers(1500, 2500, (HEIGHT, WIDTH)).astype(np.uint16))


def photo_png() -> bytes:
    """An RGB photo [HEIGHT, WIDTH] as a PNG."""
    return png_bytes(np.random.default_rng(1).integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8))


def photo_jpeg() -> bytes:
    """An RGB photo [HEIGHT, WIDTH] as a JPEG."""
    buffer = io.BytesIO()
    Image.fromarray(np.random.default_rng(2).integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)).save(buffer, "JPEG")
    return buffer.getvalue()


def png_size(data: bytes, width: int, height: int) -> bytes:
    """A PNG whose IHDR declares width x height (u32 each, modulo 2^32), its CRC made right again so that a
    reader believes the header."""
    ihdr = bytearray(data[12:29])  # b"IHDR" + 13 bytes
    struct.pack_into(">II", ihdr, 4, width % 2 ** 32, height % 2 ** 32)
    return data[:12] + bytes(ihdr) + struct.pack(">I", zlib.crc32(bytes(ihdr))) + data[33:]


def jpeg_size(data: bytes, width: int, height: int) -> bytes:
    """A JPEG whose baseline frame header (SOF0) declares width x height (u16 each, modulo 2^16)."""
    at = data.index(b"\xff\xc0") + 5  # marker, length (2), precision (1): then height, width
    return data[:at] + struct.pack(">HH", height % 2 ** 16, width % 2 ** 16) + data[at + 4:]


def npy_bytes(array: np.ndarray, header: dict | None = None, version: tuple[int, int] = (1, 0)) -> bytes:
    """`array` as .npy bytes, with the header dict (descr, fortran_order, shape) `header` when given (a lie)."""
    buffer = io.BytesIO()
    write = npy_format.write_array_header_1_0 if version == (1, 0) else npy_format.write_array_header_2_0
    write(buffer, header or npy_format.header_data_from_array_1_0(array))
    return buffer.getvalue() + array.tobytes()


def depth_npy() -> np.ndarray:
    """A float32 depth map [HEIGHT, WIDTH] of metres (1.5 to 2.5 m)."""
    return np.random.default_rng(0).uniform(1.5, 2.5, (HEIGHT, WIDTH)).astype(np.float32)


def pgm_bytes(width: int = WIDTH, height: int = HEIGHT, maxval: int = 65535, raw: np.ndarray | None = None) -> bytes:
    """An NYU raw-disparity PGM (P5, big endian): `raw` uint16 [HEIGHT, WIDTH] (default 500 to 1000)."""
    if raw is None:
        raw = np.random.default_rng(0).integers(500, 1000, (HEIGHT, WIDTH)).astype(np.uint16)
    return f"P5\n{width} {height}\n{maxval}\n".encode() + raw.astype(">u2").tobytes()


def colmap_model(folder: Path) -> None:
    """A COLMAP binary model in `folder`: one PINHOLE camera, three posed images with four keypoints each and
    four points seen by all three (cameras.bin, images.bin, points3D.bin, rigs.bin, frames.bin)."""
    import pycolmap

    reconstruction = pycolmap.Reconstruction()
    reconstruction.add_camera_with_trivial_rig(pycolmap.Camera(camera_id=1, model="PINHOLE", width=WIDTH,
                                                               height=HEIGHT, params=[50.0, 50.0, 32.0, 24.0]))
    for index in range(3):
        keypoints = pycolmap.Point2DList([pycolmap.Point2D(np.array([10.0 + j, 12.0])) for j in range(4)])
        image = pycolmap.Image(name=f"{index:04d}.png", camera_id=1, image_id=index + 1, points2D=keypoints)
        pose = np.hstack([np.eye(3), np.array([[0.0], [0.0], [3.0 + index]])])
        reconstruction.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pose))
    for point in range(4):
        track = pycolmap.Track()
        for index in range(3):
            track.add_element(index + 1, point)
        reconstruction.add_point3D(np.array([0.1 * point, 0.0, 0.0]), track, np.array([255, 0, 0], np.uint8))
    folder.mkdir(parents=True, exist_ok=True)
    reconstruction.write_binary(str(folder))


def video_bytes(folder: Path) -> bytes:
    """An 8-frame mp4v video [HEIGHT, WIDTH] (the sample's writer)."""
    from stages.lib.sample_scene.videos import write_mp4

    frames = [np.random.default_rng(k).integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8) for k in range(8)]
    write_mp4(folder / "seed.mp4", frames, 10.0)
    data = (folder / "seed.mp4").read_bytes()
    (folder / "seed.mp4").unlink()
    return data


def mp4_size(data: bytes, width: int, height: int) -> bytes:
    """An mp4v video whose sample description declares width x height (u16 each, modulo 2^16)."""
    at = data.index(b"mp4v") + 28  # the visual sample entry: 6 reserved, data index, 16 pre-defined, then the size
    return data[:at] + struct.pack(">HH", width % 2 ** 16, height % 2 ** 16) + data[at + 4:]


def mdat_size(data: bytes, size: int) -> bytes:
    """An MP4 whose media data box declares `size` bytes (u32, modulo 2^32)."""
    at = data.index(b"mdat") - 4
    return data[:at] + struct.pack(">I", size % 2 ** 32) + data[at + 4:]


def torch_file() -> bytes:
    """A small detector-like file written by torch.save."""
    import torch

    buffer = io.BytesIO()
    torch.save({"state_dict": {"weight": torch.arange(16.0).reshape(4, 4)}, "model_config": {"backbone": "x"},
                "category_names": ["mug"]}, buffer)
    return buffer.getvalue()


def zip_record_size(data: bytes, size: int) -> bytes:
    """A zip archive whose first central-directory entry declares `size` (u32, modulo 2^32) uncompressed bytes."""
    at = data.index(b"PK\x01\x02") + 24
    return data[:at] + struct.pack("<I", size % 2 ** 32) + data[at + 4:]
