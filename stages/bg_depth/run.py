"""Stage bg_depth: a depth map and camera intrinsics for one background photo.

Providers (config ``provider``):
- ``sidecar``: a depth file beside the photo (formats in stages/lib/depth/formats.py).
- ``model``:   the monocular depth model ``model`` (stages/lib/depth/models.py: a pinned Depth Anything V2 checkpoint
               fetched once into the Hugging Face cache, a save_pretrained folder, or an .onnx file), on the GPU
               when the engine gives one.
- ``auto``:    the sidecar when the photo has one, else the model (by default metric-indoor-small), else, with
               ``model=none``, no depth.

What each photo got is in depth.json (stages/records/depth.py): ``provider``, ``sidecar_format``, ``model`` (name,
repository and pinned revision, or path; what it outputs) and, for relative depth, ``recovery``.

Metric and relative depth. A metric sidecar or a metric model (``model_output`` metric_depth; by default what the
model's config says) gives metres, used as they are. Relative depth, a relative model's affine-invariant
disparity (d = a / z + b, unknown a > 0 and b) or a ``disparity`` sidecar (``<stem>.depth.disparity.npy``), is
turned into metres per photo by stages/lib/depth/recovery.py: the shift from the right angles of its planar surfaces,
the scale from two priors, a camera ``camera_height_m`` above the lowest horizontal surface and a median depth of
``median_depth_m``; pixels beyond
``max_depth_ratio`` times the median depth are dropped. Either way depth.json says ``metric``: true and compose
stands objects at their real size; ``recovery`` says where the shift and scale came from.

No depth (``auto`` without a sidecar and with ``model=none``) is a normal, cached result, not a failure: the
stage writes ``depth.json`` with ``"provider": "none"`` (and ``metric`` false, the intrinsics, the size)
and no ``depth.npy``. planes then writes ``"planes": []``, exactly as for a photo without horizontal
surfaces: compose's ``placement: plane`` leaves such a photo out while another photo has a plane, and
``placement: random`` uses it. An explicit ``sidecar`` or ``model`` provider that cannot deliver, and any
broken file, is a StageError; a hub model that is neither cached nor fetchable is one error before any stage
runs (stages/app/preflight.py). A sidecar whose median depth is implausible for its encoding is a warning
naming the encoding that fits (stages/lib/depth/formats.py, which also states the file-name rule).

A photo may be a frame slot of a background video (stages/bg_frames/run.py); a slot its video could not fill has no
image, and the stage raises EmptyInput with the reason bg_frames recorded: the node is empty, not failed, and the
photo is left out of the datasets.

Intrinsics, first that applies: config ``K``; a ``<image>.json`` with ``"K"`` (input ``intrinsics``
or beside the photo); EXIF FocalLengthIn35mmFilm (focal = f35 * image diagonal / 43.27 mm); the
paper's ``fov_deg`` = 55 degree horizontal field of view. The principal point is the image centre
(W/2, H/2) (camera conventions: stages/lib/geometry.py).

Photos: EXIF orientation is applied; grayscale, palette, RGBA (alpha dropped) and CMYK photos are
converted to RGB; 16-bit photos are scaled to 8 bit (value / 257) (``load_photo`` of stages/lib/imageio.py,
which every stage that must line up with depth.npy uses).
"""
from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING, Optional

import numpy as np

from stages.bg_depth.spec import BgDepthConfig
from stages.contract.errors import EmptyInput, StageError
from stages.lib.depth import onnx as depth_onnx
from stages.lib.depth import transformers as depth_transformers
from stages.lib.depth.formats import (RELATIVE_FORMATS, find_sidecar_files, implausible_depth, read_sidecar_depth,
                                      sidecar_format)
from stages.lib.depth.intrinsics import resolve_intrinsics
from stages.lib.depth.models import DEPTH_MODELS, ModelSource, ensure_hub_model, resolve_model
from stages.lib.depth.recovery import recover_metric_depth
from stages.lib.imageio import load_photo
from stages.records.bg_frames import BgFramesRecord
from stages.records.depth import DepthRecord

if TYPE_CHECKING:  # the engine's object; not part of the stage's cache key
    from stages.engine.context import Context

log = logging.getLogger(__name__)


def choose_provider(provider: str, has_sidecar: bool, model: str) -> str:
    """"sidecar" | "model" | "none" for the configured provider; StageError when it cannot be met."""
    if provider == "sidecar" and not has_sidecar:
        raise StageError("bg_depth: provider 'sidecar' but no depth file was given for this photo "
                         "(input 'depth', or <image>.depth.png beside it)")
    if provider == "model" and model == "none":
        raise StageError("bg_depth: provider 'model' needs bg_depth.model (one of "
                         f"{', '.join(DEPTH_MODELS)}, a saved DepthAnything folder or an .onnx file), not 'none'")
    if provider == "auto":
        return "sidecar" if has_sidecar else ("model" if model != "none" else "none")
    return provider


def model_source(model: str, given: Optional[Path]) -> tuple[ModelSource, Path]:
    """The model to run and the file or folder to load it from: the DAG's input `given` (a hub snapshot's
    config.json, or the user's folder or .onnx file; stages/depth_models.node_model), else `model` (bg_depth.model)
    resolved here, a hub model fetched into the cache once when missing."""
    if given is not None and model in DEPTH_MODELS:
        return resolve_model(model, Path.cwd()), Path(given).parent
    if given is not None:
        kind = "onnx" if Path(given).suffix.lower() == ".onnx" else "folder"
        return ModelSource(kind, str(given), Path(given)), Path(given)
    source = resolve_model(model, Path.cwd())
    if source.kind == "hub":
        return source, ensure_hub_model(source.name, source.hub)
    return source, source.path


def predict(source: ModelSource, location: Path, cfg: BgDepthConfig, photo: np.ndarray,
            device: str) -> tuple[np.ndarray, str]:
    """The model's map of photo uint8 [H, W, 3] and what it holds: (float32 [H, W], "metric_depth" | "disparity")."""
    if source.kind == "onnx":
        session = depth_onnx.load_depth_session(location, cfg.onnx_threads, device)
        output = "disparity" if cfg.model_output == "auto" else str(cfg.model_output)
        return depth_onnx.run_depth_model(session, photo, cfg.model_input_size, location), output
    output = depth_transformers.model_output_kind(location) if cfg.model_output == "auto" else str(cfg.model_output)
    model = depth_transformers.load_depth_model(str(location), device)
    return depth_transformers.run_depth_model(model, photo, cfg.model_input_size, device, str(location)), output


def metric_depth(values: np.ndarray, output: str, K: np.ndarray, cfg: BgDepthConfig,
                 rng: np.random.Generator) -> tuple[np.ndarray, Optional[dict]]:
    """(metres [H, W] float32, 0 = missing; the recovery record or None) of a model's map or a sidecar [H, W]:
    "metric_depth" is used as it is, "disparity" goes through stages/lib/depth/recovery.py."""
    if output == "metric_depth":
        return np.where(np.isfinite(values) & (values > 0), values, 0.0).astype(np.float32), None
    recovered = recover_metric_depth(values, K, cfg.camera_height_m, cfg.median_depth_m, cfg.max_depth_ratio,
                                     rng)
    return recovered.depth, recovered.record()


def model_label(model: Optional[dict]) -> Optional[str]:
    """A model as one string for the run summary: "<name> (<repo>@<revision>)" or its path; None without one."""
    if model is None:
        return None
    return f"{model['name']} ({model['repo']}@{model['revision']})" if model.get("repo") else str(model["path"])


def run(ctx: Context) -> dict:
    """Write depth.npy (float32 [H, W]) and depth.json for ctx.inputs["image"]."""
    cfg = ctx.typed(BgDepthConfig)
    started = time.perf_counter()
    image_path = Path(ctx.inputs["image"])
    empty = None if image_path.exists() else BgFramesRecord.empty_reason(image_path)
    if empty:  # a frame slot its video could not fill: nothing to compute, not a failure
        raise EmptyInput(empty)
    photo = load_photo(image_path, cfg.min_side_px)                 # [H, W, 3] uint8
    height, width = photo.shape[:2]
    beside = find_sidecar_files(image_path)
    depth_path = ctx.inputs.get("depth") or beside.get("depth")
    intrinsics_json = ctx.inputs.get("intrinsics") or beside.get("intrinsics")
    K, K_source = resolve_intrinsics(image_path, width, height, cfg.K, cfg.fov_deg, intrinsics_json)
    given_model = ctx.inputs.get("model")  # the DAG passes the model as an input (stages/depth_models.node_model)
    provider = choose_provider(cfg.provider, depth_path is not None, "local" if given_model else cfg.model)
    rng = np.random.default_rng(ctx.seed)

    depth, metric, fmt, model, recovery, warning = None, False, None, None, None, None
    if provider == "sidecar":
        fmt = sidecar_format(Path(depth_path), cfg.sidecar_format)
        values = read_sidecar_depth(Path(depth_path), fmt)          # [H, W] metres, or disparity (RELATIVE_FORMATS)
        if values.shape != (height, width):
            raise StageError(f"depth sidecar {depth_path}: size {values.shape[1]}x{values.shape[0]} "
                             f"does not match the photo {image_path} ({width}x{height})")
        relative = fmt in RELATIVE_FORMATS
        depth, recovery = metric_depth(values, "disparity" if relative else "metric_depth", K, cfg, rng)
        metric = True
        warning = None if relative else implausible_depth(Path(depth_path), fmt, depth)
    elif provider == "model":
        source, location = model_source(cfg.model, given_model)
        prediction, output = predict(source, location, cfg, photo, ctx.device)
        depth, recovery = metric_depth(prediction, output, K, cfg, rng)
        metric, model = True, {**source.describe(), "output": output}
    else:
        warning = (f"background image {image_path}: no depth sidecar and bg_depth.model=none, so no depth and no "
                   "placement plane: compose's placement 'plane' leaves it out while another photo has a plane "
                   "(placement 'random' uses it); add <stem>.depth.png beside it or set bg_depth.model")
    if warning:
        log.warning("%s", warning)

    DepthRecord(provider, metric, K, width, height, depth, fmt, model, recovery).write(ctx.out)
    valid = depth > 0 if depth is not None else np.zeros((height, width), bool)
    return {
        "provider": provider,
        "sidecar_format": fmt,
        "model": model_label(model),
        "recovery": recovery,
        "metric": metric,
        "K_source": K_source,
        "valid_fraction": float(valid.mean()),
        "median_depth": float(np.median(depth[valid])) if valid.any() else 0.0,
        "seconds": time.perf_counter() - started,
    }
