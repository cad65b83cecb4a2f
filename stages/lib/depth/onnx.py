"""Monocular depth with a Depth Anything (v1 or v2) ONNX model run by onnxruntime, and the input both model
runners share (stages/lib/depth/transformers.py runs the same preprocessing).

The model file comes from a path the user gives (`bg_depth.model=/path/model.onnx`); nothing is downloaded.
Works with the common exports (e.g. fabio-sim/Depth-Anything-ONNX, the v2 metric exports): one image input
[1, 3, h, w] float32, RGB scaled to [0, 1] and ImageNet-normalised; one output [1, h, w] or
[1, 1, h, w]. Static input sizes are used as they are; dynamic ones get the Depth Anything
"lower bound" resize (shorter side = input_size, both sides multiples of 14, aspect kept).
The output is resized back to the photo's size with bilinear interpolation.

What the output means is the caller's business (see stages/bg_depth/run.py): relative models give
affine-invariant disparity, metric models give metres.
"""
from __future__ import annotations

import logging
import math
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

from stages.contract.errors import StageError

log = logging.getLogger(__name__)

IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)
PATCH = 14   # ViT patch size of Depth Anything: input sides must be multiples of it


@lru_cache(maxsize=1)  # kept for the next photo of this process, as depth_transformers' model
def load_depth_session(model_path: Path, threads: int = 1, device: str = "cpu"):
    """Open an onnxruntime session for a depth model and check its input looks like an image.

    Returns an onnxruntime.InferenceSession. Raises StageError naming the file otherwise.
    """
    import onnxruntime as ort

    model_path = Path(model_path)
    if not model_path.is_file():
        raise StageError(f"depth model {model_path}: file not found (set bg_depth.model to a Depth "
                         f"Anything .onnx file on this machine)")
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    providers = ["CPUExecutionProvider"]
    if device == "cuda" and "CUDAExecutionProvider" in ort.get_available_providers():
        providers.insert(0, "CUDAExecutionProvider")
    try:
        session = ort.InferenceSession(str(model_path), sess_options=options, providers=providers)
    except Exception as error:  # onnxruntime raises its own exception types
        raise StageError(f"depth model {model_path}: onnxruntime cannot load it ({error})") from error
    inputs = session.get_inputs()
    shape = inputs[0].shape if inputs else []
    wrong_channels = len(shape) == 4 and isinstance(shape[1], int) and shape[1] != 3
    if len(inputs) != 1 or len(shape) != 4 or wrong_channels:
        raise StageError(f"depth model {model_path}: not a depth model: expected one image input "
                         f"[1, 3, H, W], got {[(i.name, i.shape) for i in inputs]}")
    return session


def model_input_size(session, image_height: int, image_width: int, input_size: int) -> tuple[int, int]:
    """(height, width) to feed: the model's static size, or the Depth Anything lower-bound resize."""
    _, _, static_h, static_w = session.get_inputs()[0].shape
    if isinstance(static_h, int) and isinstance(static_w, int):
        return static_h, static_w
    return lower_bound_size(image_height, image_width, input_size)


def lower_bound_size(image_height: int, image_width: int, input_size: int) -> tuple[int, int]:
    """(height, width) of Depth Anything's "lower bound" resize: shorter side input_size, sides multiples of 14."""
    scale = input_size / min(image_height, image_width)
    return (_multiple_of_patch(image_height * scale, input_size),
            _multiple_of_patch(image_width * scale, input_size))


def _multiple_of_patch(value: float, minimum: int) -> int:
    """Round to a multiple of PATCH, rounding up when rounding would go below minimum."""
    rounded = int(round(value / PATCH) * PATCH)
    if rounded < minimum:
        rounded = int(math.ceil(value / PATCH) * PATCH)
    return max(rounded, PATCH)


def preprocess(photo: np.ndarray, height: int, width: int) -> np.ndarray:
    """uint8 RGB [H, W, 3] -> float32 [1, 3, height, width], ImageNet-normalised."""
    scaled = photo.astype(np.float32) / 255.0
    resized = cv2.resize(scaled, (width, height), interpolation=cv2.INTER_CUBIC)   # [h, w, 3]
    normalised = (resized - IMAGENET_MEAN) / IMAGENET_STD
    return np.ascontiguousarray(normalised.transpose(2, 0, 1)[None])


def run_depth_model(session, photo: np.ndarray, input_size: int = 518,
                    model_path: Path | str = "model") -> np.ndarray:
    """Run the depth model on a photo and resize its output back.

    photo: uint8 RGB [H, W, 3]. Returns the raw model output as float32 [H, W] (disparity or
    metres, whatever the model gives). Raises StageError when the output is not one map.
    """
    height, width = photo.shape[:2]
    in_h, in_w = model_input_size(session, height, width, input_size)
    batch = preprocess(photo, in_h, in_w)                           # [1, 3, in_h, in_w]
    try:
        outputs = session.run(None, {session.get_inputs()[0].name: batch})
    except Exception as error:
        raise StageError(f"depth model {model_path}: inference failed on a {in_w}x{in_h} input "
                         f"({error})") from error
    log.debug("depth model %s: input %dx%d", model_path, in_w, in_h)
    return output_to_photo(np.asarray(outputs[0]), height, width, model_path)


def output_to_photo(output: np.ndarray, height: int, width: int, model_path: Path | str = "model") -> np.ndarray:
    """A depth model's output [1, h, w] or [1, 1, h, w] -> float32 [height, width] (bilinear). StageError naming the
    model when it is not one finite map."""
    prediction = output
    if prediction.ndim == 4 and prediction.shape[:2] == (1, 1):
        prediction = prediction[0, 0]
    elif prediction.ndim == 3 and prediction.shape[0] == 1:
        prediction = prediction[0]
    if prediction.ndim != 2 or min(prediction.shape) < 2:
        raise StageError(f"depth model {model_path}: not a depth model: its first output has shape "
                         f"{list(output.shape)}, expected [1, H, W] or [1, 1, H, W]")
    if not np.isfinite(prediction).all():
        raise StageError(f"depth model {model_path}: output contains NaN or infinite values")
    return cv2.resize(prediction.astype(np.float32), (width, height), interpolation=cv2.INTER_LINEAR)
