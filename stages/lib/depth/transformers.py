"""Monocular depth with a Depth Anything model of `transformers` (DepthAnythingForDepthEstimation) from a folder.

The folder is a save_pretrained layout: config.json (a DepthAnythingConfig with its Dinov2 backbone) and
model.safetensors; a published checkpoint is the snapshot folder of the Hugging Face cache that
stages/lib/depth/models.py fetched, a user's own model any such folder. Both load through `load_depth_model`, offline
(nothing is fetched here). The input is prepared as for the ONNX models (stages/lib/depth/onnx.py: ImageNet
normalisation, the lower-bound resize to multiples of 14, which is also what the checkpoints' image processors
do) and the output is resized back to the photo. The model runs on `device` ("cuda" when the engine gives a GPU).

What comes out is the config's `depth_estimation_type`: "metric" models give metres ("metric_depth"), "relative"
ones affine-invariant disparity ("disparity"). transformers and torch are imported when a model is loaded, never
when this module is.
"""
from __future__ import annotations

import json
import logging
from functools import lru_cache
from pathlib import Path

import numpy as np

from stages.contract.errors import StageError
from stages.lib.depth.onnx import lower_bound_size, output_to_photo, preprocess

log = logging.getLogger(__name__)

OUTPUTS = {"metric": "metric_depth", "relative": "disparity"}  # depth_estimation_type -> what the map holds


def model_output_kind(folder: Path) -> str:
    """"metric_depth" or "disparity" from the folder's config.json; StageError naming it when it is not a
    DepthAnything config."""
    path = Path(folder) / "config.json"
    try:
        config = json.loads(path.read_text())
    except (OSError, ValueError) as error:
        raise StageError(f"depth model {path}: cannot read ({error})") from error
    if config.get("model_type") != "depth_anything":
        raise StageError(f"depth model {path}: model_type {config.get('model_type')!r}, expected 'depth_anything' "
                         "(a DepthAnythingForDepthEstimation saved with save_pretrained)")
    kind = config.get("depth_estimation_type", "relative")
    if kind not in OUTPUTS:
        raise StageError(f"depth model {path}: depth_estimation_type {kind!r}, expected one of {list(OUTPUTS)}")
    return OUTPUTS[kind]


@lru_cache(maxsize=1)
def load_depth_model(folder: str, device: str = "cpu"):
    """The DepthAnythingForDepthEstimation of a save_pretrained folder, in eval mode on `device` (kept for the next
    photo of this process). StageError naming the folder when transformers cannot load it."""
    model_output_kind(Path(folder))
    from transformers import DepthAnythingForDepthEstimation
    from transformers.utils import logging as transformers_logging

    transformers_logging.disable_progress_bar()  # one bar per photo would fill the logs

    try:
        model = DepthAnythingForDepthEstimation.from_pretrained(folder, local_files_only=True)
    except (OSError, ValueError, RuntimeError) as error:
        raise StageError(f"depth model {folder}: transformers cannot load it ({error})") from error
    log.info("depth model %s loaded on %s (%.1f M parameters)", folder, device,
             sum(p.numel() for p in model.parameters()) / 1e6)
    return model.eval().to(device)


def run_depth_model(model, photo: np.ndarray, input_size: int = 518, device: str = "cpu",
                    name: str = "model") -> np.ndarray:
    """The model's map for photo uint8 RGB [H, W, 3]: float32 [H, W] (metres or disparity, see model_output_kind)."""
    import torch

    height, width = photo.shape[:2]
    in_h, in_w = lower_bound_size(height, width, input_size)
    batch = torch.from_numpy(preprocess(photo, in_h, in_w)).to(device)      # [1, 3, in_h, in_w]
    with torch.inference_mode():
        output = model(pixel_values=batch).predicted_depth                 # [1, in_h, in_w]
    return output_to_photo(output.float().cpu().numpy(), height, width, name)
