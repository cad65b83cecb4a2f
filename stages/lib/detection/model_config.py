"""The detector's settings (what model.pt records to rebuild it) and the backbones to choose from: plain dataclasses
(no torch), so that configs holding them load without the libraries that use them."""
from __future__ import annotations

from dataclasses import dataclass, field, fields

from stages.contract.choices import choices

BACKBONES = ("efficientnet_lite0_fpn", "resnet18_fpn", "resnet50_fpn", "mobilenet_v3_fpn")


BackboneName = choices("BackboneName", BACKBONES)  # train_maskrcnn.backbone


@dataclass
class ModelConfig:
    """Everything needed to rebuild the detector (saved in model.pt; the training config extends it).

    image_size: images are resized so the longer side is this many pixels (min_size = max_size) for
        inference; training images arrive sized (and maybe cropped) by the data pipeline, unresized.
    anchor_sizes: anchor side lengths in pixels per FPN level (strides 8, 16, 32), each with 3 aspect ratios.
    trainable_layers: with pretrained weights, how many of the backbone's 5 layer groups train.
    roi_sampling_ratio: RoIAlign samples per bin and axis (1 cost 15 % less per CPU training step
        than 2; its backward pass is single-threaded scatter on a CPU).
    mask_roi_size: the side of the RoIAlign grid the mask head reads; it predicts masks on a grid twice that
        (14: torchvision's 28x28).
    mask_feature_stride: 8 (default), or 4: the FPN gains a stride-4 level from which the mask head alone
        reads the boxes under 112 px (torchvision's level rule); the RPN and box head keep strides 8-32.
    Head sizes are the CPU's (benchmarks/results/detector.md): 64 FPN channels cost 27 % less per step
    than 128 at the same box mAP, 64 mask-head channels 21 % less (the mask head's backward was half of
    all convolution gradients); a GPU budget (train_maskrcnn.cuda) restores the wider heads.
    """

    backbone: BackboneName = BackboneName.efficientnet_lite0_fpn
    pretrained: bool = True
    weights_path: str = ""
    trainable_layers: int = 3
    image_size: int = 512
    fpn_channels: int = 64
    anchor_sizes: list[list[int]] = field(default_factory=lambda: [[16, 32], [48, 96], [128, 256]])
    rpn_pre_nms_train: int = 300
    rpn_post_nms_train: int = 150
    rpn_pre_nms_test: int = 300
    rpn_post_nms_test: int = 150
    rpn_batch_size_per_image: int = 128
    box_batch_size_per_image: int = 64
    box_head_size: int = 512
    mask_head_channels: int = 64
    mask_head_layers: int = 2
    mask_roi_size: int = 14
    mask_feature_stride: int = 8
    roi_sampling_ratio: int = 1
    box_score_thresh: float = 0.05
    detections_per_image: int = 50

    def __post_init__(self) -> None:
        if self.mask_feature_stride not in (4, 8):
            raise ValueError(f"train_maskrcnn.mask_feature_stride must be 4 or 8, got {self.mask_feature_stride}")


def model_config_of(cfg) -> ModelConfig:
    """The ModelConfig part of a config object that has (at least) ModelConfig's fields."""
    return ModelConfig(**{f.name: getattr(cfg, f.name) for f in fields(ModelConfig)})
