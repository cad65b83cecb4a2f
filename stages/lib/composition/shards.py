"""A generated dataset made of shards (compose or cut_and_paste outputs, each images first..first+n-1 of the
dataset, in index order) joined into one COCO dataset folder: the images linked, not copied, the ids numbered as
one generator writing them all would have numbered them, the statistics and the placement records joined.

The inputs a shard's annotations name (compose's `object_models[...]["input"]` and each image's
`depth["input"]`, names of the shard's own inputs) are qualified with the shard's input name, `shard:0003>depth:bg7`,
which stages/engine/cache_entry.py `input_path` follows through both manifests.
"""
from __future__ import annotations

import json
import os
import shutil
from collections import Counter
from pathlib import Path

from stages.contract.errors import StageError
from stages.records.coco_dataset import CocoDataset
from stages.records.placements import PlacementsRecord

STATS = "stats.json"
PREVIEW = "preview.png"
INPUT_SEPARATOR = ">"  # "<input of this node>><input of that node>"
SUMMED = ("images", "instances", "seconds", "images_without_objects")  # stats.json counts added over shards
COUNTERS = ("objects_per_image_histogram", "placement", "random_placement_fallbacks", "dropped_instances")


def link_or_copy(source: Path, target: Path) -> None:
    """A hard link of `source` at `target`, or a copy where the file system cannot link (another device)."""
    try:
        os.link(source, target)
    except OSError:
        shutil.copy2(source, target)


def qualified(shard: str, value: dict | None) -> dict | None:
    """A copy of a {"input": name, ...} reference with the name qualified by the shard's input name."""
    if not value or "input" not in value:
        return value
    return {**value, "input": f"{shard}{INPUT_SEPARATOR}{value['input']}"}


def join_shards(shards: dict[str, Path], out: Path) -> CocoDataset:
    """The COCO dataset of `shards` ({input name: shard folder}, in index order), written into `out`: images/
    hard-linked, image and annotation ids 1..n in order, the first shard's categories and info (its inputs
    qualified). StageError naming the shard whose categories differ or whose file names repeat another's."""
    images_dir = out / CocoDataset.IMAGES
    images_dir.mkdir(parents=True, exist_ok=True)
    joined: CocoDataset | None = None
    seen: set[str] = set()
    for name, folder in shards.items():
        shard = CocoDataset.read(folder)
        if joined is None:
            models = {obj: qualified(name, model) for obj, model in shard.info.get("object_models", {}).items()}
            info = {**shard.info, **({"object_models": models} if models else {})}
            joined = CocoDataset([], [], shard.categories, info, shard.licenses)
        elif shard.categories != joined.categories:
            raise StageError(f"{folder}: its categories differ from the first shard's ({joined.category_names})")
        image_ids = {}
        for image in shard.images:
            if image["file_name"] in seen:
                raise StageError(f"{folder}: image {image['file_name']} is also in an earlier shard")
            seen.add(image["file_name"])
            link_or_copy(CocoDataset.image_file(folder, image), images_dir / image["file_name"])
            image_ids[image["id"]] = len(joined.images) + 1
            fields = {"depth": qualified(name, image["depth"])} if "depth" in image else {}
            joined.images.append({**image, "id": image_ids[image["id"]], **fields})
        for ann in shard.annotations:
            joined.annotations.append({**ann, "id": len(joined.annotations) + 1, "image_id": image_ids[ann["image_id"]]})
    if joined is None:
        raise StageError("a dataset needs at least one shard")
    joined.write(out)
    return joined


def join_stats(shards: dict[str, Path]) -> dict:
    """The shards' stats.json joined: counts and histograms added, images per second over the summed seconds,
    objects per image over all images, the rest (photos and objects left out, ...) as the first shard gives it."""
    stats = [json.loads((folder / STATS).read_text()) for folder in shards.values() if (folder / STATS).is_file()]
    if not stats:
        return {}
    joined = dict(stats[0])
    for key in SUMMED:
        if key in joined:
            joined[key] = sum(s.get(key, 0) for s in stats)
    for key in COUNTERS:
        if key in joined:
            total = Counter()
            for s in stats:
                total.update(s.get(key) or {})
            joined[key] = dict(sorted(total.items()))
    joined["seconds"] = round(joined.get("seconds", 0.0), 3)
    joined["images_per_s"] = round(joined.get("images", 0) / max(joined.get("seconds", 0.0), 1e-9), 3)
    joined["objects_per_image"] = round(joined.get("instances", 0) / max(joined.get("images", 0), 1), 3)
    joined["shards"] = len(shards)
    return joined


def join_placements(shards: dict[str, Path]) -> PlacementsRecord | None:
    """The shards' placements.json joined (None when no shard has one)."""
    records = [PlacementsRecord.read(folder) for folder in shards.values()]
    if not any(records):
        return None
    return PlacementsRecord({name: objects for record in records if record for name, objects in record.images.items()})
