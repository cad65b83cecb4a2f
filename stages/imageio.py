"""Reading photos and frames: the image file types the project accepts and the two readers.

`load_photo` is the background-photo loader (PIL, EXIF orientation applied): every stage that must line
up with a background's depth map reads the photo with it. `read_rgb` reads a frame written by the
pipeline itself (OpenCV, no EXIF handling).
"""
from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
from PIL import Image, ImageOps

from stages.errors import StageError

log = logging.getLogger(__name__)

# Suffixes of image files in a folder of frames or of background photos (PIL and OpenCV read them all).
IMAGE_SUFFIXES = (".bmp", ".jpeg", ".jpg", ".png", ".ppm", ".tif", ".tiff", ".webp")


def list_images(folder: Path) -> list[Path]:
    """Image files (IMAGE_SUFFIXES, any case) directly in `folder`, sorted by name."""
    return sorted(p for p in Path(folder).iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def load_photo(path: Path, min_side_px: int = 32) -> np.ndarray:
    """Read a background photo as uint8 RGB [H, W, 3] (EXIF orientation applied).

    Grayscale/palette/RGBA/CMYK are converted to RGB, 16-bit and 32-bit integer photos scaled
    by 1/257. Raises StageError naming the file when unreadable or smaller than min_side_px.
    """
    path = Path(path)
    try:
        with Image.open(path) as image:
            image.load()
            image = ImageOps.exif_transpose(image)
    except Exception as error:  # PIL raises many types for broken files
        raise StageError(f"background image {path}: cannot read it as an image ({error})") from error
    if image.mode in ("I;16", "I;16B", "I;16L", "I", "F"):
        values = np.asarray(image, dtype=np.float64)
        if image.mode == "F" and values.max() <= 1.0:
            values = values * 255.0
        elif image.mode != "F":
            values = values / 257.0
        gray = np.clip(np.rint(values), 0, 255).astype(np.uint8)
        rgb = np.repeat(gray[:, :, None], 3, axis=2)
        log.info("background image %s: %s photo converted to 8-bit RGB", path, image.mode)
    else:
        if image.mode != "RGB":
            log.info("background image %s: %s photo converted to RGB", path, image.mode)
        rgb = np.asarray(image.convert("RGB"), dtype=np.uint8)
    height, width = rgb.shape[:2]
    if min(height, width) < min_side_px:
        raise StageError(f"background image {path}: {width}x{height} is too small "
                         f"(need at least {min_side_px} px on each side)")
    return np.ascontiguousarray(rgb)


def read_rgb(path: Path) -> np.ndarray:
    """An image file as RGB uint8 [H, W, 3]; StageError naming the file when unreadable."""
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise StageError(f"cannot read image {path}: missing or not an image file")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
