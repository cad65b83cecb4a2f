"""The eval stage's spec: how a trained detector (`model`, a train_maskrcnn folder) is scored on a COCO test set
(`testset`)."""
from __future__ import annotations

from dataclasses import dataclass

from stages.inputs import Input, Inputs

INPUTS = Inputs((Input("model"), Input("testset", raw="testset")))


@dataclass
class EvalConfig:
    """max_images: evaluate only the first N test images (0 = all). draw_*: the predictions.png grid.
    onnx: also export the detector to model.onnx (batch 1) and check it on the first test image in
    onnxruntime (adds ~30 s on this machine).
    """

    max_images: int = 0
    mask_threshold: float = 0.5
    draw_images: int = 8
    draw_score_threshold: float = 0.5
    threads: int = 0
    onnx: bool = False
