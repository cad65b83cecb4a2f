"""Readers for depth files that sit beside a photo ("sidecar" depth), returning metres (or, for the one relative
encoding, disparity).

Every reader returns float32 [H, W] with 0 = missing: metres, except ``disparity``. Encodings:

- ``png_mm``: 16-bit PNG, millimetres (the sample backgrounds, many RGB-D apps).
- ``npy_m``:  NumPy ``.npy`` array [H, W] (or [H, W, 1]) in metres.
- ``tum``:    TUM RGB-D benchmark 16-bit PNG, metres = value / 5000.
- ``nyu``:    NYU Depth v2 raw Kinect disparity in a 16-bit PGM, metres = 351.3 / (1092.5 - raw).
              The PGM header claims big-endian samples, but the NYU toolbox dumps (and Open3D's test
              copy) hold the bytes swapped; Open3D reads them big-endian and swaps again. Raw Kinect
              disparity has 11 bits (2047 = no reading), so the reader takes the byte order whose
              values fit in 11 bits.
- ``sun``:    SUN RGB-D 16-bit PNG with the bits rotated: d = (v >> 3) | (v << 13) (16-bit), then mm.
- ``disparity``: NumPy ``.npy`` [H, W] of relative, affine-invariant disparity (larger = nearer, unknown scale and
              shift), as a relative depth model gives it; bg_depth turns it into metres exactly as a relative
              model's output (stages/lib/depth/recovery.py). Only by name: ``<stem>.depth.disparity.npy``.

Which encoding a file has, first that applies: ``bg_depth.sidecar_format`` when not "auto"; the file-name
rule ``<photo stem>.depth.<format>.<ext>`` (e.g. ``office.depth.tum.png``); the extension: ``.npy`` is
npy_m, ``.pgm`` is nyu; a ``.png`` not named ``<stem>.depth...`` whose name holds the word tum, sun or nyu
(``TUM_depth.png``) is that dataset's; any other ``.png`` (``office.depth.png``) is png_mm.

A depth whose median lies outside PLAUSIBLE_MEDIAN_M (a photo to stand objects in) is flagged by
`implausible_depth`, with the encodings under which the same file would be plausible: TUM depth read as
millimetres is 5x too far.
"""
from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from stages.contract.errors import StageError
from stages.lib.file_checks import check_pixels, load_npy, npy_header, regular_file
from stages.lib.imageio import open_image

log = logging.getLogger(__name__)

SIDECAR_FORMATS = ("png_mm", "npy_m", "tum", "nyu", "sun", "disparity")
RELATIVE_FORMATS = ("disparity",)  # not metres: affine-invariant disparity

_NYU_INVALID_RAW = 2047          # Kinect v1 "no reading" disparity
_NYU_MAX_VALID_RAW = 1092        # 351.3 / (1092.5 - raw) must stay positive


SIDECAR_EXTENSIONS = {"png_mm": ".png", "npy_m": ".npy", "tum": ".png", "nyu": ".pgm", "sun": ".png",
                      "disparity": ".npy"}
PLAUSIBLE_MEDIAN_M = (0.3, 8.0)  # median depth (metres) of a photo to stand objects in
_SIDECAR_NAME = re.compile(rf"\.depth(\.(?P<format>{'|'.join(SIDECAR_FORMATS)}))?\.(png|npy|pgm)$", re.IGNORECASE)


_PAIR_DEPTH_NAME = re.compile(r"_depth\.(png|npy|pgm)$", re.IGNORECASE)
_PAIR_COLOUR_STEM = re.compile(r"_(color|colour|rgb)$", re.IGNORECASE)


def is_depth_sidecar(path: Path) -> bool:
    """Whether a file name is a depth sidecar's: <stem>.depth.<ext>, <stem>.depth.<format>.<ext>, or the
    depth half of an RGB-D pair, <name>_depth.<ext> (beside <name>_color.<ext>)."""
    name = Path(path).name
    return _SIDECAR_NAME.search(name) is not None or _PAIR_DEPTH_NAME.search(name) is not None


def sidecar_candidates(image_path: Path) -> list[Path]:
    """The depth sidecar names a photo may have beside it, in the order they are looked for: <stem>.depth.<ext>,
    <stem>.depth.<format>.<ext>, and for an RGB-D pair's colour half <name>_color (or _colour, _rgb),
    <name>_depth.<ext> (the layout of the TUM, NYU and SUN RGB-D samples)."""
    image_path = Path(image_path)
    names = [f"{image_path.stem}.depth{ext}" for ext in (".png", ".npy", ".pgm")]
    names += [f"{image_path.stem}.depth.{fmt}{ext}" for fmt, ext in SIDECAR_EXTENSIONS.items()]
    pair = _PAIR_COLOUR_STEM.sub("", image_path.stem)
    if pair != image_path.stem:
        names += [f"{pair}_depth{ext}" for ext in (".png", ".npy", ".pgm")]
    return [image_path.with_name(name) for name in names]


def find_sidecar_files(image_path: Path) -> dict[str, Path]:
    """Files beside a photo that bg_depth can use: {"depth": ..., "intrinsics": ...} when present.

    Depth: the first of sidecar_candidates (<stem>.depth.png | .npy | .pgm, then
    <stem>.depth.<format>.<ext>); intrinsics: <stem>.json. The DAG should pass them as inputs so that their
    contents enter the cache key.
    """
    image_path = Path(image_path)
    found: dict[str, Path] = {}
    depth = next((candidate for candidate in sidecar_candidates(image_path) if candidate.is_file()), None)
    if depth is not None:
        found["depth"] = depth
    intrinsics = image_path.with_suffix(".json")
    if intrinsics.is_file():
        found["intrinsics"] = intrinsics
    return found


def detect_sidecar_format(path: Path) -> str:
    """The encoding of a depth file from its name (the file-name rule of the module doc).

    Raises StageError for extensions other than .png, .npy and .pgm.
    """
    path = Path(path)
    name, suffix = path.name.lower(), path.suffix.lower()
    named = _SIDECAR_NAME.search(name)
    if named and named.group("format"):
        return named.group("format")
    if suffix == ".npy":
        return "npy_m"
    if suffix == ".pgm":
        return "nyu"
    if suffix == ".png":
        for dataset in ("tum", "sun", "nyu"):
            if not named and re.search(rf"(^|[^a-z]){dataset}([^a-z]|$)", name):
                return dataset
        return "png_mm"
    raise StageError(
        f"depth sidecar {path}: cannot tell its encoding from the extension {suffix!r}; "
        f"use .png (uint16 mm), .npy (metres) or .pgm (NYU), or set sidecar_format to one of "
        f"{SIDECAR_FORMATS}")


def sidecar_format(path: Path, fmt: str = "auto") -> str:
    """The encoding to read `path` with: `fmt`, or the file-name rule when "auto"; StageError for others."""
    if fmt == "auto":
        return detect_sidecar_format(path)
    if fmt not in SIDECAR_FORMATS:
        raise StageError(f"depth sidecar {path}: unknown sidecar_format {fmt!r}; "
                         f"expected 'auto' or one of {SIDECAR_FORMATS}")
    return fmt


def read_sidecar_depth(path: Path, fmt: str = "auto") -> np.ndarray:
    """Read a depth sidecar file as float32 metres [H, W] (0 = missing; disparity for RELATIVE_FORMATS).

    fmt: "auto" (see detect_sidecar_format) or one of SIDECAR_FORMATS.
    """
    path = Path(path)
    regular_file(path, "depth sidecar")
    fmt = sidecar_format(path, fmt)
    readers = {"png_mm": read_png_mm, "npy_m": read_npy_m, "tum": read_tum,
               "nyu": read_nyu, "sun": read_sun, "disparity": read_npy_m}
    depth = readers[fmt](path)                                   # [H, W] metres
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0).astype(np.float32)
    if not (depth > 0).any():
        raise StageError(f"depth sidecar {path}: no valid depth (all pixels zero or invalid "
                         f"after decoding as {fmt!r}); check the file and sidecar_format")
    log.debug("read %s as %s: %dx%d, %.1f%% valid", path, fmt, depth.shape[1], depth.shape[0],
              100.0 * (depth > 0).mean())
    return depth


def implausible_depth(path: Path, fmt: str, depth: np.ndarray) -> str | None:
    """None when `depth` ([H, W] metres, 0 = missing; `path` read as `fmt`) looks right; else a warning naming
    the encodings under which the file would: its median lies outside PLAUSIBLE_MEDIAN_M, or a 16-bit PNG
    bears SUN's bit rotation (see _png_encodings_that_fit) but is read otherwise."""
    low, high = PLAUSIBLE_MEDIAN_M
    median = float(np.median(depth[depth > 0]))
    fits = _png_encodings_that_fit(_read_uint16_png(path)) if fmt in _PNG_DECODERS else {}
    fits.pop(fmt, None)
    if low <= median <= high and "sun" not in fits:
        return None
    if low <= median <= high:
        message = (f"depth sidecar {path}: read as {fmt} (median depth {median:.2f} m), but its values bear the "
                   "bit rotation of SUN RGB-D depth (multiples of 8); ")
    else:
        message = (f"depth sidecar {path}: median depth {median:.2f} m when read as {fmt} is implausible for a "
                   f"photo to place objects in (expected {low:g} to {high:g} m); ")
    if not fits:
        return message + "no other encoding fits: check the file and bg_depth.sidecar_format"
    stem = path.name.split(".depth")[0] if ".depth" in path.name else path.stem
    first = next(iter(fits))
    return (message + ", ".join(f"as {other} it is {value:.2f} m" for other, value in fits.items())
            + f": set bg_depth.sidecar_format={first} or name the file {stem}.depth.{first}{SIDECAR_EXTENSIONS[first]}")


def _png_encodings_that_fit(raw: np.ndarray) -> dict[str, float]:
    """{encoding: median metres} of the 16-bit PNG encodings under which the values raw [H, W] have a plausible
    median, sun first: it is listed only when nine in ten values are multiples of 8 (its bit rotation leaves
    the low 3 bits zero below 8.19 m; the real SUN sample has 97 %, the TUM one 15 %)."""
    low, high = PLAUSIBLE_MEDIAN_M
    valid_raw = raw[raw > 0]
    fits = {}
    for fmt in ("sun", "png_mm", "tum"):
        if fmt == "sun" and (valid_raw.size == 0 or np.mean(valid_raw % 8 == 0) < 0.9):
            continue
        decoded = _PNG_DECODERS[fmt](raw)
        valid = decoded[decoded > 0]
        if valid.size and low <= float(np.median(valid)) <= high:
            fits[fmt] = float(np.median(valid))
    return fits


def _read_uint16_png(path: Path) -> np.ndarray:
    """Read a single-channel 16-bit PNG as uint16 [H, W]; StageError for anything else."""
    with open_image(path, "depth sidecar") as image:
        mode = image.mode
        try:
            values = np.array(image)
        except Exception as error:  # PIL raises many types for broken files
            raise StageError(f"depth sidecar {path}: cannot read as an image ({error})") from error
    if values.ndim != 2 or mode not in _UINT16_MODES:
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


_UINT16_MODES = ("I;16", "I;16B", "I;16L", "I")  # PIL modes of single-channel 16-bit PNGs
_PNG_DECODERS = {"png_mm": decode_mm, "tum": decode_tum, "sun": decode_sun}  # 16-bit PNG encodings


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
    """.npy [H, W] or [H, W, 1] (metres, or disparity) -> float32 [H, W] (NaN and infinity stay: no depth)."""
    sidecar_size(path, "npy_m")  # its header: an [H, W] array under the pixel limit, held in full by the file
    values = load_npy(path, "depth sidecar")
    if values.ndim == 3:
        values = values[:, :, 0]
    if not np.issubdtype(values.dtype, np.number) or np.iscomplexobj(values):
        raise StageError(f"depth sidecar {path}: expected a numeric [H, W] array, got dtype {values.dtype}")
    return values.astype(np.float32)


def _pgm_header(path: Path, data: bytes) -> tuple[int, int, int]:
    """(width, height, offset of the samples) of a 16-bit binary PGM whose bytes (or first bytes) are `data`;
    StageError unless the header says P5 and maxval > 255 and, when the whole file is given, it holds them."""
    header = re.match(rb"P5\s+(\d{1,9})\s+(\d{1,9})\s+(\d{1,9})\s", data)
    if header is None:
        raise StageError(f"depth sidecar {path}: not a binary PGM (P5) file")
    width, height, maxval = (int(group) for group in header.groups())
    check_pixels(path, "depth sidecar", width, height)
    size = path.stat().st_size - header.end()
    if not 256 <= maxval <= 65535 or size < width * height * 2:
        raise StageError(f"depth sidecar {path}: expected a 16-bit PGM of {width}x{height}, "
                         f"got maxval {maxval} and {size} data bytes")
    return width, height, header.end()


def sidecar_size(path: Path, fmt: str) -> tuple[int, int]:
    """(width, height) of a depth sidecar read as `fmt`, from its header only; StageError naming the file
    when it is missing, not of that kind (16-bit single-channel PNG, [H, W] .npy, 16-bit PGM) or broken."""
    path = Path(path)
    regular_file(path, "depth sidecar")
    if fmt == "nyu":
        with open(path, "rb") as handle:
            width, height, _ = _pgm_header(path, handle.read(64))
        return width, height
    if SIDECAR_EXTENSIONS[fmt] == ".npy":
        shape, _, _ = npy_header(path, "depth sidecar")
        if len(shape) not in (2, 3) or (len(shape) == 3 and shape[2] != 1):
            raise StageError(f"depth sidecar {path}: expected an [H, W] array, got shape {shape}")
        check_pixels(path, "depth sidecar", shape[1], shape[0])
        return shape[1], shape[0]
    with open_image(path, "depth sidecar") as image:
        mode, size = image.mode, image.size
    if mode not in _UINT16_MODES:
        raise StageError(f"depth sidecar {path}: expected a single-channel 16-bit PNG, got mode {mode!r}")
    return size


def read_nyu(path: Path) -> np.ndarray:
    """NYU raw-disparity PGM (P5, maxval 65535) -> metres [H, W]."""
    data = path.read_bytes()
    width, height, offset = _pgm_header(path, data)
    samples = np.frombuffer(data, dtype=">u2", count=width * height, offset=offset)
    raw = samples.reshape(height, width)
    swapped = raw.byteswap()
    if raw.max() > _NYU_INVALID_RAW and swapped.max() <= _NYU_INVALID_RAW:
        raw = swapped
    elif raw.max() > _NYU_INVALID_RAW:
        raise StageError(f"depth sidecar {path}: values do not look like 11-bit Kinect disparity "
                         f"in either byte order (max {raw.max()} / {swapped.max()})")
    return decode_nyu(raw)
