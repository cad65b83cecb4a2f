"""COCO instance-segmentation datasets: RLE masks, a builder, and loading with pycocotools."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from pycocotools import mask as mask_utils


def mask_to_rle(mask: np.ndarray) -> dict:
    """Encode a binary mask as COCO compressed RLE with a JSON-able string `counts`.

    mask: [H, W] bool or 0/1 array.
    """
    rle = mask_utils.encode(np.asfortranarray(mask.astype(np.uint8)))
    return {"size": [int(s) for s in rle["size"]], "counts": rle["counts"].decode("ascii")}


def rle_to_mask(rle: dict) -> np.ndarray:
    """Decode a COCO RLE (compressed string or uncompressed list counts) to a [H, W] bool mask."""
    if isinstance(rle.get("counts"), list):
        rle = mask_utils.frPyObjects(rle, *rle["size"])
    elif isinstance(rle.get("counts"), str):
        rle = {"size": rle["size"], "counts": rle["counts"].encode("ascii")}
    return mask_utils.decode(rle).astype(bool)


def mask_bbox(mask: np.ndarray) -> list[float]:
    """Tight COCO box [x, y, w, h] in pixels of a non-empty [H, W] mask."""
    ys, xs = np.nonzero(mask)
    x0, y0 = float(xs.min()), float(ys.min())
    return [x0, y0, float(xs.max()) + 1.0 - x0, float(ys.max()) + 1.0 - y0]


class CocoBuilder:
    """Collects images and instance masks into one COCO dict (category ids 1..n in given order)."""

    def __init__(self, categories: list[str], info: dict[str, Any] | None = None):
        self.categories = [{"id": i + 1, "name": name, "supercategory": "object"} for i, name in enumerate(categories)]
        self.images: list[dict] = []
        self.annotations: list[dict] = []
        self.info = dict(info or {})

    def category_id(self, name: str) -> int:
        """The id of a category by name; KeyError names the known categories."""
        for cat in self.categories:
            if cat["name"] == name:
                return cat["id"]
        raise KeyError(f"unknown category {name!r}; known: {[c['name'] for c in self.categories]}")

    def add_image(self, file_name: str, width: int, height: int, **extra: Any) -> int:
        """Register an image; returns its id (1-based, in insertion order)."""
        image_id = len(self.images) + 1
        self.images.append({"id": image_id, "file_name": file_name, "width": int(width), "height": int(height), **extra})
        return image_id

    def add_instance(self, image_id: int, category_id: int, mask: np.ndarray, **extra: Any) -> int:
        """Add one instance; box and area come from the [H, W] mask, which must be non-empty."""
        mask = np.asarray(mask, dtype=bool)
        area = int(mask.sum())
        if area == 0:
            raise ValueError(f"empty mask for an instance of category {category_id} in image {image_id}")
        ann_id = len(self.annotations) + 1
        self.annotations.append({
            "id": ann_id, "image_id": int(image_id), "category_id": int(category_id),
            "segmentation": mask_to_rle(mask), "area": area, "bbox": mask_bbox(mask), "iscrowd": 0, **extra,
        })
        return ann_id

    def to_dict(self) -> dict:
        """The dataset as a COCO dict."""
        return {"info": self.info, "licenses": [], "images": self.images,
                "annotations": self.annotations, "categories": self.categories}

    def write(self, path: str | Path) -> None:
        """Write the dataset JSON to `path`."""
        Path(path).write_text(json.dumps(self.to_dict()))


def read_coco_json(path: str | Path) -> dict:
    """The parsed COCO annotation file; ValueError naming the file and what is wrong when it is not JSON, or
    lacks the images, annotations or categories lists, or an annotation names an unknown image or category.
    FileNotFoundError when it is missing."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"COCO annotation file not found: {path}")
    try:
        data = json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError) as error:
        raise ValueError(f"{path}: not valid JSON ({error})") from error
    lists = ("images", "annotations", "categories")
    if not isinstance(data, dict) or any(not isinstance(data.get(key), list) for key in lists):
        raise ValueError(f"{path}: not a COCO annotation file (needs the lists {', '.join(lists)})")
    try:
        images = {image["id"] for image in data["images"] if image["file_name"]}
        categories = {category["id"] for category in data["categories"] if category["name"]}
        unknown = [(ann["id"], ann["image_id"], ann["category_id"]) for ann in data["annotations"]
                   if ann["image_id"] not in images or ann["category_id"] not in categories]
    except (KeyError, TypeError) as error:
        raise ValueError(f"{path}: an image, category or annotation lacks the key {error} "
                         "(images need id and file_name, categories id and name, annotations id, "
                         "image_id and category_id)") from error
    if unknown:
        raise ValueError(f"{path}: {len(unknown)} annotations name an image or category id that is not listed "
                         f"(first: annotation {unknown[0][0]}, image {unknown[0][1]}, category {unknown[0][2]})")
    return data


def load_coco(path: str | Path):
    """Load a COCO annotation file (checked by read_coco_json) with pycocotools, quietly."""
    import contextlib
    import io

    from pycocotools.coco import COCO

    coco = COCO()
    coco.dataset = read_coco_json(path)
    with contextlib.redirect_stdout(io.StringIO()):
        coco.createIndex()
    return coco


def format_ap(ap: float | None) -> str:
    """An AP (percent) for people: "61.3", or "n/a" where the test set cannot measure it (boxes only)."""
    return "n/a" if ap is None else f"{ap:.1f}"
