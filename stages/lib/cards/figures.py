"""The figures of a dataset card: the histograms (beside a test set's when one is given) and a grid of example
images with every instance outlined, boxed and named in its class colour."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from stages.lib.cards.stats import DatasetStats, instance_area
from stages.lib.coco import segmentation_mask
from stages.lib.composition.preview import PALETTE, outline_masks, preview_grid
from stages.records.coco_dataset import CocoDataset

SIZE_BINS = np.geomspace(4, 1024, 25)  # square root of the instance area, pixels


def _histogram(axis, values: np.ndarray, bins, label: str, colour: str) -> None:
    """Draw a density histogram of `values` [M] (nothing when empty) on a matplotlib axis."""
    if len(values):
        axis.hist(values, bins=bins, density=True, alpha=0.55, color=colour, label=f"{label} ({len(values)})")


def write_histograms(path: Path, stats: DatasetStats, compare: DatasetStats | None = None,
                     names: tuple[str, str] = ("dataset", "test set")) -> None:
    """A PNG of six panels: instances per class (share), visible fraction, size, box centre x and y, instances
    per image; with `compare`, its histograms drawn over the dataset's (densities, so sizes differ)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(2, 3, figsize=(13, 7))
    sets = [(stats, names[0], "tab:blue")] + ([(compare, names[1], "tab:orange")] if compare is not None else [])
    classes = [c.name for c in stats.classes]
    for k, (found, label, colour) in enumerate(sets):
        shares = {c.name: c.share for c in found.classes}
        positions = np.arange(len(classes)) + (k - 0.5 * (len(sets) - 1)) * 0.38
        axes[0, 0].bar(positions, [shares.get(name, 0.0) for name in classes], width=0.38, color=colour, label=label)
        _histogram(axes[0, 1], found.visible_fraction, np.linspace(0, 1, 21), label, colour)
        _histogram(axes[0, 2], found.size_px, SIZE_BINS, label, colour)
        _histogram(axes[1, 0], found.centre[:, 0], np.linspace(0, 1, 21), label, colour)
        _histogram(axes[1, 1], found.centre[:, 1], np.linspace(0, 1, 21), label, colour)
        counts = sorted(found.objects_per_image)
        total = max(sum(found.objects_per_image.values()), 1)
        axes[1, 2].bar(np.asarray(counts) + (k - 0.5 * (len(sets) - 1)) * 0.38,
                       [found.objects_per_image[c] / total for c in counts], width=0.38, color=colour, label=label)
    axes[0, 0].set_xticks(np.arange(len(classes)), classes, rotation=30, ha="right")
    axes[0, 2].set_xscale("log")
    titles = ["share of instances per class", "visible fraction", "size (sqrt of mask area, px)",
              "box centre x (fraction of width)", "box centre y (fraction of height)", "instances per image"]
    for axis, title in zip(axes.ravel(), titles):
        axis.set_title(title, fontsize=10)
        if axis.get_legend_handles_labels()[0]:
            axis.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=80)
    plt.close(figure)


def labelled_image(image: np.ndarray, annotations: list[dict], names: dict[int, str]) -> np.ndarray:
    """image [H, W, 3] uint8 RGB with each annotation's mask outlined, its box drawn and its class named, in the
    class colour."""
    height, width = image.shape[:2]
    masks = [segmentation_mask(a["segmentation"], height, width) if a.get("segmentation") else
             np.zeros((height, width), bool) for a in annotations]
    canvas = outline_masks(image, masks, [a["category_id"] for a in annotations])
    for ann in annotations:
        colour = PALETTE[(ann["category_id"] - 1) % len(PALETTE)]
        x, y, w, h = (int(round(v)) for v in instance_area(ann)[0])
        cv2.rectangle(canvas, (x, y), (x + w, y + h), colour, 1)
        label = names.get(ann["category_id"], str(ann["category_id"]))
        (text_w, text_h), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, 0.45, 1)
        top = max(0, y - text_h - 4)
        cv2.rectangle(canvas, (x, top), (x + text_w + 4, top + text_h + 4), colour, -1)
        cv2.putText(canvas, label, (x + 2, top + text_h + 1), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1,
                    cv2.LINE_AA)
    return canvas


def write_examples(path: Path, folder: Path, dataset: CocoDataset, count: int, seed: int) -> list[str]:
    """A JPEG grid of `count` images of the dataset in `folder` drawn at random (seeded), each labelled
    (labelled_image); returns their file names."""
    if not dataset.images:
        return []
    rng = np.random.default_rng(seed)
    chosen = sorted(rng.choice(len(dataset.images), size=min(count, len(dataset.images)), replace=False))
    names = {c["id"]: c["name"] for c in dataset.categories}
    by_image = dataset.annotations_by_image()
    tiles = []
    for index in chosen:
        image = dataset.images[index]
        pixels = cv2.cvtColor(cv2.imread(str(CocoDataset.image_file(folder, image))), cv2.COLOR_BGR2RGB)
        tiles.append(labelled_image(pixels, by_image[image["id"]], names))
    cv2.imwrite(str(path), cv2.cvtColor(preview_grid(tiles, tile_width=400), cv2.COLOR_RGB2BGR),
                [cv2.IMWRITE_JPEG_QUALITY, 85])
    return [dataset.images[index]["file_name"] for index in chosen]
