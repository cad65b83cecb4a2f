"""The eval stage's spec: how a trained detector (`model`, a train_maskrcnn folder) is scored on a COCO test set
(`testset`)."""
from __future__ import annotations

from dataclasses import dataclass

from stages.contract.inputs import Input, Inputs
from stages.lib.detection.mask_settings import MASK_REFINE_EPS, MaskScore

MACHINE = ("device",)  # stages/engine/machine.py: the detector runs on the run's device
INPUTS = Inputs((Input("model"), Input("testset", raw="testset")))


@dataclass
class EvalConfig:
    """max_images: evaluate only the first N test images (0 = all). draw_*: the predictions.png grid.
    onnx: also export the detector to model.onnx (batch 1, any size: the network up to its mask head,
    stages/lib/detection/onnx_export.py; `python -m stages.app.predict model.onnx PHOTOS` runs it) and check it on the
    first test image in onnxruntime against PyTorch, both post-processed alike (adds a few seconds).
    mask_threshold: a pixel whose mask probability exceeds it is in the mask. mask_score: the score that ranks the
    masks in the mask AP (MaskScore, stages/lib/detection/mask_settings.py); the box AP always ranks by the box score.
    mask_refine_radius: the pasted mask probabilities are guided-filtered by the photo's colours before the
    threshold (stages/lib/masks/refine.py), in windows of this radius in pixels at the detector's input scale
    (its image_size; 6 is 8 pixels in a 640x480 photo); 0 = the mask head's masks as they are. mask_refine_eps: the
    filter's regulariser in squared colour units (colours in [0, 1]). Both chosen on composed images of another
    seed (benchmarks/mask_refinement.py). The post-processing is shared with predict
    (stages/lib/detection/postprocess.py), which keeps these settings in a model folder.
    mask_owner_score: a detection with at least this box score takes from a detection of another class whose mask is
    no smaller than its own the pixels where its mask probability is the higher and above mask_threshold
    (stages/lib/masks/overlap.py), so the masks of different objects are disjoint, as what a photo shows of them
    is; None keeps the overlaps. Chosen among eight rules on composed images of another seed (the same benchmark).
    """

    max_images: int = 0
    mask_threshold: float = 0.5
    mask_score: MaskScore = MaskScore.maskness
    mask_refine_radius: float = 6.0
    mask_refine_eps: float = MASK_REFINE_EPS
    mask_owner_score: float | None = 0.5
    draw_images: int = 8
    draw_score_threshold: float = 0.5
    threads: int = 0
    onnx: bool = False

    def __post_init__(self) -> None:
        if self.mask_refine_radius < 0 or self.mask_refine_eps <= 0:
            raise ValueError(f"eval: need mask_refine_radius >= 0 and mask_refine_eps > 0, got "
                             f"{self.mask_refine_radius} and {self.mask_refine_eps}")
        if self.mask_owner_score is not None and not 0.0 <= self.mask_owner_score <= 1.0:
            raise ValueError(f"eval: mask_owner_score must be in [0, 1] or None, got {self.mask_owner_score}")
