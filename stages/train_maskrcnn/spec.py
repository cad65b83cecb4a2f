"""The train_maskrcnn stage's spec: the detector (ModelConfig) and its training on a COCO dataset folder (`dataset`),
sized for a 2-core CPU and, with `cuda`, for a GPU."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from stages.contract.choices import choices
from stages.contract.inputs import Input, Inputs
from stages.lib.detection.model_config import ModelConfig
from stages.lib.device import params_for_device

Optimizer = choices("Optimizer", ("sgd", "adamw"))  # train_maskrcnn.optimizer
Schedule = choices("Schedule", ("cosine", "step"))  # train_maskrcnn.schedule
# On a CUDA GPU: whole images at 512 px in batches of 8 with the wider heads, decoded by 6 processes, for a
# paper-like budget: 1250 iterations on the default 1000 images (measured on an H100 with 200-image datasets:
# 900 iterations gave 64.4 box mAP on test A, 1800 gave 68.2, at 0.21 s per iteration).
# The wider heads (the CPU defaults halve them): FPN and mask head channels, RoIs and training proposals.
WIDE_HEADS = {"fpn_channels": 128, "mask_head_channels": 128, "box_batch_size_per_image": 128,
              "rpn_pre_nms_train": 600, "rpn_post_nms_train": 300}
CUDA_BUDGET = {"image_size": 512, "train_crop": 0, "batch_size": 8, "epochs": 10.0, **WIDE_HEADS, "loader_workers": 6}


MACHINE = ("device",)  # stages/engine/machine.py: trained on the run's device
INPUTS = Inputs((Input("dataset"),))  # a COCO dataset folder


@dataclass
class TrainMaskrcnnConfig(ModelConfig):
    """Detector (ModelConfig fields) plus training settings, sized for a 2-core CPU.

    Budget: `epochs` passes over the dataset in batches of `batch_size` (iterations =
    ceil(epochs * images / batch_size)). `train_crop` > 0 trains on crop x crop windows around a
    random object of each image resized to `image_size`: objects keep the size they have at
    inference, and a step costs less than on the whole image. Default: 8 epochs of the default 1000
    composed images, 256 px windows of 512 px images: 8000 windows, 15-17 minutes on 2 cores of an AVX2
    EPYC (2.15x the 4-epoch budget), 60.6 / 60.3 box mAP on the sample's test A / B over three seeds, against
    54.9 / 55.0 at 4 epochs (benchmarks/results/detector.md: the curve the budget was chosen from;
    benchmarks/results/plant_masks.md: the plant's masks gain with the epochs).
    lr schedule: linear warm-up from lr * 0.001 over `warmup_iterations`, then `schedule`
    "cosine" (to lr * 0.05) or "step" (x0.1 at 70 % and 90 % of the budget).
    threads: torch CPU threads, 0 = all cores. loader_workers: processes that decode and augment
    the next batches while the model trains (0 = in the training process). bf16: the forward pass
    under bfloat16 autocast (losses and the weights stay float32).
    closeup_share: the share of training samples that are close-ups, one object zoomed until the longer side
    of its box is `closeup_fill` (a range, at most 1) of the training window (`train_crop`, else
    `image_size`). Without them the detector knows only the object sizes of the composed images and
    finds heads and bodies instead of whole objects in real close-up photos (benchmarks/results/real_plush_dog).
    mask_dice_weight: the weight of a Dice term beside the mask head's per-cell cross-entropy
        (stages/lib/masks/dice.py; 0 = torchvision's mask loss alone). At 1, over three seeds of the sample,
        the plant's mask AP gap to the other classes narrowed from 29.0 / 21.8 to 23.6 / 16.9 points on test A / B
        and mask mAP rose by 1.2 / 1.2 (benchmarks/results/plant_masks.md).
    cuda: settings that replace these on a CUDA GPU (`for_device`): the budget scales with the device.
    """

    epochs: float = 8.0
    batch_size: int = 4
    train_crop: int = 256
    optimizer: Optimizer = Optimizer.sgd
    lr: float = 0.02
    momentum: float = 0.9
    weight_decay: float = 1e-4
    warmup_iterations: int = 30
    schedule: Schedule = Schedule.cosine
    grad_clip: float = 5.0
    hflip: bool = True
    scale_min: float = 0.75
    scale_max: float = 1.25
    colour_jitter: float = 0.2
    mask_dice_weight: float = 1.0
    closeup_share: float = 0.25
    closeup_fill: list[float] = field(default_factory=lambda: [0.5, 1.0])
    checkpoint_every: int = 50
    checkpoint_dir: str = ""
    threads: int = 0
    loader_workers: int = 1
    bf16: bool = False
    cuda: dict[str, Any] = field(default_factory=lambda: dict(CUDA_BUDGET))

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.mask_dice_weight < 0:
            raise ValueError(f"train_maskrcnn.mask_dice_weight must be >= 0, got {self.mask_dice_weight}")
        low, high = self.closeup_fill
        if not 0.0 <= self.closeup_share <= 1.0 or not 0.0 < low <= high <= 1.0:
            raise ValueError(f"train_maskrcnn: need 0 <= closeup_share <= 1 and 0 < closeup_fill[0] <= "
                             f"closeup_fill[1] <= 1, got {self.closeup_share} and {list(self.closeup_fill)}")

    def iterations(self, num_images: int) -> int:
        """Training iterations of the budget on a dataset of `num_images` images."""
        return max(1, math.ceil(self.epochs * num_images / self.batch_size))


def for_device(params: dict, device: str) -> dict:
    """The stage's params for `device` (stages/lib/device.py `params_for_device`): the `cuda` settings applied on a
    CUDA GPU, dropped elsewhere; ValueError naming unknown `cuda` keys or the setting out of range."""
    return params_for_device(params, device, TrainMaskrcnnConfig, "train_maskrcnn")
