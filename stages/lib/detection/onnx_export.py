"""ONNX export of a trained Mask R-CNN (batch 1, any image size) and a check of the exported graph in onnxruntime.

The graph is inference.HeadOutputs: the detector up to its mask head, without the paste of the masks into the image,
which runs outside it with the rest of the post-processing (stages/lib/detection/postprocess.py), shared by both
backends (stages/lib/detection/backends.py). It is traced on one example photo; every size the graph computes follows
the input's (EfficientNet-Lite's "SAME" padding too, TraceableConv2dSame), so it gives PyTorch's detections on photos
of any size and shape.
"""
from __future__ import annotations

import copy
import time
import warnings
from pathlib import Path

import numpy as np
import onnx
import torch
import torch.nn.functional as F

from stages.lib.detection.backends import OnnxDetector, TorchDetector
from stages.lib.detection.efficientnet_lite import Conv2dSame
from stages.lib.detection.inference import OUTPUT_NAMES, HeadOutputs, image_tensor
from stages.lib.detection.postprocess import PostProcessing, postprocess


class TraceableConv2dSame(Conv2dSame):
    """Conv2dSame whose padding a trace keeps as a function of the input's size. Conv2dSame's math.ceil turns the
    size into a Python number, so a traced graph padded every input as the example photo's size needs, and other
    sizes gave feature maps of the wrong size (and no detections). The same padding, in integer arithmetic."""

    def convolve(self, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None = None) -> torch.Tensor:
        """The "SAME" convolution of x [B, C, H, W] (Conv2dSame.convolve's, as traceable operations)."""
        stride, kernel = self.stride[0], self.kernel_size[0]
        if stride == 1:
            return super().convolve(x, weight, bias)
        pads = []
        for size in (x.shape[-1], x.shape[-2]):  # F.pad order: last dim first; kernel >= stride: never negative
            total = ((size + stride - 1) // stride - 1) * stride + kernel - size
            pads += [total // 2, total - total // 2]
        return F.conv2d(F.pad(x, pads), weight, bias, self.stride, 0, 1, self.groups)


def traceable(model: torch.nn.Module) -> torch.nn.Module:
    """A copy of the detector (CPU, eval mode) whose Conv2dSame layers are TraceableConv2dSame (the same results)."""
    model = copy.deepcopy(model).cpu().eval()
    for module in model.modules():
        if type(module) is Conv2dSame:
            if module.kernel_size[0] < module.stride[0]:
                raise ValueError(f"cannot export a {module.kernel_size[0]}-pixel convolution of stride "
                                 f"{module.stride[0]} with traceable padding")
            module.__class__ = TraceableConv2dSame
    return model


def export_onnx(model: torch.nn.Module, path: str | Path, example: np.ndarray, metadata: dict[str, str]) -> None:
    """Write the detector as ONNX (TorchScript exporter, opset 17), traced on `example` (RGB uint8 [H, W, 3]):
    input "image" [3, H, W] float32 in [0, 1] (RGB), H and W dynamic; outputs boxes [N, 4] (x0 y0 x1 y1 in the
    image's pixels), labels [N] int64 (1..K), scores [N], mask_probs [N, 1, M, M] (not pasted). `metadata` (string
    keys and values) goes into the file's metadata_props."""
    head = HeadOutputs(traceable(model))
    with warnings.catch_warnings():  # tracer warnings about data-dependent shapes are expected here
        warnings.simplefilter("ignore")
        torch.onnx.export(head, (image_tensor(example),), str(path), dynamo=False, opset_version=17,
                          input_names=["image"], output_names=list(OUTPUT_NAMES),
                          dynamic_axes={"image": [1, 2], **{name: [0] for name in OUTPUT_NAMES}})
    graph = onnx.load(str(path))
    for key, value in metadata.items():
        graph.metadata_props.add(key=key, value=value)
    onnx.save(graph, str(path))


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two [H, W] bool masks (1 when both are empty)."""
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0


def compare_detections(reference: dict, other: dict) -> dict:
    """How far `other`'s detections are from `reference`'s (postprocess outputs, in score order): their counts,
    whether the labels agree one by one, and when the counts agree the largest box difference in pixels and the
    smallest mask IoU (None otherwise)."""
    same = len(reference["scores"]) == len(other["scores"])
    box_difference = np.abs(reference["boxes"] - other["boxes"]).max(initial=0.0) if same else None
    return {"reference_detections": len(reference["scores"]), "detections": len(other["scores"]),
            "same_labels": same and bool(np.array_equal(reference["labels"], other["labels"])),
            "max_box_difference_px": None if box_difference is None else float(box_difference),
            "min_mask_iou": min((mask_iou(a, b) for a, b in zip(reference["masks"], other["masks"])), default=1.0)
            if same else None}


def check_onnx(model: torch.nn.Module, path: str | Path, image: np.ndarray, post: PostProcessing,
               detector_size: int) -> dict:
    """Detections of the ONNX file in onnxruntime (CPU, one thread) against the PyTorch model's (on the CPU) on one
    RGB uint8 image [H, W, 3], both post-processed with `post`: compare_detections, and onnxruntime's seconds."""
    reference = postprocess(TorchDetector(model.cpu().eval(), "cpu").outputs(image), post, detector_size)
    detector = OnnxDetector(path, threads=1)
    started = time.perf_counter()
    outputs = detector.outputs(image)
    seconds = time.perf_counter() - started
    return {**compare_detections(reference, postprocess(outputs, post, detector_size)), "onnxruntime_seconds": seconds}
