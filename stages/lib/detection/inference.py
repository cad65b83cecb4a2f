"""The detector's forward pass up to the mask head, and the paste of its masks into the photo.

torchvision's Mask R-CNN ends by pasting every detection's mask probabilities (a grid of M x M cells over its box)
into a full-size [N, H, W] tensor, the slowest step on a CPU for the 50 detections of a photo and, in an ONNX graph,
a loop. `HeadOutputs` runs the same modules in the same order but stops before the paste, so that a caller pastes
only the detections it keeps (`paste`, one mask at a time as torchvision does: the same bits whichever are kept), and
the ONNX export (stages/lib/detection/onnx_export.py) is this module traced: both backends share what follows it.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import nn
from torchvision.models.detection import MaskRCNN
from torchvision.models.detection.roi_heads import paste_masks_in_image
from torchvision.models.detection.transform import resize_boxes

OUTPUT_NAMES = ("boxes", "labels", "scores", "mask_probs")  # HeadOutputs' outputs, the ONNX graph's too


def image_tensor(image: np.ndarray, device: str = "cpu") -> torch.Tensor:
    """An RGB uint8 image [H, W, 3] as the detector's input: float [3, H, W] in [0, 1] on `device`."""
    return torch.from_numpy(np.array(image, copy=True)).permute(2, 0, 1).float().div(255).to(device)


class HeadOutputs(nn.Module):
    """A trained MaskRCNN (eval mode) whose forward takes one image [3, H, W] in [0, 1] and returns boxes [N, 4]
    (x0 y0 x1 y1 in the image's pixels), labels [N] (1..K), scores [N] and mask_probs [N, 1, M, M] (each
    detection's mask probabilities of its label on its box's grid, not pasted): what `model([image])` computes
    before its masks are pasted, bit for bit."""

    def __init__(self, model: MaskRCNN):
        super().__init__()
        self.model = model

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        model = self.model
        images, _ = model.transform([image])
        features = model.backbone(images.tensors)
        proposals, _ = model.rpn(images, features)
        detections = model.roi_heads(features, proposals, images.image_sizes)[0][0]
        boxes = resize_boxes(detections["boxes"], images.image_sizes[0], (image.shape[-2], image.shape[-1]))
        return boxes, detections["labels"], detections["scores"], detections["masks"]


@torch.no_grad()
def head_outputs(model: nn.Module, image: np.ndarray, device: str) -> dict:
    """HeadOutputs of `model` on one RGB uint8 image [H, W, 3], as tensors on `device`: image [3, H, W] in [0, 1],
    boxes [N, 4], labels [N], scores [N], mask_probs [N, 1, M, M]."""
    x = image_tensor(image, device)  # [3, H, W]
    return {"image": x, **dict(zip(OUTPUT_NAMES, HeadOutputs(model)(x)))}


def paste(outputs: dict) -> dict:
    """head_outputs' dict with its masks pasted into the image: image [3, H, W], boxes [N, 4], scores [N],
    labels [N], probability [N, H, W] (torchvision's paste_masks_in_image, which pastes each mask on its own)."""
    height, width = outputs["image"].shape[-2:]
    probability = paste_masks_in_image(outputs["mask_probs"], outputs["boxes"], (height, width))[:, 0]
    return {"image": outputs["image"], "boxes": outputs["boxes"], "scores": outputs["scores"],
            "labels": outputs["labels"], "probability": probability}


def select(outputs: dict, keep: torch.Tensor) -> dict:
    """The detections of head_outputs' dict where keep [N] (bool) is true; the image as it is."""
    return {name: value if name == "image" else value[keep] for name, value in outputs.items()}
