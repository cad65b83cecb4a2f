"""A generated dataset in shards (stages/lib/composition/shards.py, the dataset stage, the pipeline's shard nodes): the
joined shards equal one folder, growing a dataset keeps its shards' keys, and a joined dataset's references into
its shards' inputs resolve."""
from __future__ import annotations

import filecmp
import json
from pathlib import Path

from stages.app.pipeline import build_graph, shard_settings
from stages.compose import run as compose
from stages.contract.fan_in import input_name
from stages.dataset import run as dataset_stage
from stages.engine.cache_entry import MANIFEST, input_path
from stages.engine.context import Context
from stages.engine.scheduler import Engine
from stages.records.coco_dataset import CocoDataset
from stages.records.placements import PlacementsRecord
from tests.factories.backgrounds import write_floor_scene
from tests.factories.configs import compose_cfg

ROOT = Path(__file__).resolve().parents[1]
PARAMS = {"objects": [{"name": "blob", "height_m": 0.4}], "image_size": None, "preview_count": 2, "workers": 1,
          "random_placement_share": 0.3}


def composed(inputs: dict, out: Path, first: int, count: int) -> Path:
    """compose's output of images first..first+count-1 in `out` (seed 5, item "full")."""
    out.mkdir(parents=True)
    compose.run(Context(stage="compose", item="full", params={**PARAMS, "first_image": first, "num_images": count},
                        inputs=inputs, out=out, seed=5))
    return out


def test_joined_shards_equal_one_folder(tmp_path):
    inputs = write_floor_scene(tmp_path / "scene")
    whole = composed(inputs, tmp_path / "whole", 0, 5)
    shards = {input_name("shard", "0000"): composed(inputs, tmp_path / "s0", 0, 3),
              input_name("shard", "0001"): composed(inputs, tmp_path / "s1", 3, 2)}
    joined = tmp_path / "joined"
    joined.mkdir()
    metrics = dataset_stage.run(Context(stage="dataset", item="full", params={"card_samples": 3}, inputs=shards,
                                        out=joined, seed=5))
    one, two = CocoDataset.read(whole), CocoDataset.read(joined)
    assert [image["depth"]["input"] for image in two.images if image["depth"]] == [
        f"shard:{k // 3:04d}>depth:floor" for k, image in enumerate(one.images) if image["depth"]]
    unqualified = [{**image, "depth": image["depth"] and {**image["depth"], "input": "depth:floor"}}
                   for image in two.images]
    assert (one.images, one.annotations, one.categories) == (unqualified, two.annotations, two.categories)
    assert two.info["object_models"]["blob"]["input"] == "shard:0000>object:blob"
    assert all(filecmp.cmp(CocoDataset.image_file(whole, image), CocoDataset.image_file(joined, image),
                           shallow=False) for image in one.images)
    assert PlacementsRecord.read(joined).images == PlacementsRecord.read(whole).images
    stats = json.loads((whole / "stats.json").read_text())
    assert (metrics["images"], metrics["instances"], metrics["shards"]) == (5, stats["instances"], 2)
    assert metrics["placement"] == stats["placement"] and metrics["card_checks"] == 0
    assert (joined / "card.md").is_file() and filecmp.cmp(joined / "preview.png", tmp_path / "s0" / "preview.png")


def test_a_dataset_grows_and_shrinks_by_whole_shards():
    assert [(s["first_image"], s["num_images"]) for s in shard_settings({"num_images": 1100, "shard_size": 250})] == [
        (0, 250), (250, 250), (500, 250), (750, 250), (1000, 100)]
    keys = {}
    for size in (1000, 2000, 500, 1100):
        graph = build_graph(compose_cfg([f"compose.num_images={size}"]), ROOT)
        engine = Engine(ROOT / "outputs" / "unused-cache")
        keys[size] = [engine.key(node) for node in graph.nodes["compose"]]
        assert [n.item for n in graph.nodes["dataset"]] == ["full"]
        assert sorted(graph.nodes["dataset"][0].inputs) == [input_name("shard", f"{k:04d}")
                                                            for k in range(len(keys[size]))] + ["testset"]
    assert keys[2000][:4] == keys[1000] and len(set(keys[2000])) == 8  # 1000 -> 2000 computes only 4 new shards
    assert keys[500] == keys[1000][:2] and keys[1100][:4] == keys[1000]
    assert keys[1100][4] not in keys[2000]  # a last, partial shard is a node of its own


def test_a_reference_into_a_shards_input_resolves(tmp_path):
    cache = tmp_path / "cache"
    for stage, key, inputs in (("dataset", "d1", {"shard:0000": "c1"}), ("compose", "c1", {"object:blob": "e1",
                                                                                         "depth:bg7": "b1/depth"})):
        (cache / stage / key).mkdir(parents=True)
        (cache / stage / key / MANIFEST).write_text(json.dumps({"inputs": inputs}))
    (cache / "extract" / "e1").mkdir(parents=True)
    (cache / "bg_depth" / "b1" / "depth").mkdir(parents=True)
    entry = cache / "dataset" / "d1"
    assert input_path(entry, "shard:0000>object:blob") == cache / "extract" / "e1"
    assert input_path(entry, "shard:0000>depth:bg7") == cache / "bg_depth" / "b1" / "depth"
    assert input_path(entry, "shard:0000") == cache / "compose" / "c1"
    assert input_path(entry, "shard:0001>object:blob") is None and input_path(entry, "shard:0000>object:x") is None
