"""Generating a dataset image by image (one seed per image index, optional process pool) and
writing it as a COCO dataset folder (stages/records/coco_dataset.py): images/%06d.jpg (file_name relative to
images/), annotations.json, and beside them stats.json, preview.png and, when the generator says per image which
objects it placed and kept (`info["objects"]`), placements.json (stages/records/placements.py).

A generator is a pair of module-level functions: `setup(*args) -> state` (loads the assets once
per process) and `make(state, index, images_dir) -> ComposedImage` (writes the image file). Each
image uses its own numpy Generator seeded by (seed, index), and every process runs torch with one
thread, so the files do not depend on the number of workers.
"""
from __future__ import annotations

import json
import logging
import os
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator

import cv2
import numpy as np
import torch

from stages.contract.errors import StageError
from stages.lib.coco import CocoBuilder
from stages.lib.composition.preview import write_preview
from stages.lib.processes import spawn_pool
from stages.records.coco_dataset import CocoDataset
from stages.records.placements import PlacementsRecord

log = logging.getLogger(__name__)

JPEG_QUALITY = 95
IMAGES_PER_AUTO_WORKER = 100  # workers=0 starts no process for fewer images than this
_WORKER: dict[str, Any] = {}


@dataclass
class Instance:
    """One annotated object of a composed image."""

    category_id: int
    mask: np.ndarray  # [H, W] bool, the visible part
    extra: dict[str, Any] = field(default_factory=dict)  # stored in the COCO annotation


@dataclass
class ComposedImage:
    """What one generated image contributes to the dataset."""

    file_name: str
    width: int
    height: int
    instances: list[Instance]
    info: dict[str, Any]  # per-image facts for stats.json (placement kind, fallback reason, drops) and the
    #                       record of what was placed ("objects": [{"object", "kept", "why"}], placements.json)
    fields: dict[str, Any] = field(default_factory=dict)  # stored in the COCO image entry (compose: K, depth)


def image_rng(seed: int, index: int, *stream: int) -> np.random.Generator:
    """The random generator of image `index` (independent of workers and shards); `stream` names another
    independent generator of the same image (e.g. compose's light)."""
    return np.random.default_rng([int(seed), int(index), *map(int, stream)])


def write_jpeg(path: Path, image: np.ndarray) -> None:
    """Write a float32 [H, W, 3] RGB image in [0, 1] as JPEG."""
    pixels = cv2.convertScaleAbs(image, alpha=255.0)  # rounds and saturates to uint8 in one pass
    if not cv2.imwrite(str(path), cv2.cvtColor(pixels, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY]):
        raise StageError(f"cannot write image {path} (does its folder exist? is the disk full?)")


def _worker_init(setup: Callable, setup_args: tuple, make: Callable, images_dir: Path) -> None:
    torch.set_num_threads(1)
    _WORKER.update(state=setup(*setup_args), make=make, images_dir=images_dir)


def _worker_make(index: int) -> ComposedImage:
    return _WORKER["make"](_WORKER["state"], index, _WORKER["images_dir"])


def image_processes(workers: int, count: int, cores: int) -> int:
    """Processes that make `count` images: `workers`, or for 0 one per core but at least
    IMAGES_PER_AUTO_WORKER images each (a process costs seconds to start)."""
    return workers if workers > 0 else min(cores, max(1, count // IMAGES_PER_AUTO_WORKER))


def generate(setup: Callable, setup_args: tuple, make: Callable, count: int, images_dir: Path,
             workers: int, first: int = 0) -> Iterator[ComposedImage]:
    """Yield the composed images first..first+count-1 in index order (a shard of a dataset: each image depends on
    its index only), made in `workers` processes (1 = here, 0 = image_processes' choice for the cores this process
    may use: torch's thread count, which the engine sets to a node's share)."""
    images_dir.mkdir(parents=True, exist_ok=True)
    indices = range(first, first + count)
    workers = image_processes(workers, count, torch.get_num_threads())
    if workers <= 1:
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            state = setup(*setup_args)
            for index in indices:
                yield make(state, index, images_dir)
        finally:
            torch.set_num_threads(threads)
        return
    with spawn_pool(workers, _worker_init, (setup, setup_args, make, images_dir)) as pool:
        yield from pool.map(_worker_make, indices, chunksize=max(1, min(16, count // (4 * workers))))


def write_dataset(out: Path, categories: list[str], images: Iterator[ComposedImage], count: int,
                  progress: Callable, preview_count: int = 16, info: dict | None = None,
                  extra_stats: dict | None = None) -> dict:
    """Collect generated images into out/annotations.json, out/stats.json and out/preview.png.

    Returns the stats dict (images/s, objects per image, placement kinds, fallback reasons, drops, and the
    generator's `extra_stats`, e.g. what it left out).
    """
    builder = CocoBuilder(categories, info=info)
    start = time.perf_counter()
    per_image_objects, kinds, fallbacks, drops = [], Counter(), Counter(), Counter()
    placed: dict[str, list[dict]] = {}
    preview_images, preview_masks, preview_categories = [], [], []
    for item in progress(images, total=count):
        image_id = builder.add_image(item.file_name, item.width, item.height, **item.fields)
        for inst in item.instances:
            builder.add_instance(image_id, inst.category_id, inst.mask, **inst.extra)
        per_image_objects.append(len(item.instances))
        kinds[item.info.get("placement", "unknown")] += 1
        if item.info.get("fallback"):
            fallbacks[item.info["fallback"]] += 1
        drops.update(item.info.get("dropped", {}))
        if "objects" in item.info:
            placed[item.file_name] = item.info["objects"]
        if len(preview_images) < preview_count:
            rgb = cv2.cvtColor(cv2.imread(str(CocoDataset.image_file(out, builder.dataset.images[-1]))),
                               cv2.COLOR_BGR2RGB)
            preview_images.append(rgb)
            preview_masks.append([inst.mask for inst in item.instances])
            preview_categories.append([inst.category_id for inst in item.instances])
    seconds = time.perf_counter() - start
    builder.dataset.write(out)
    if placed:
        PlacementsRecord(placed).write(out)
    write_preview(out / "preview.png", preview_images, preview_masks, preview_categories)
    objects = np.asarray(per_image_objects, dtype=np.float64)
    stats = {
        "images": count, "seconds": round(seconds, 3), "images_per_s": round(count / max(seconds, 1e-9), 3),
        "instances": int(objects.sum()), "objects_per_image": round(float(objects.mean()), 3) if count else 0.0,
        "objects_per_image_histogram": {str(k): int(v) for k, v in sorted(Counter(per_image_objects).items())},
        "images_without_objects": int((objects == 0).sum()),
        "placement": dict(kinds), "random_placement_fallbacks": dict(fallbacks), "dropped_instances": dict(drops),
        **(extra_stats or {}),
    }
    (out / "stats.json").write_text(json.dumps(stats, indent=2))
    log.info("wrote %d images (%.2f images/s, %.2f objects/image)", count, stats["images_per_s"],
             stats["objects_per_image"])
    return stats
