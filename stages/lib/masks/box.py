"""The box of a mask's pixels, on the mask's own device (the torch twin of stages.lib.dataset_formats.polygons.mask_box, which
takes numpy masks): the eval's mask post-processing works in these boxes, not on the whole photo."""
from __future__ import annotations

import torch


def tensor_mask_box(mask: torch.Tensor) -> tuple[int, int, int, int] | None:
    """(x0, y0, x1, y1), ends exclusive, of the nonzero pixels of a [H, W] tensor; None when it has none."""
    rows, columns = mask.any(dim=1).nonzero()[:, 0], mask.any(dim=0).nonzero()[:, 0]
    if len(rows) == 0:
        return None
    return int(columns[0]), int(rows[0]), int(columns[-1]) + 1, int(rows[-1]) + 1
