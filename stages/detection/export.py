"""ONNX export of a trained Mask R-CNN (batch 1) and a check of the exported graph in onnxruntime."""
from __future__ import annotations

import time
import warnings
from pathlib import Path

import numpy as np
import torch

OUTPUT_NAMES = ["boxes", "labels", "scores", "masks"]


def export_onnx(model: torch.nn.Module, path: str | Path, example: torch.Tensor) -> None:
    """Write the detector as ONNX (TorchScript exporter, opset 17): input "image" [3, H, W] in [0, 1],
    outputs boxes [N, 4], labels [N], scores [N], masks [N, 1, H, W]; H and W are dynamic."""
    model = model.cpu().eval()
    with warnings.catch_warnings():  # tracer warnings about data-dependent shapes are expected here
        warnings.simplefilter("ignore")
        torch.onnx.export(model, ([example],), str(path), dynamo=False, opset_version=17, input_names=["image"],
                          output_names=OUTPUT_NAMES, dynamic_axes={"image": [1, 2]})


def check_onnx(model: torch.nn.Module, path: str | Path, image: torch.Tensor) -> dict:
    """Run the ONNX file in onnxruntime on image [3, H, W] and compare with the PyTorch model.

    Returns detections in each, the largest box difference in pixels (None when the counts differ)
    and onnxruntime seconds for the image.
    """
    import onnxruntime

    session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    started = time.perf_counter()
    boxes = session.run(["boxes"], {"image": image.numpy()})[0]  # [N, 4]
    seconds = time.perf_counter() - started
    with torch.no_grad():
        reference = model.cpu().eval()([image])[0]["boxes"].numpy()  # [M, 4]
    same = boxes.shape == reference.shape
    return {"onnx_detections": int(boxes.shape[0]), "torch_detections": int(reference.shape[0]),
            "max_box_difference_px": float(np.abs(boxes - reference).max(initial=0.0)) if same else None,
            "onnxruntime_seconds": seconds}
