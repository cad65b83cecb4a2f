"""A photo's intrinsics K [3, 3] (pixels, OpenCV camera): given in the config, in an intrinsics file
({"K": 3x3}), from EXIF FocalLengthIn35mmFilm, or from a field of view; checked before use."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import numpy as np
from PIL import Image

from stages.contract.errors import StageError
from stages.lib.file_checks import load_json
from stages.lib.geometry import DEFAULT_FOV_DEG, fov_intrinsics

EXIF_IFD = 0x8769
EXIF_FOCAL_35MM = 0xA405
FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)


def exif_focal_px(path: Path, width: int, height: int) -> Optional[float]:
    """Focal length in pixels from EXIF FocalLengthIn35mmFilm, or None when absent."""
    try:
        with Image.open(path) as image:
            focal_35mm = image.getexif().get_ifd(EXIF_IFD).get(EXIF_FOCAL_35MM)
    except Exception:  # unreadable EXIF is simply absent EXIF
        return None
    if not focal_35mm or float(focal_35mm) <= 0:
        return None
    return float(focal_35mm) * math.hypot(width, height) / FULL_FRAME_DIAGONAL_MM


def parse_K(value, source: str) -> np.ndarray:
    """Validate a 3x3 intrinsics matrix (nested lists) -> float64 [3, 3]."""
    try:
        K = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as error:
        raise StageError(f"intrinsics from {source}: K is not numeric ({str(error)[:200]})") from error
    if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise StageError(f"intrinsics from {source}: K must be a 3x3 matrix of finite numbers with positive focal "
                         f"lengths, got {value!r:.200}")
    return K


def read_intrinsics_json(path: Path) -> np.ndarray:
    """K [3, 3] of a photo's intrinsics file ({"K": 3x3}); StageError naming the file when it is not that."""
    record = load_json(path, "intrinsics file")
    if not isinstance(record, dict) or "K" not in record:
        raise StageError(f"intrinsics file {path}: expected an object with key 'K'")
    return parse_K(record["K"], str(path))


def resolve_intrinsics(image_path: Path, width: int, height: int, config_K=None,
                       fov_deg: float = DEFAULT_FOV_DEG, intrinsics_json: Optional[Path] = None
                       ) -> tuple[np.ndarray, str]:
    """K [3, 3] and where it came from: "config" | "json" | "exif" | "fov" (see module doc)."""
    if config_K is not None:
        return parse_K(config_K, "config K"), "config"
    if intrinsics_json is not None:
        return read_intrinsics_json(Path(intrinsics_json)), "json"
    focal = exif_focal_px(image_path, width, height)
    if focal is not None:
        K = fov_intrinsics(width, height, fov_deg)
        K[0, 0] = K[1, 1] = focal
        return K, "exif"
    return fov_intrinsics(width, height, fov_deg), "fov"
