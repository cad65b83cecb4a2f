"""Reading files that come from strangers (a user's downloads, a disk that failed) within bounds: every check raises
StageError naming the file and what is wrong, before anything is allocated from what the file declares.

- `regular_file`: the path is a readable regular file (not missing, not a folder, not unreadable); its size.
- `check_declared`: the bytes a header declares fit in the file (a PLY saying 10^10 vertices in 620 bytes).
- `check_pixels`: an image's or video frame's declared size is under the pixel limit, `max_image_pixels()`:
  MAX_PIXELS_ENV when set (dag.py sets it from `run.max_image_pixels`, and worker processes inherit it), else
  DEFAULT_MAX_PIXELS.
- `require_finite`: no NaN or infinity where none can be meant (a splat's positions, a camera, a box).
- `load_json`: a JSON file parsed, with every way that fails (bytes, syntax, nesting too deep) as StageError.
- `npy_header` / `load_npy`: a .npy array's header read and its data size checked against the file first.
"""
from __future__ import annotations

import json
import math
import os
import stat
from pathlib import Path
from typing import Any

import numpy as np
from numpy.lib import format as npy_format

from stages.contract.errors import StageError

MAX_PIXELS_ENV = "CUT_AND_SPLAT_MAX_IMAGE_PIXELS"
DEFAULT_MAX_PIXELS = 50_000_000  # 50 megapixels: an 8660 x 5774 photo, 8K video frames (33); reading one of them
#                                  peaks at 0.4 GB (a photo) to 0.6 GB (a 16-bit depth map)
NPY_MAX_HEADER = 10_000  # bytes of a .npy header (numpy's own default limit)


def max_image_pixels() -> int:
    """The pixel limit of an image or video frame: MAX_PIXELS_ENV when set, else DEFAULT_MAX_PIXELS."""
    return int(os.environ.get(MAX_PIXELS_ENV, DEFAULT_MAX_PIXELS))


def regular_file(path: Path, what: str) -> int:
    """The size in bytes of `path`; StageError naming it, as `what` (e.g. "depth sidecar"), when it is missing, a
    folder or another non-file, or cannot be read (permissions)."""
    path = Path(path)
    try:
        info = path.stat()
    except FileNotFoundError as error:
        raise StageError(f"{what} {path}: not found") from error
    except (OSError, ValueError) as error:  # a name too long, a link loop, a NUL byte
        raise StageError(f"{what} {path}: cannot be found ({error})") from error
    if stat.S_ISDIR(info.st_mode):
        raise StageError(f"{what} {path}: is a folder, expected a file")
    if not stat.S_ISREG(info.st_mode):
        raise StageError(f"{what} {path}: not a regular file")
    try:
        with open(path, "rb"):
            pass
    except OSError as error:
        raise StageError(f"{what} {path}: cannot be read ({error.strerror or error}); check its permissions") from error
    return info.st_size


def check_declared(path: Path, what: str, declared: int, available: int, declares: str) -> None:
    """StageError unless `declared` bytes (what the header `declares`, e.g. "10 vertices of 62 bytes") fit in the
    `available` bytes the file holds after its header."""
    if declared < 0 or declared > available:
        raise StageError(f"{what} {path}: its header declares {declares} ({declared} bytes), but the file holds "
                         f"{available} bytes after its header; it is truncated or its header is wrong")


def count_text(number: int) -> str:
    """A whole number as text, a huge one (a lying header's 10^400) as its power of ten."""
    return str(number) if abs(number) < 10 ** 15 else f"about 10^{int(math.log10(abs(number)))}"


def check_pixels(path: Path, what: str, width: int, height: int) -> None:
    """StageError unless width x height is a positive size of at most max_image_pixels() pixels."""
    limit, size = max_image_pixels(), f"{count_text(width)}x{count_text(height)}"
    if width <= 0 or height <= 0:
        raise StageError(f"{what} {path}: its size {size} is empty or negative")
    if width * height > limit:
        megapixels = f"{width * height / 1e6:.1f}" if width * height < 10 ** 15 else count_text(width * height // 10 ** 6)
        raise StageError(f"{what} {path}: {size} is {megapixels} megapixels, above the limit of {limit / 1e6:g} "
                         "megapixels; downscale it, or raise run.max_image_pixels")


def require_finite(path: Path, what: str, **arrays: np.ndarray) -> None:
    """StageError naming the first of `arrays` (name -> array of any shape) that holds NaN or infinite values."""
    for name, values in arrays.items():
        bad = ~np.isfinite(np.asarray(values, dtype=np.float64))
        if bad.any():
            raise StageError(f"{what} {path}: its {name} hold {int(bad.sum())} NaN or infinite values")


def finite_number(value: Any) -> bool:
    """Whether `value` is a JSON number (int or float, not bool) that is finite."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def load_json(path: Path, what: str) -> Any:
    """The parsed JSON of `path`; StageError naming it when it is not a readable file, not UTF-8 or not JSON
    (nesting too deep included)."""
    regular_file(path, what)
    try:
        return json.loads(Path(path).read_bytes())
    except (ValueError, RecursionError) as error:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        raise StageError(f"{what} {path}: not valid JSON ({type(error).__name__}: {str(error)[:200]})") from error


def npy_header(path: Path, what: str) -> tuple[tuple[int, ...], np.dtype, int]:
    """(shape, dtype, offset of the data) of a .npy file whose data the file holds in full; StageError naming it
    when it is not a .npy file, holds Python objects, or is shorter than its header declares."""
    size = regular_file(path, what)
    with open(path, "rb") as handle:
        try:
            version = npy_format.read_magic(handle)
            read = npy_format.read_array_header_1_0 if version == (1, 0) else npy_format.read_array_header_2_0
            shape, _, dtype = read(handle, max_header_size=NPY_MAX_HEADER)
        except Exception as error:  # noqa: BLE001 - numpy's header parser raises ValueError, SyntaxError, TokenError...
            raise StageError(f"{what} {path}: not a .npy array ({str(error)[:200]})") from error
        offset = handle.tell()
    if dtype.hasobject:
        raise StageError(f"{what} {path}: holds Python objects, not numbers")
    check_declared(path, what, math.prod(shape) * dtype.itemsize, size - offset,
                   f"a {dtype} array of shape {shape}")
    return tuple(shape), dtype, offset


def load_npy(path: Path, what: str) -> np.ndarray:
    """A .npy array, its header checked first (npy_header)."""
    npy_header(path, what)
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError) as error:
        raise StageError(f"{what} {path}: cannot read as a .npy array ({error})") from error
