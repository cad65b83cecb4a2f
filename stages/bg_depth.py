"""Stage bg_depth: a depth map and camera intrinsics for one background photo.

Providers (config ``provider``):
- ``sidecar``: a depth file beside the photo (formats in stages/depth_formats.py), metric.
- ``onnx``:    a Depth Anything v1/v2 ONNX model from ``onnx_path`` (stages/depth_onnx.py).
- ``auto``:    sidecar when one is given, else onnx when ``onnx_path`` is set, else no depth.

No depth (``auto`` with neither available) is a normal, cached result, not a failure: the stage
writes ``depth.json`` with ``"provider": "none"`` (and ``metric`` false, the intrinsics, the size)
and no ``depth.npy``. planes then writes ``"planes": []``, exactly as for a photo without horizontal
surfaces: compose's ``placement: plane`` leaves such a photo out while another photo has a plane, and
``placement: random`` uses it. An explicit ``sidecar`` or ``onnx`` provider that cannot deliver, and any
broken file, is a StageError. A sidecar whose median depth is implausible for its encoding is a warning
naming the encoding that fits (stages/depth_formats.py, which also states the file-name rule).

Relative depth, honestly: Depth Anything's relative models output affine-invariant disparity
d = a / z + b with unknown a > 0 and b. We model inverse depth as ``disparity_scale * d +
disparity_shift``. With ``disparity_scale`` unset (default) the scale is chosen so that the median
disparity maps to 1, i.e. depth is in units of the median scene depth, the shift is
``disparity_shift`` in those units (default 0: assumes b = 0, which keeps planes planar only when
the model's shift is small), pixels further than ``max_relative_depth`` median depths are dropped,
and ``metric`` is false: compose must then size objects relative to the scene, not in metres. With
``disparity_scale`` set (a calibration the user vouches for) the result is metres and metric.
Metric models (``onnx_output: metric_depth``) give metres directly.

Intrinsics, first that applies: config ``K``; a ``<image>.json`` with ``"K"`` (input ``intrinsics``
or beside the photo); EXIF FocalLengthIn35mmFilm (focal = f35 * image diagonal / 43.27 mm); the
paper's ``fov_deg`` = 55 degree horizontal field of view. The principal point is the image centre
(W/2, H/2) (camera conventions: stages/geometry.py).

Photos: EXIF orientation is applied; grayscale, palette, RGBA (alpha dropped) and CMYK photos are
converted to RGB; 16-bit photos are scaled to 8 bit (value / 257) (``load_photo`` of stages/imageio.py,
which every stage that must line up with depth.npy uses).
"""
from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Optional

import numpy as np
from PIL import Image

from stages.depth_formats import (SIDECAR_FORMATS, implausible_depth, read_sidecar_depth, sidecar_candidates,
                                  sidecar_format)
from stages.depth_onnx import load_depth_session, run_depth_model
from stages.errors import StageError
from stages.geometry import DEFAULT_FOV_DEG, fov_intrinsics
from stages.imageio import load_photo
from stages.records.depth import DepthRecord

if TYPE_CHECKING:  # the engine's object; not part of the stage's cache key
    from stages.context import Context

log = logging.getLogger(__name__)

PROVIDERS = ("sidecar", "onnx", "auto")
ONNX_OUTPUTS = ("disparity", "metric_depth")
EXIF_IFD = 0x8769
EXIF_FOCAL_35MM = 0xA405
FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)


@dataclass
class BgDepthConfig:
    provider: str = "auto"                    # "sidecar" | "onnx" | "auto"
    sidecar_format: str = "auto"              # "auto" | "png_mm" | "npy_m" | "tum" | "nyu" | "sun"
    onnx_path: str = ""                       # Depth Anything .onnx on this machine; "" = none
    onnx_output: str = "disparity"            # "disparity" (relative models) | "metric_depth"
    onnx_input_size: int = 518                # shorter side fed to dynamic-size models (x14)
    onnx_threads: int = 1
    disparity_scale: Optional[float] = None   # inverse metres per disparity unit; None = relative
    disparity_shift: float = 0.0              # added to scaled disparity (1/m, or 1/median depth)
    max_relative_depth: float = 20.0          # relative mode: drop depth beyond this x median
    fov_deg: float = DEFAULT_FOV_DEG          # horizontal field of view when nothing else is known
    K: Optional[list] = None                  # 3x3 override for every photo
    min_side_px: int = 32                     # smaller photos are rejected


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
    except (TypeError, ValueError) as error:
        raise StageError(f"intrinsics from {source}: K is not numeric ({error})") from error
    if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise StageError(f"intrinsics from {source}: K must be a 3x3 matrix with positive focal "
                         f"lengths, got {value!r}")
    return K


def read_intrinsics_json(path: Path) -> np.ndarray:
    """K [3, 3] of a photo's intrinsics file ({"K": 3x3}); StageError naming the file when it is not that."""
    try:
        record = json.loads(Path(path).read_text())
    except (OSError, ValueError) as error:
        raise StageError(f"intrinsics file {path}: cannot read JSON ({error})") from error
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


def find_sidecar_files(image_path: Path) -> dict[str, Path]:
    """Files beside a photo that bg_depth can use: {"depth": ..., "intrinsics": ...} when present.

    Depth: the first of depth_formats.sidecar_candidates (<stem>.depth.png | .npy | .pgm, then
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


def choose_provider(provider: str, has_sidecar: bool, onnx_path: str) -> str:
    """"sidecar" | "onnx" | "none" for the configured provider; StageError when it cannot be met."""
    if provider not in PROVIDERS:
        raise StageError(f"bg_depth: unknown provider {provider!r}; expected one of {PROVIDERS}")
    if provider == "sidecar" and not has_sidecar:
        raise StageError("bg_depth: provider 'sidecar' but no depth file was given for this photo "
                         "(input 'depth', or <image>.depth.png beside it)")
    if provider == "onnx" and not onnx_path:
        raise StageError("bg_depth: provider 'onnx' needs onnx_path (a Depth Anything .onnx file)")
    if provider == "auto":
        return "sidecar" if has_sidecar else ("onnx" if onnx_path else "none")
    return provider


def depth_from_model_output(prediction: np.ndarray, output_kind: str = "disparity",
                            disparity_scale: Optional[float] = None, disparity_shift: float = 0.0,
                            max_relative_depth: float = 20.0) -> tuple[np.ndarray, bool]:
    """Model output [H, W] -> (depth [H, W] float32, 0 = missing; metric flag). See module doc."""
    if output_kind not in ONNX_OUTPUTS:
        raise StageError(f"bg_depth: unknown onnx_output {output_kind!r}; expected {ONNX_OUTPUTS}")
    if output_kind == "metric_depth":
        depth = np.where(prediction > 0, prediction, 0.0).astype(np.float32)
        return depth, True
    positive = prediction[prediction > 0]
    if positive.size == 0:
        raise StageError("bg_depth: the depth model returned no positive disparity")
    metric = disparity_scale is not None
    scale = disparity_scale if metric else 1.0 / float(np.median(positive))
    inverse_depth = scale * prediction.astype(np.float64) + disparity_shift     # [H, W]
    min_inverse = 0.0 if metric else 1.0 / max_relative_depth
    valid = (prediction > 0) & (inverse_depth > min_inverse)
    depth = np.where(valid, 1.0 / np.where(valid, inverse_depth, 1.0), 0.0).astype(np.float32)
    return depth, metric


def run(ctx: Context) -> dict:
    """Write depth.npy (float32 [H, W]) and depth.json for ctx.inputs["image"]."""
    cfg = BgDepthConfig(**ctx.params)
    started = time.perf_counter()
    if cfg.sidecar_format != "auto" and cfg.sidecar_format not in SIDECAR_FORMATS:
        raise StageError(f"bg_depth: unknown sidecar_format {cfg.sidecar_format!r}; expected "
                         f"'auto' or one of {SIDECAR_FORMATS}")
    image_path = Path(ctx.inputs["image"])
    photo = load_photo(image_path, cfg.min_side_px)                 # [H, W, 3] uint8
    height, width = photo.shape[:2]
    beside = find_sidecar_files(image_path)
    depth_path = ctx.inputs.get("depth") or beside.get("depth")
    intrinsics_json = ctx.inputs.get("intrinsics") or beside.get("intrinsics")
    K, K_source = resolve_intrinsics(image_path, width, height, cfg.K, cfg.fov_deg, intrinsics_json)
    onnx_path = str(ctx.inputs.get("onnx_model") or cfg.onnx_path)  # the DAG passes the model as an input
    provider = choose_provider(cfg.provider, depth_path is not None, onnx_path)

    depth, metric, fmt, warning = None, False, None, None
    if provider == "sidecar":
        fmt = sidecar_format(Path(depth_path), cfg.sidecar_format)
        depth = read_sidecar_depth(Path(depth_path), fmt)
        metric = True
        warning = implausible_depth(Path(depth_path), fmt, depth)
        if depth.shape != (height, width):
            raise StageError(f"depth sidecar {depth_path}: size {depth.shape[1]}x{depth.shape[0]} "
                             f"does not match the photo {image_path} ({width}x{height})")
    elif provider == "onnx":
        session = load_depth_session(Path(onnx_path), cfg.onnx_threads, ctx.device)
        prediction = run_depth_model(session, photo, cfg.onnx_input_size, onnx_path)
        depth, metric = depth_from_model_output(prediction, cfg.onnx_output, cfg.disparity_scale,
                                                cfg.disparity_shift, cfg.max_relative_depth)
    else:
        warning = (f"background image {image_path}: no depth sidecar and no onnx_path, so no depth and no "
                   "placement plane: compose's placement 'plane' leaves it out while another photo has a plane "
                   "(placement 'random' uses it); add <stem>.depth.png beside it or set bg_depth.onnx_path")
    if warning:
        log.warning("%s", warning)

    DepthRecord(provider, metric, K, width, height, depth).write(ctx.out)
    valid = depth > 0 if depth is not None else np.zeros((height, width), bool)
    return {
        "provider": provider,
        "sidecar_format": fmt,
        "metric": metric,
        "K_source": K_source,
        "valid_fraction": float(valid.mean()),
        "median_depth": float(np.median(depth[valid])) if valid.any() else 0.0,
        "seconds": time.perf_counter() - started,
    }
