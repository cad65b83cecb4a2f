"""torchvision Mask R-CNN sized for a CPU: 3-level FPN, matching anchors, lighter heads."""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import asdict

import torch
from torch import nn
from torchvision.models.detection import MaskRCNN
from torchvision.models.detection.anchor_utils import AnchorGenerator
from torchvision.models.detection.faster_rcnn import FastRCNNPredictor, TwoMLPHead
from torchvision.models.detection.mask_rcnn import MaskRCNNHeads, MaskRCNNPredictor
from torchvision.models.detection.rpn import RegionProposalNetwork, RPNHead
from torchvision.ops import MultiScaleRoIAlign

from stages.contract.choices import plain
from stages.lib.torch_files import load_torch_file

from .backbones import FPN_STRIDES, build_backbone, level_names
from .model_config import ModelConfig

FEATURE_NAMES = level_names(fine=False)  # the levels of the RPN and the box head (strides 8, 16, 32)


class PyramidRPN(RegionProposalNetwork):
    """torchvision's RPN on the named FPN levels only (the mask head's stride-4 level gets no anchors)."""

    levels: list[str] = FEATURE_NAMES

    def forward(self, images, features, targets=None):
        """features: OrderedDict name -> [B, C, H/s, W/s]; the levels outside `levels` are left out."""
        return super().forward(images, OrderedDict((name, features[name]) for name in self.levels), targets)


def build_maskrcnn(cfg: ModelConfig, num_classes: int, load_weights: bool = True) -> MaskRCNN:
    """Mask R-CNN for `num_classes` object classes (label 0 is background).

    load_weights: read the backbone's ImageNet weights when cfg.pretrained; pass False when a trained
    state dict is loaded right after (the layer structure is the same either way).
    """
    if len(cfg.anchor_sizes) != len(FPN_STRIDES) or len({len(s) for s in cfg.anchor_sizes}) != 1:
        raise ValueError(f"anchor_sizes needs {len(FPN_STRIDES)} lists of equal length, got {cfg.anchor_sizes}")
    weights = cfg.weights_path if cfg.pretrained and load_weights else None
    fine = cfg.mask_feature_stride == 4
    backbone = build_backbone(cfg.backbone, cfg.pretrained, weights, cfg.trainable_layers, cfg.fpn_channels, fine)
    anchors = AnchorGenerator(tuple(tuple(s) for s in cfg.anchor_sizes), ((0.5, 1.0, 2.0),) * len(FPN_STRIDES))
    channels = cfg.fpn_channels
    model = MaskRCNN(
        backbone.module, num_classes=None,
        min_size=cfg.image_size, max_size=cfg.image_size,
        image_mean=backbone.image_mean, image_std=backbone.image_std,
        rpn_anchor_generator=anchors, rpn_head=RPNHead(channels, anchors.num_anchors_per_location()[0]),
        rpn_pre_nms_top_n_train=cfg.rpn_pre_nms_train, rpn_post_nms_top_n_train=cfg.rpn_post_nms_train,
        rpn_pre_nms_top_n_test=cfg.rpn_pre_nms_test, rpn_post_nms_top_n_test=cfg.rpn_post_nms_test,
        rpn_batch_size_per_image=cfg.rpn_batch_size_per_image,
        box_roi_pool=MultiScaleRoIAlign(FEATURE_NAMES, output_size=7, sampling_ratio=cfg.roi_sampling_ratio),
        box_head=TwoMLPHead(channels * 7 * 7, cfg.box_head_size),
        box_predictor=FastRCNNPredictor(cfg.box_head_size, num_classes + 1),
        box_batch_size_per_image=cfg.box_batch_size_per_image, box_score_thresh=cfg.box_score_thresh,
        box_detections_per_img=cfg.detections_per_image,
        mask_roi_pool=MultiScaleRoIAlign(level_names(fine), output_size=cfg.mask_roi_size,
                                         sampling_ratio=cfg.roi_sampling_ratio),
        mask_head=MaskRCNNHeads(channels, [cfg.mask_head_channels] * cfg.mask_head_layers, 1),
        mask_predictor=MaskRCNNPredictor(cfg.mask_head_channels, cfg.mask_head_channels, num_classes + 1),
        _skip_resize=True,  # training: the data pipeline sizes (and crops) images; inference still resizes
    )
    if fine:
        model.rpn.__class__ = PyramidRPN  # the same RPN (modules, settings, state-dict keys) on the 3 levels
    init_predictors(model)
    return model


def init_predictors(model: MaskRCNN) -> None:
    """Small initial outputs of the last layers (as Detectron2 does), so the first losses are sane.

    torchvision's default (Kaiming) init gave initial mask losses of 2-9 instead of ln 2 with
    ImageNet-initialised features of large magnitude (EfficientNet-Lite0's are ~6x ResNet's).
    """
    predictor = model.roi_heads.box_predictor
    for layer, std in ((predictor.cls_score, 0.01), (predictor.bbox_pred, 0.001),
                       (model.roi_heads.mask_predictor.mask_fcn_logits, 0.001)):
        nn.init.normal_(layer.weight, std=std)
        nn.init.zeros_(layer.bias)


def count_parameters(model: nn.Module) -> dict:
    """Total and trainable parameter counts."""
    return {"total": sum(p.numel() for p in model.parameters()),
            "trainable": sum(p.numel() for p in model.parameters() if p.requires_grad)}


def save_detector(path, model: nn.Module, cfg: ModelConfig, category_names: list[str]) -> None:
    """Write model.pt: state dict, the ModelConfig as a dict, and the category names (label i+1)."""
    torch.save({"state_dict": model.state_dict(), "model_config": plain(asdict(cfg)),
                "category_names": list(category_names)}, path)


def load_detector(path, device: str = "cpu") -> tuple[MaskRCNN, ModelConfig, list[str]]:
    """Rebuild a detector from model.pt (no ImageNet weights read); returns it in eval mode. The file is read by
    the bounded reader (stages/lib/torch_files.py): a truncated or foreign file is a StageError naming it."""
    saved = load_torch_file(path, "detector file")
    missing = {"state_dict", "model_config", "category_names"} - set(saved)
    if missing:
        raise ValueError(f"{path}: not a detector file written by train_maskrcnn (lacks {sorted(missing)})")
    cfg = ModelConfig(**saved["model_config"])
    model = build_maskrcnn(cfg, len(saved["category_names"]), load_weights=False)
    model.load_state_dict(saved["state_dict"], strict=True)
    return to_device(model, device).eval(), cfg, saved["category_names"]


def to_device(model: nn.Module, device: str) -> nn.Module:
    """Move the model to `device` in channels-last memory format (17 % faster CPU training steps)."""
    return model.to(device=device, memory_format=torch.channels_last)
