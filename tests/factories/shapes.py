"""A small synthetic COCO dataset (coloured rectangles and discs on noise) for tests and smoke runs."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from stages.lib.coco import CocoBuilder

SHAPE_NAMES = ["red_box", "blue_disc"]


def shape_mask(kind: str, height: int, width: int, rng: np.random.Generator) -> np.ndarray:
    """A random [H, W] bool mask of a rectangle ("red_box") or disc ("blue_disc"), 15-40 % of the size."""
    size = rng.uniform(0.15, 0.4) * min(height, width)
    cy, cx = rng.uniform(size / 2, height - size / 2), rng.uniform(size / 2, width - size / 2)
    ys, xs = np.mgrid[:height, :width] + 0.5
    if kind == "red_box":
        return (np.abs(ys - cy) < size / 2) & (np.abs(xs - cx) < size * 0.35)
    return (ys - cy) ** 2 + (xs - cx) ** 2 < (size / 2) ** 2


def write_shapes_dataset(folder: str | Path, num_images: int, size: int = 96, seed: int = 0,
                         names: list[str] | None = None) -> Path:
    """Write `folder/images/*.png` + `folder/annotations.json` with 1-2 shapes per image; returns folder.

    names: category names in id order (default SHAPE_NAMES); shape i is drawn for category i.
    """
    folder = Path(folder)
    (folder / "images").mkdir(parents=True, exist_ok=True)
    names = names or SHAPE_NAMES
    colours = np.array([[220, 40, 40], [40, 60, 220]], np.uint8)
    rng = np.random.default_rng(seed)
    builder = CocoBuilder(names)
    for i in range(num_images):
        image = rng.integers(60, 190, size=(size, size, 3), dtype=np.uint8)  # [H, W, 3] noise
        image_id = builder.add_image(f"{i:04d}.png", size, size)
        occupied = np.zeros((size, size), bool)
        for k in rng.permutation(len(SHAPE_NAMES))[: rng.integers(1, 3)]:
            mask = shape_mask(SHAPE_NAMES[k], size, size, rng) & ~occupied
            if mask.sum() < 20:
                continue
            image[mask] = colours[k]
            occupied |= mask
            builder.add_instance(image_id, int(k) + 1, mask)
        Image.fromarray(image).save(folder / "images" / f"{i:04d}.png")
    builder.dataset.write(folder)
    return folder
