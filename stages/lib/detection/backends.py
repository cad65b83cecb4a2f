"""The two ways to run a detector on a photo, with the same outputs (inference.head_outputs' dict): PyTorch on the
run's device, and an exported ONNX graph in onnxruntime on the CPU. What follows (the paste, the mask refinement,
the thresholds) is stages/lib/detection/postprocess.py's, the same for both."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from stages.lib.detection.inference import OUTPUT_NAMES, head_outputs, image_tensor


class TorchDetector:
    """A trained MaskRCNN (eval mode) on `device`."""

    backend = "pytorch"

    def __init__(self, model: torch.nn.Module, device: str):
        self.model, self.device = model, device

    def outputs(self, image: np.ndarray) -> dict:
        """head_outputs on one RGB uint8 image [H, W, 3]: image [3, H, W], boxes [N, 4], labels [N], scores [N],
        mask_probs [N, 1, M, M], tensors on the device."""
        return head_outputs(self.model, image, self.device)


class OnnxDetector:
    """An ONNX file written by stages/lib/detection/onnx_export.py, run by onnxruntime on the CPU with `threads` threads
    (0: onnxruntime's default, all cores). ValueError naming the file when onnxruntime cannot load it."""

    backend = "onnxruntime"
    device = "cpu"

    def __init__(self, path: str | Path, threads: int = 0):
        import onnxruntime

        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
        # idle threads sleep instead of spinning, as torch's do (stages/__init__.py: a spinning team of 2 threads ran
        # many times slower with another process busy on a 2-core machine)
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        try:
            self.session = onnxruntime.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        except Exception as error:  # onnxruntime raises its own types (InvalidProtobuf, Fail, ...)
            raise ValueError(f"{path}: onnxruntime cannot load it as an ONNX model ({error})") from error
        names = [output.name for output in self.session.get_outputs()]
        if names != list(OUTPUT_NAMES):
            raise ValueError(f"{path}: an ONNX graph with outputs {names}, not a detector exported by this version "
                             f"(outputs {list(OUTPUT_NAMES)}); export it again")

    def metadata(self) -> dict[str, str]:
        """The file's metadata_props (string keys and values)."""
        return dict(self.session.get_modelmeta().custom_metadata_map)

    def outputs(self, image: np.ndarray) -> dict:
        """The graph's outputs on one RGB uint8 image [H, W, 3], as head_outputs gives them (CPU tensors)."""
        x = image_tensor(image)  # [3, H, W]
        found = self.session.run(list(OUTPUT_NAMES), {"image": x.numpy()})
        return {"image": x, **{name: torch.from_numpy(value) for name, value in zip(OUTPUT_NAMES, found)}}
