"""Reading photos and frames: the image file types the project accepts and the two readers.

`load_photo` is the background-photo loader (PIL, EXIF orientation applied): every stage that must line
up with a background's depth map reads the photo with it. `read_rgb` reads a frame written by the
pipeline itself (OpenCV, no EXIF handling). `open_image` opens a user's image lazily (its header only) and refuses
one above the pixel limit (stages/lib/file_checks.py: `run.max_image_pixels`) before anything is decoded.
"""
from __future__ import annotations

import logging
import struct
from pathlib import Path

import numpy as np
from PIL import Image, ImageOps

from stages.contract.errors import StageError
from stages.lib.file_checks import check_pixels, regular_file

log = logging.getLogger(__name__)

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# Suffixes of image files in a folder of frames or of background photos (PIL and OpenCV read them all).
IMAGE_SUFFIXES = (".bmp", ".jpeg", ".jpg", ".png", ".ppm", ".tif", ".tiff", ".webp")


def list_images(folder: Path) -> list[Path]:
    """Image files (IMAGE_SUFFIXES, any case) directly in `folder`, sorted by name."""
    return sorted(p for p in Path(folder).iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def check_png_chunks(path: Path, what: str) -> None:
    """StageError unless every chunk of a PNG file fits in the file (OpenCV's reader allocates what a chunk's
    length declares, up to 2 GB, before it reads it). Files that are not PNG pass."""
    size = Path(path).stat().st_size
    with open(path, "rb") as handle:
        if handle.read(8) != PNG_SIGNATURE:
            return
        while header := handle.read(8):
            length, kind = (struct.unpack(">I", header[:4])[0], header[4:]) if len(header) == 8 else (size, b"?")
            if handle.tell() + length + 4 > size:
                raise StageError(f"{what} {path}: its PNG chunk {kind!r} declares {length} bytes, more than the file "
                                 "holds; it is truncated or corrupt")
            if kind == b"IEND":
                return
            handle.seek(length + 4, 1)  # the data and the CRC


def open_image(path: Path, what: str) -> Image.Image:
    """A user's image file opened by PIL, its header read but nothing decoded; StageError naming it (as `what`,
    e.g. "background image") when it is not a readable file, not an image, a PNG whose chunks do not fit in it, or
    above the pixel limit (which stands in for PIL's own decompression-bomb limit while the header is read)."""
    path = Path(path)
    regular_file(path, what)
    check_png_chunks(path, what)
    bomb_limit, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None
    try:
        image = Image.open(path)
    except Exception as error:  # PIL raises many types for broken files
        raise StageError(f"{what} {path}: cannot read it as an image ({error})") from error
    finally:
        Image.MAX_IMAGE_PIXELS = bomb_limit
    try:
        check_pixels(path, what, *image.size)
    except StageError:
        image.close()
        raise
    return image


def image_size(path: Path, what: str) -> tuple[int, int]:
    """(width, height) of a user's image from its header (open_image's checks)."""
    with open_image(path, what) as image:
        return image.size


def load_photo(path: Path, min_side_px: int = 32) -> np.ndarray:
    """Read a background photo as uint8 RGB [H, W, 3] (EXIF orientation applied).

    Grayscale/palette/RGBA/CMYK are converted to RGB, 16-bit and 32-bit integer photos scaled
    by 1/257. Raises StageError naming the file when unreadable, above the pixel limit (open_image) or
    smaller than min_side_px.
    """
    path = Path(path)
    with open_image(path, "background image") as image:
        try:
            image.load()
            ImageOps.exif_transpose(image, in_place=True)
            rgb = _rgb(path, image)
        except Exception as error:  # PIL raises many types for broken files
            raise StageError(f"background image {path}: cannot read it as an image ({error})") from error
    height, width = rgb.shape[:2]
    if min(height, width) < min_side_px:
        raise StageError(f"background image {path}: {width}x{height} is too small "
                         f"(need at least {min_side_px} px on each side)")
    return np.ascontiguousarray(rgb)


def _rgb(path: Path, image: Image.Image) -> np.ndarray:
    """A decoded photo as uint8 RGB [H, W, 3]: 16-bit and 32-bit integer photos scaled by 1/257, float ones from
    [0, 1] or [0, 255] (NaN as 0), other modes converted by PIL."""
    if image.mode in ("I;16", "I;16B", "I;16L", "I", "F"):
        values = np.nan_to_num(np.asarray(image, dtype=np.float64))
        if image.mode == "F" and values.max() <= 1.0:
            values = values * 255.0
        elif image.mode != "F":
            values = values / 257.0
        gray = np.clip(np.rint(values), 0, 255).astype(np.uint8)
        log.info("background image %s: %s photo converted to 8-bit RGB", path, image.mode)
        return np.repeat(gray[:, :, None], 3, axis=2)
    if image.mode == "RGB":
        return np.asarray(image, dtype=np.uint8)
    log.info("background image %s: %s photo converted to RGB", path, image.mode)
    return np.asarray(image.convert("RGB"), dtype=np.uint8)


def read_rgb(path: Path) -> np.ndarray:
    """An image file as RGB uint8 [H, W, 3]; StageError naming the file when unreadable."""
    import cv2  # here, so that the specs naming image and depth files load without OpenCV

    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise StageError(f"cannot read image {path}: missing or not an image file")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
