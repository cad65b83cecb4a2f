"""Masks of different objects made disjoint, at inference: a pixel of the photo shows one object.

Mask R-CNN predicts each detection's mask on its own, so where two objects touch, both masks may claim the same
pixels: on the sample's test photos the plant's mask takes in a green vase standing beside it, whole, while the
vase's own detection claims it too (benchmarks/results/plant_masks.md, "One object per pixel"). A pixel in the masks
of two classes goes to the surer mask (the higher probability), with one exception: a mask never gives pixels to a
larger one. A mask that spills over a neighbour is larger than it should be, so in the measurements a rule of
probability alone let the bigger objects' spill take the small eyedrops' and cans' pixels; with the exception the
small keep theirs and the spill is still cut back. Only a confident detection (box score at least `owner_score`)
takes pixels. Detections of the same class keep their overlaps: those are mostly duplicates of one object, which would
carve each other up.
"""
from __future__ import annotations

import torch

from stages.lib.masks.box import tensor_mask_box


def separate_classes(probability: torch.Tensor, scores: torch.Tensor, labels: torch.Tensor, threshold: float,
                     owner_score: float) -> torch.Tensor:
    """Mask probabilities [N, H, W] in which each mask has given up the pixels a rival of another class holds.

    probability: [N, H, W] in [0, 1] (pasted, possibly refined); scores: [N] box scores; labels: [N] class labels;
    threshold: the probability above which a pixel is in a mask; owner_score: the box score from which a detection
    takes pixels (one below it can lose pixels but takes none).
    A rival of detection i is a detection j of another class with scores[j] >= owner_score whose mask (the pixels
    above `threshold`) is no larger than i's. Where i's mask and a rival's overlap and the rival's probability is the
    higher, i's probability is set to 0; elsewhere it is kept.
    """
    masks = probability > threshold  # [N, H, W]
    areas = masks.sum(dim=(1, 2))  # [N]
    owners = scores >= owner_score  # [N]
    separated = probability
    for i in torch.nonzero(areas > 0).flatten().tolist():
        rivals = owners & (labels != labels[i]) & (areas <= areas[i])  # [N]
        if not bool(rivals.any()):
            continue
        x0, y0, x1, y1 = tensor_mask_box(masks[i])  # i's mask is not empty
        own = probability[i, y0:y1, x0:x1]  # [h, w]
        rival = probability[rivals, y0:y1, x0:x1].amax(dim=0)  # [h, w]
        beaten = masks[i, y0:y1, x0:x1] & (rival > own)  # [h, w]: in i's mask, so the rival's is above threshold too
        if bool(beaten.any()):
            if separated is probability:
                separated = probability.clone()
            separated[i, y0:y1, x0:x1] = own.masked_fill(beaten, 0.0)
    return separated
