"""Readers for depth files that sit beside a photo ("sidecar" depth), all returning metres.

Every reader returns float32 [H, W] metres with 0 = missing. Encodings:

- ``png_mm``: 16-bit PNG, millimetres (the sample backgrounds, many RGB-D apps).
- ``npy_m``:  NumPy ``.npy`` array [H, W] (or [H, W, 1]) in metres.
- ``tum``:    TUM RGB-D benchmark 16-bit PNG, metres = value / 5000.
- ``nyu``:    NYU Depth v2 raw Kinect disparity in a 16-bit PGM, metres = 351.3 / (1092.5 - raw).
              The PGM header claims big-endian samples, but the NYU toolbox dumps (and Open3D's test
              copy) hold the bytes swapped; Open3D reads them big-endian and swaps again. Raw Kinect
              disparity has 11 bits (2047 = no reading), so the reader takes the byte order whose
              values fit in 11 bits.
- ``sun``:    SUN RGB-D 16-bit PNG with the bits rotated: d = (v >> 3) | (v << 13) (16-bit), then mm.
"""
from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np
from PIL import Image

from stages.context import StageError

log = logging.getLogger(__name__)

SIDECAR_FORMATS = ("png_mm", "npy_m", "tum", "nyu", "sun")

_NYU_INVALID_RAW = 2047          # Kinect v1 "no reading" disparity
_NYU_MAX_VALID_RAW = 1092        # 351.3 / (1092.5 - raw) must stay positive


def detect_sidecar_format(path: Path) -> str:
    """Guess the encoding of a depth file from its extension and name.

    .npy -> npy_m; .pgm -> nyu; a name containing "tum" / "sun" / "nyu" -> that dataset;
    any other 16-bit PNG -> png_mm. Raises StageError for other extensions.
    """
    path = Path(path)
    name = path.name.lower()
    suffix = path.suffix.lower()
    if suffix == ".npy":
        return "npy_m"
    if suffix == ".pgm":
        return "nyu"
    if suffix == ".png":
        for dataset in ("tum", "sun", "nyu"):
            if re.search(rf"(^|[^a-z]){dataset}([^a-z]|$)", name):
                return dataset
        return "png_mm"
    raise StageError(
        f"depth sidecar {path}: cannot tell its encoding from the extension {suffix!r}; "
        f"use .png (uint16 mm), .npy (metres) or .pgm (NYU), or set sidecar_format to one of "
        f"{SIDECAR_FORMATS}")


def read_sidecar_depth(path: Path, fmt: str = "auto") -> np.ndarray:
    """Read a depth sidecar file as float32 metres [H, W] (0 = missing).

    fmt: "auto" (see detect_sidecar_format) or one of SIDECAR_FORMATS.
    """
    path = Path(path)
    if not path.is_file():
        raise StageError(f"depth sidecar {path}: file not found")
    if fmt == "auto":
        fmt = detect_sidecar_format(path)
    readers = {"png_mm": read_png_mm, "npy_m": read_npy_m, "tum": read_tum,
               "nyu": read_nyu, "sun": read_sun}
    if fmt not in readers:
        raise StageError(f"depth sidecar {path}: unknown sidecar_format {fmt!r}; "
                         f"expected 'auto' or one of {SIDECAR_FORMATS}")
    depth = readers[fmt](path)                                   # [H, W] metres
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0).astype(np.float32)
    if not (depth > 0).any():
        raise StageError(f"depth sidecar {path}: no valid depth (all pixels zero or invalid "
                         f"after decoding as {fmt!r}); check the file and sidecar_format")
    log.debug("read %s as %s: %dx%d, %.1f%% valid", path, fmt, depth.shape[1], depth.shape[0],
              100.0 * (depth > 0).mean())
    return depth


def _read_uint16_png(path: Path) -> np.ndarray:
    """Read a single-channel 16-bit PNG as uint16 [H, W]; StageError for anything else."""
    try:
        with Image.open(path) as image:
            mode = image.mode
            values = np.array(image)
    except Exception as error:  # PIL raises many types for broken files
        raise StageError(f"depth sidecar {path}: cannot read as an image ({error})") from error
    if values.ndim != 2 or mode not in ("I;16", "I;16B", "I;16L", "I"):
        raise StageError(f"depth sidecar {path}: expected a single-channel 16-bit PNG, "
                         f"got mode {mode!r} with shape {values.shape}")
    if values.min() < 0 or values.max() > 65535:
        raise StageError(f"depth sidecar {path}: values outside the 16-bit range")
    return values.astype(np.uint16)


def decode_mm(raw: np.ndarray) -> np.ndarray:
    """uint16 millimetres [H, W] -> float32 metres [H, W]."""
    return raw.astype(np.float32) / 1000.0


def decode_tum(raw: np.ndarray) -> np.ndarray:
    """TUM uint16 [H, W] (value / 5000 = metres) -> float32 metres [H, W]."""
    return raw.astype(np.float32) / 5000.0


def decode_nyu(raw: np.ndarray) -> np.ndarray:
    """NYU raw Kinect disparity uint16 [H, W] -> float32 metres [H, W] (invalid -> 0)."""
    raw = raw.astype(np.float32)
    valid = raw <= _NYU_MAX_VALID_RAW
    return np.where(valid, 351.3 / (1092.5 - np.minimum(raw, _NYU_MAX_VALID_RAW)), 0.0).astype(np.float32)


def decode_sun(raw: np.ndarray) -> np.ndarray:
    """SUN RGB-D bit-rotated uint16 [H, W] -> float32 metres [H, W]."""
    value = raw.astype(np.uint32)
    millimetres = ((value >> 3) | (value << 13)) & 0xFFFF
    return millimetres.astype(np.float32) / 1000.0


def read_png_mm(path: Path) -> np.ndarray:
    """16-bit PNG in millimetres -> metres [H, W]."""
    return decode_mm(_read_uint16_png(path))


def read_tum(path: Path) -> np.ndarray:
    """TUM RGB-D depth PNG -> metres [H, W]."""
    return decode_tum(_read_uint16_png(path))


def read_sun(path: Path) -> np.ndarray:
    """SUN RGB-D depth PNG -> metres [H, W]."""
    return decode_sun(_read_uint16_png(path))


def read_npy_m(path: Path) -> np.ndarray:
    """.npy metres [H, W] or [H, W, 1] -> float32 metres [H, W]."""
    try:
        values = np.load(path, allow_pickle=False)
    except Exception as error:
        raise StageError(f"depth sidecar {path}: cannot read as a .npy array ({error})") from error
    if values.ndim == 3 and values.shape[2] == 1:
        values = values[:, :, 0]
    if values.ndim != 2 or not np.issubdtype(values.dtype, np.number):
        raise StageError(f"depth sidecar {path}: expected a numeric [H, W] array of metres, "
                         f"got dtype {values.dtype} shape {values.shape}")
    return values.astype(np.float32)


def read_nyu(path: Path) -> np.ndarray:
    """NYU raw-disparity PGM (P5, maxval 65535) -> metres [H, W]."""
    data = path.read_bytes()
    header = re.match(rb"P5\s+(\d+)\s+(\d+)\s+(\d+)\s", data)
    if header is None:
        raise StageError(f"depth sidecar {path}: not a binary PGM (P5) file")
    width, height, maxval = (int(group) for group in header.groups())
    if maxval < 256 or len(data) - header.end() < width * height * 2:
        raise StageError(f"depth sidecar {path}: expected a 16-bit PGM of {width}x{height}, "
                         f"got maxval {maxval} and {len(data) - header.end()} data bytes")
    samples = np.frombuffer(data, dtype=">u2", count=width * height, offset=header.end())
    raw = samples.reshape(height, width)
    swapped = raw.byteswap()
    if raw.max() > _NYU_INVALID_RAW and swapped.max() <= _NYU_INVALID_RAW:
        raw = swapped
    elif raw.max() > _NYU_INVALID_RAW:
        raise StageError(f"depth sidecar {path}: values do not look like 11-bit Kinect disparity "
                         f"in either byte order (max {raw.max()} / {swapped.max()})")
    return decode_nyu(raw)
