"""A COCO instance dataset folder: `images/` and `annotations.json` (`file_name` relative to `images/`).

Written by compose and cut_and_paste (stages/lib/composition/dataset.py) and by the sample's test sets; read by
eval, train_maskrcnn (stages/lib/detection/data.py), the preflight check of a user's test set and the exports
(stages/lib/dataset_formats/). docs/stage_contracts.md, sections compose / cut_and_paste and eval. Annotations may carry
fields pycocotools ignores (compose: `visible_fraction`, `pose`, `amodal_segmentation`, ...); they are kept
as they are.
"""
from __future__ import annotations

import json
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

from stages.contract.errors import StageError
from stages.lib.file_checks import count_text, finite_number, max_image_pixels, regular_file
from stages.records.files import write_json

LISTS = ("images", "annotations", "categories")


@dataclass
class CocoDataset:
    """The parsed annotations.json of a dataset folder (COCO dicts, extra fields kept)."""

    images: list[dict]  # {"id", "file_name", "width", "height", ...}
    annotations: list[dict]  # {"id", "image_id", "category_id", "bbox", ["segmentation", "area", "iscrowd"], ...}
    categories: list[dict]  # {"id", "name", ["supercategory"]}
    info: dict[str, Any] = field(default_factory=dict)
    licenses: list = field(default_factory=list)

    JSON: ClassVar[str] = "annotations.json"
    IMAGES: ClassVar[str] = "images"

    def to_dict(self) -> dict:
        """The dataset as a COCO dict (the key order of the file)."""
        return {"info": self.info, "licenses": self.licenses, "images": self.images,
                "annotations": self.annotations, "categories": self.categories}

    def write(self, folder: Path) -> None:
        """Write annotations.json into `folder` (the images are the writer's: `images/<file_name>`)."""
        write_json(Path(folder) / self.JSON, self.to_dict())

    @classmethod
    def image_file(cls, folder: Path, image: dict) -> Path:
        """The file of one image entry of the dataset in `folder`."""
        return Path(folder) / cls.IMAGES / image["file_name"]

    @property
    def category_names(self) -> list[str]:
        """Category names in id order."""
        return [c["name"] for c in sorted(self.categories, key=lambda c: c["id"])]

    def annotations_by_image(self) -> dict[int, list[dict]]:
        """{image id: its annotations in file order} for every image (empty lists included)."""
        by_image: dict[int, list[dict]] = {image["id"]: [] for image in self.images}
        for ann in self.annotations:
            by_image[ann["image_id"]].append(ann)
        return by_image

    @classmethod
    def read(cls, folder: Path) -> "CocoDataset":
        """Read a dataset folder. StageError naming annotations.json when it is missing, unreadable or not JSON,
        lacks the images, annotations or categories lists or a required key, has no category, repeats an image
        id, a category id or name, has an image whose size is not positive or above the pixel limit or whose
        file_name is not a path inside images/, names an unknown image or category, has an RLE mask whose size is
        not its image's or a malformed polygon or box (NaN or infinite values included), or lists an image that
        is not in images/."""
        folder = Path(folder)
        path = folder / cls.JSON
        if not path.is_file():
            raise StageError(f"COCO annotation file not found: {path} (a dataset folder holds images/ and "
                             f"{cls.JSON})")
        regular_file(path, "COCO annotation file")
        try:
            data = json.loads(path.read_bytes())
        except (ValueError, RecursionError) as error:  # RecursionError: nesting too deep
            raise StageError(f"{path}: not valid JSON ({str(error)[:200]})") from error
        if not isinstance(data, dict) or any(not isinstance(data.get(key), list) for key in LISTS):
            raise StageError(f"{path}: not a COCO annotation file (needs the lists {', '.join(LISTS)})")
        dataset = cls(data["images"], data["annotations"], data["categories"], data.get("info") or {},
                      data.get("licenses") or [])
        try:
            dataset._check(path)
        except KeyError as error:
            raise StageError(f"{path}: an image, category or annotation lacks the key {error} (images need id, "
                             "file_name, width and height, categories id and name, annotations id, image_id, "
                             "category_id and bbox)") from error
        except TypeError as error:
            raise StageError(f"{path}: an image, category or annotation is not a mapping, or holds a value of the "
                             f"wrong type ({error})") from error
        except (ValueError, OverflowError) as error:
            raise StageError(f"{path}: an image's width or height is not a number ({error})") from error
        missing = [image["file_name"] for image in dataset.images if not cls.image_file(folder, image).is_file()]
        if missing:
            raise StageError(f"{path}: {len(missing)} of {len(dataset.images)} images are not in "
                             f"{folder / cls.IMAGES} (first: {missing[0]})")
        return dataset

    def _check(self, path: Path) -> None:
        """The checks of `read` on the parsed lists; KeyError / TypeError for a missing key."""
        sizes = {image["id"]: (int(image["height"]), int(image["width"])) for image in self.images
                 if image["file_name"]}
        for image in self.images:
            problem = image_problem(image)
            if problem:
                raise StageError(f"{path}: image {str(image['id'])[:40]}: {problem}")
        categories = {category["id"] for category in self.categories if category["name"]}
        if not categories:
            raise StageError(f"{path}: no categories")
        for what, values in (("image ids", [image["id"] for image in self.images]),
                             ("category ids", [c["id"] for c in self.categories]),
                             ("category names", [c["name"] for c in self.categories])):
            repeated = sorted(str(value) for value, count in Counter(values).items() if count > 1)
            if repeated:
                raise StageError(f"{path}: repeated {what} {repeated}")
        unknown = [(ann["id"], ann["image_id"], ann["category_id"]) for ann in self.annotations
                   if ann["image_id"] not in sizes or ann["category_id"] not in categories]
        if unknown:
            raise StageError(f"{path}: {len(unknown)} annotations name an image or category id that is not listed "
                             f"(first: annotation {unknown[0][0]}, image {unknown[0][1]}, category {unknown[0][2]})")
        for ann in self.annotations:
            problem = shape_problem(ann, sizes[ann["image_id"]])
            if problem:
                raise StageError(f"{path}: annotation {ann['id']} (image {ann['image_id']}): {problem}")


def image_problem(image: dict) -> str | None:
    """What is wrong with an image entry's file name and size, or None: file_name a relative path inside
    images/, width and height positive with at most max_image_pixels() pixels."""
    name, width, height = image["file_name"], int(image["width"]), int(image["height"])
    if not isinstance(name, str) or Path(name).is_absolute() or ".." in Path(name).parts or "\0" in name:
        return f"file_name {str(name)[:80]!r} is not a path inside images/"
    if width <= 0 or height <= 0 or width * height > max_image_pixels():
        return (f"size {count_text(width)}x{count_text(height)} is empty or above the limit of "
                f"{max_image_pixels() / 1e6:g} megapixels")
    return None


def shape_problem(ann: dict, size: tuple[int, int]) -> str | None:
    """What is wrong with an annotation's box and masks for an image of size (height, width), or None.

    A box is [x, y, w, h] with w, h >= 0; `segmentation` (and compose's `amodal_segmentation`) is absent
    (boxes only), an RLE of the image size, or a list of polygons of at least 3 (x, y) points each."""
    box = ann["bbox"]
    if not (isinstance(box, list) and len(box) == 4 and all(finite_number(v) for v in box)
            and box[2] >= 0 and box[3] >= 0):
        return f"bbox {str(box)[:80]} is not [x, y, width, height] of finite numbers"
    for key in ("segmentation", "amodal_segmentation"):
        segmentation = ann.get(key)
        if not segmentation:
            continue
        if isinstance(segmentation, dict):
            if list(segmentation.get("size", [])) != list(size) or not isinstance(segmentation.get("counts"), (str, list)):
                return (f"{key} is not an RLE mask of its image's size {list(size)} (size "
                        f"{segmentation.get('size')})")
        elif not isinstance(segmentation, list) or any(
                not isinstance(polygon, list) or len(polygon) < 6 or len(polygon) % 2
                or not all(finite_number(v) for v in polygon) for polygon in segmentation):
            return (f"{key} is neither an RLE mask nor a list of polygons [x1, y1, x2, y2, ...] of 3 points or more "
                    "(finite numbers)")
    return None
