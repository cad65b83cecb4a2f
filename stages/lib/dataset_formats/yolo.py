"""COCO dataset folders as one YOLO (Ultralytics) dataset: `images/<split>/`, `labels/<split>/<stem>.txt` and
`data.yaml` (docs/stage_contracts.md, section "Dataset formats").

A label line is `class x_centre y_centre width height` (task detect: the COCO box) or `class x1 y1 x2 y2 ...`
(task segment: the mask as one polygon, stages/lib/dataset_formats/polygons.py), coordinates normalised by the image
size; class ids are 0.. in the category order of the `train` split, the other splits' categories are
matched by name. Crowd annotations are left out (as Ultralytics' own converter does); an image without
instances gets an empty label file (a background image).
"""
from __future__ import annotations

import logging
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable

import numpy as np
import yaml

from stages.contract.errors import StageError
from stages.lib.coco import segmentation_mask
from stages.lib.dataset_formats.polygons import mask_box, mask_iou, mask_polygon, polygon_mask
from stages.records.coco_dataset import CocoDataset

log = logging.getLogger(__name__)

TASKS = ("segment", "detect")
DATA_YAML = "data.yaml"
YAML_SPLITS = ("train", "val", "test")  # the split keys Ultralytics reads from data.yaml


@dataclass
class SplitStats:
    """What one split's export wrote and how well its polygons give back the masks."""

    images: int = 0
    instances: int = 0
    crowd_skipped: int = 0
    polygon_iou: list[float] = field(default_factory=list)  # per instance: the polygon filled again vs its mask
    several_loops: int = 0  # instances whose polygon joins several components or holes

    def summary(self) -> dict:
        """JSON-able counts and the polygon IoU's minimum, mean and share >= 0.95."""
        out = {"images": self.images, "instances": self.instances, "crowd_skipped": self.crowd_skipped}
        if self.polygon_iou:
            iou = np.asarray(self.polygon_iou)
            out.update(polygon_iou_min=round(float(iou.min()), 4), polygon_iou_mean=round(float(iou.mean()), 4),
                       polygon_iou_share_095=round(float((iou >= 0.95).mean()), 4), several_loops=self.several_loops)
        return out


def polygon_fit(mask: np.ndarray, polygon: np.ndarray) -> float:
    """IoU of a mask [H, W] bool and its polygon [P, 2] (pixel coordinates) filled again, computed in the
    mask's box (the polygon and its bridges lie inside it)."""
    x0, y0, x1, y1 = mask_box(mask)
    filled = polygon_mask(polygon - np.array([x0, y0]), x1 - x0, y1 - y0)
    crop = mask[y0:y1, x0:x1]
    return mask_iou(crop, filled)


def label_line(class_id: int, values: np.ndarray) -> str:
    """`class v1 v2 ...` with the normalised values [N] to 6 decimals."""
    return str(class_id) + " %.6f" * len(values) % tuple(values)


def image_labels(image: dict, anns: list[dict], class_of: dict[int, int], task: str, stats: SplitStats,
                 source: Path) -> list[str]:
    """The label lines of one image's annotations (with masks for task segment: require_masks); updates
    `stats`. StageError for an empty mask."""
    size = np.array([image["width"], image["height"]], dtype=np.float64)
    lines = []
    for ann in anns:
        if ann.get("iscrowd", 0):
            stats.crowd_skipped += 1
            continue
        class_id = class_of[ann["category_id"]]
        if task == "detect":
            x, y, w, h = ann["bbox"]
            lines.append(label_line(class_id, np.array([x + w / 2, y + h / 2, w, h]) / np.tile(size, 2)))
        else:
            mask = segmentation_mask(ann["segmentation"], image["height"], image["width"])
            if not mask.any():
                raise StageError(f"{source}: annotation {ann['id']} has an empty mask")
            polygon = mask_polygon(mask)
            stats.polygon_iou.append(polygon_fit(mask, polygon.points))
            stats.several_loops += int(polygon.loops > 1)
            lines.append(label_line(class_id, (polygon.points / size).ravel()))
        stats.instances += 1
    return lines


def require_masks(dataset: CocoDataset, source: Path) -> None:
    """StageError (before anything is written) unless every non-crowd annotation has a mask."""
    for ann in dataset.annotations:
        if not ann.get("iscrowd", 0) and not ann.get("segmentation"):
            raise StageError(f"{source}: annotation {ann['id']} has no mask; a boxes-only dataset exports with "
                             "--format yolo-detect")


def class_ids(dataset: CocoDataset, names: list[str], source: Path) -> dict[int, int]:
    """{category id of `dataset`: YOLO class id} matched by name to `names`; StageError for a category the
    train split lacks."""
    unknown = sorted(set(dataset.category_names) - set(names))
    if unknown:
        raise StageError(f"{source}: categories {unknown} are not among the train split's {names} (categories "
                         "match by name)")
    return {c["id"]: names.index(c["name"]) for c in dataset.categories}


def export_split(folder: Path, dataset: CocoDataset, split: str, names: list[str], out: Path, task: str,
                 progress: Callable[[Iterable], Iterable]) -> SplitStats:
    """Copy one dataset's images to out/images/<split>/ and write its labels to out/labels/<split>/."""
    source = folder / CocoDataset.JSON
    class_of, stats = class_ids(dataset, names, source), SplitStats()
    by_image = dataset.annotations_by_image()
    for image in progress(dataset.images):
        target = out / "images" / split / image["file_name"]
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(CocoDataset.image_file(folder, image), target)
        label = (out / "labels" / split / image["file_name"]).with_suffix(".txt")
        label.parent.mkdir(parents=True, exist_ok=True)
        lines = image_labels(image, by_image[image["id"]], class_of, task, stats, source)
        label.write_text("".join(line + "\n" for line in lines))
        stats.images += 1
    return stats


def export_yolo(splits: dict[str, Path], out: Path, task: str,
                progress: Callable[[Iterable], Iterable] = lambda items: items) -> dict:
    """Export COCO dataset folders {split: folder} (a `train` split, optionally `val` and `test`) into `out`
    as one YOLO dataset of `task` ("segment" | "detect"); without `val`, data.yaml validates on train.
    Returns {split: SplitStats.summary()} and the class names."""
    if task not in TASKS:
        raise StageError(f"YOLO task must be one of {TASKS}, not {task!r}")
    unknown = sorted(set(splits) - set(YAML_SPLITS))
    if "train" not in splits or unknown:
        raise StageError(f"YOLO splits are {YAML_SPLITS} with a train split; got {sorted(splits)}")
    datasets = {split: CocoDataset.read(folder) for split, folder in splits.items()}
    names = datasets["train"].category_names
    for split, dataset in datasets.items():
        class_ids(dataset, names, splits[split] / CocoDataset.JSON)
        if task == "segment":
            require_masks(dataset, splits[split] / CocoDataset.JSON)
    summary = {}
    for split, dataset in datasets.items():
        summary[split] = export_split(splits[split], dataset, split, names, out, task, progress).summary()
        log.info("YOLO %s split %s: %s", task, split, summary[split])
    data = {split: f"images/{split}" for split in YAML_SPLITS if split in splits}
    data.setdefault("val", "images/train")
    data["names"] = dict(enumerate(names))
    header = (f"# YOLO {task} dataset written by `python -m stages.app.convert` from "
              f"{', '.join(f'{split}: {folder}' for split, folder in splits.items())}\n"
              "# paths are relative to this file's folder (no `path:` key)\n")
    (out / DATA_YAML).write_text(header + yaml.safe_dump({key: data[key] for key in ("train", "val", "test", "names")
                                                          if key in data}, sort_keys=False, allow_unicode=True))
    return {"task": task, "names": names, "splits": summary}
