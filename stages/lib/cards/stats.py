"""The numbers of a dataset card, from a COCO dataset alone (and, for a composed one, the generator's record of
what it placed): per class instances, images and share; per instance its visible fraction (compose's
`visible_fraction`), size (square root of its mask area, pixels) and box centre (fractions of the image); per
image its instance count; the placement kinds; and the checks that flag a broken dataset."""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from stages.lib.coco import rle_box_and_area
from stages.records.coco_dataset import CocoDataset
from stages.records.placements import PlacementsRecord

STARVED_SHARE = 1 / 3  # check: a class with less than this x the mean share of instances


@dataclass
class ClassCounts:
    """One category's instances, the images it appears in, and its share of all instances."""

    name: str
    instances: int
    images: int
    share: float


@dataclass
class DatasetStats:
    """What a card shows of a dataset (arrays have one value per instance, in annotation order)."""

    images: int
    instances: int
    classes: list[ClassCounts]
    visible_fraction: np.ndarray  # [M] in [0, 1] of the instances that record it (compose), else empty
    size_px: np.ndarray  # [N] square root of the mask (or box) area, pixels
    centre: np.ndarray  # [N, 2] box centre as fractions of the image width and height
    objects_per_image: Counter = field(default_factory=Counter)  # instance count -> images
    placement: Counter = field(default_factory=Counter)  # instance placement kind (compose) -> instances
    empty_images: list[str] = field(default_factory=list)  # file names of images without an instance
    bad_instances: list[str] = field(default_factory=list)  # "annotation <id> (<file>): why"


def instance_area(ann: dict) -> tuple[list[float], float]:
    """An annotation's box [x, y, w, h] and area in pixels: of its RLE mask when it has one (the box it gives too),
    else its own `area` or its box's."""
    segmentation = ann.get("segmentation")
    if isinstance(segmentation, dict):
        box, area = rle_box_and_area(segmentation)
        return box, float(area)
    box = [float(v) for v in ann["bbox"]]
    return box, float(ann.get("area") or box[2] * box[3])


def outside_image(box: list[float], width: int, height: int) -> bool:
    """Whether a box [x, y, w, h] reaches outside the image (more than half a pixel, for rounding)."""
    x, y, w, h = box
    return x < -0.5 or y < -0.5 or x + w > width + 0.5 or y + h > height + 0.5


def dataset_stats(dataset: CocoDataset) -> DatasetStats:
    """The card's numbers of `dataset`."""
    images = {image["id"]: image for image in dataset.images}
    names = {c["id"]: c["name"] for c in dataset.categories}
    by_class = Counter(ann["category_id"] for ann in dataset.annotations)
    class_images = {cid: len({a["image_id"] for a in dataset.annotations if a["category_id"] == cid}) for cid in names}
    total = len(dataset.annotations)
    classes = [ClassCounts(names[cid], by_class[cid], class_images[cid], by_class[cid] / total if total else 0.0)
               for cid in sorted(names)]
    sizes, centres, visible, bad = [], [], [], []
    for ann in dataset.annotations:
        image = images[ann["image_id"]]
        box, area = instance_area(ann)
        if area <= 0:
            bad.append(f"annotation {ann['id']} ({image['file_name']}): empty mask")
        elif outside_image(box, int(image["width"]), int(image["height"])):
            bad.append(f"annotation {ann['id']} ({image['file_name']}): box {[round(v, 1) for v in box]} outside "
                       f"the {image['width']}x{image['height']} image")
        sizes.append(np.sqrt(max(area, 0.0)))
        centres.append([(box[0] + box[2] / 2) / image["width"], (box[1] + box[3] / 2) / image["height"]])
        if "visible_fraction" in ann:
            visible.append(float(ann["visible_fraction"]))
    per_image = dataset.annotations_by_image()
    return DatasetStats(
        images=len(dataset.images), instances=total, classes=classes,
        visible_fraction=np.asarray(visible, dtype=np.float64), size_px=np.asarray(sizes, dtype=np.float64),
        centre=np.asarray(centres, dtype=np.float64).reshape(-1, 2),
        objects_per_image=Counter(len(anns) for anns in per_image.values()),
        placement=Counter(str(ann["placement"]) for ann in dataset.annotations if "placement" in ann),
        empty_images=[images[image_id]["file_name"] for image_id, anns in per_image.items() if not anns],
        bad_instances=bad)


def record_disagreements(dataset: CocoDataset, record: PlacementsRecord) -> list[str]:
    """Per image, where the annotations' classes differ from the objects the generator's record says it kept: an
    object kept but not annotated, or an annotation of an object it did not keep ("<file>: ...")."""
    names = {c["id"]: c["name"] for c in dataset.categories}
    annotated = {image["file_name"]: Counter() for image in dataset.images}
    by_id = {image["id"]: image["file_name"] for image in dataset.images}
    for ann in dataset.annotations:
        annotated[by_id[ann["image_id"]]][names[ann["category_id"]]] += 1
    found = []
    for file_name, kept in record.kept_by_image().items():
        labels = annotated.get(file_name)
        if labels is None:
            found.append(f"{file_name}: in the generator's record, not in the dataset")
            continue
        missing, extra = kept - labels, labels - kept
        if missing:
            found.append(f"{file_name}: kept but not annotated: {', '.join(sorted(missing.elements()))}")
        if extra:
            found.append(f"{file_name}: annotated but not kept: {', '.join(sorted(extra.elements()))}")
    return found


def dataset_checks(stats: DatasetStats, disagreements: list[str] = ()) -> list[str]:
    """The card's findings, one line each (empty: nothing wrong): classes under STARVED_SHARE of the mean share,
    instances with an empty mask or outside their image, images without an instance, and the generator's
    record's disagreements (record_disagreements)."""
    found = []
    mean_share = 1.0 / max(len(stats.classes), 1)
    for counts in stats.classes:
        if stats.instances and counts.share < STARVED_SHARE * mean_share:
            found.append(f"class {counts.name!r} has {counts.instances} instances, {counts.share:.1%} of all "
                         f"(under a third of the mean share, {mean_share:.1%})")
    found += [f"bad instance: {line}" for line in stats.bad_instances]
    if stats.empty_images:
        found.append(f"{len(stats.empty_images)} image{'s' if len(stats.empty_images) > 1 else ''} without an instance "
                     f"(first: {stats.empty_images[0]})")
    found += [f"record: {line}" for line in disagreements]
    return found
