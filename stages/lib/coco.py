"""COCO instance-segmentation datasets: RLE masks, a builder of the dataset record
(stages/records/coco_dataset.py), and loading a dataset folder with pycocotools."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from pycocotools import mask as mask_utils

from stages.records.coco_dataset import CocoDataset


def mask_to_rle(mask: np.ndarray) -> dict:
    """Encode a binary mask as COCO compressed RLE with a JSON-able string `counts`.

    mask: [H, W] bool or 0/1 array.
    """
    rle = mask_utils.encode(np.asfortranarray(mask.astype(np.uint8)))
    return {"size": [int(s) for s in rle["size"]], "counts": rle["counts"].decode("ascii")}


def _encoded(rle: dict) -> dict:
    """A COCO RLE (compressed string or uncompressed list counts) as pycocotools' compressed form (bytes)."""
    if isinstance(rle.get("counts"), list):
        return mask_utils.frPyObjects(rle, *rle["size"])
    if isinstance(rle.get("counts"), str):
        return {"size": rle["size"], "counts": rle["counts"].encode("ascii")}
    return rle


def rle_to_mask(rle: dict) -> np.ndarray:
    """Decode a COCO RLE (compressed string or uncompressed list counts) to a [H, W] bool mask."""
    return mask_utils.decode(_encoded(rle)).astype(bool)


def rle_box_and_area(rle: dict) -> tuple[list[float], int]:
    """The tight box [x, y, w, h] and the pixel count of a COCO RLE, without decoding it."""
    encoded = _encoded(rle)
    return [float(v) for v in mask_utils.toBbox(encoded)], int(mask_utils.area(encoded))


def segmentation_mask(segmentation: dict | list, height: int, width: int) -> np.ndarray:
    """A COCO segmentation (RLE, or a list of polygons [x1, y1, x2, y2, ...]) as a [height, width] bool mask."""
    if isinstance(segmentation, list):
        return mask_utils.decode(mask_utils.merge(mask_utils.frPyObjects(segmentation, height, width))).astype(bool)
    return rle_to_mask(segmentation)


def mask_bbox(mask: np.ndarray) -> list[float]:
    """Tight COCO box [x, y, w, h] in pixels of a non-empty [H, W] mask."""
    ys, xs = np.nonzero(mask)
    x0, y0 = float(xs.min()), float(ys.min())
    return [x0, y0, float(xs.max()) + 1.0 - x0, float(ys.max()) + 1.0 - y0]


class CocoBuilder:
    """Collects images and instance masks into a CocoDataset (category ids 1..n in given order)."""

    def __init__(self, categories: list[str], info: dict[str, Any] | None = None):
        self.dataset = CocoDataset([], [], [{"id": i + 1, "name": name, "supercategory": "object"}
                                            for i, name in enumerate(categories)], dict(info or {}))

    def category_id(self, name: str) -> int:
        """The id of a category by name; KeyError names the known categories."""
        for cat in self.dataset.categories:
            if cat["name"] == name:
                return cat["id"]
        raise KeyError(f"unknown category {name!r}; known: {self.dataset.category_names}")

    def add_image(self, file_name: str, width: int, height: int, **extra: Any) -> int:
        """Register an image; returns its id (1-based, in insertion order)."""
        image_id = len(self.dataset.images) + 1
        self.dataset.images.append({"id": image_id, "file_name": file_name, "width": int(width),
                                    "height": int(height), **extra})
        return image_id

    def add_instance(self, image_id: int, category_id: int, mask: np.ndarray, **extra: Any) -> int:
        """Add one instance; box and area come from the [H, W] mask, which must be non-empty."""
        mask = np.asarray(mask, dtype=bool)
        area = int(mask.sum())
        if area == 0:
            raise ValueError(f"empty mask for an instance of category {category_id} in image {image_id}")
        ann_id = len(self.dataset.annotations) + 1
        self.dataset.annotations.append({
            "id": ann_id, "image_id": int(image_id), "category_id": int(category_id),
            "segmentation": mask_to_rle(mask), "area": area, "bbox": mask_bbox(mask), "iscrowd": 0, **extra,
        })
        return ann_id


def load_coco(folder: str | Path):
    """A dataset folder (images/ + annotations.json, checked by CocoDataset.read) as a pycocotools COCO
    object, loaded quietly. `folder` may also be the path of its annotations.json."""
    import contextlib
    import io

    from pycocotools.coco import COCO

    folder = Path(folder)
    if folder.name == CocoDataset.JSON:
        folder = folder.parent
    coco = COCO()
    coco.dataset = CocoDataset.read(folder).to_dict()
    with contextlib.redirect_stdout(io.StringIO()):
        coco.createIndex()
    return coco


def format_ap(ap: float | None) -> str:
    """An AP (percent) for people: "61.3", or "n/a" where the test set cannot measure it (boxes only)."""
    return "n/a" if ap is None else f"{ap:.1f}"
