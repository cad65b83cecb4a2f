"""Dataset cards (stages/lib/cards/, `python -m stages.app.dataset_card`): their counts are pycocotools' counts, and
each check fires on a dataset made to trip it."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from stages.lib.cards.page import CARD, EXAMPLES, HISTOGRAMS, write_card
from stages.lib.cards.stats import dataset_checks, dataset_stats, record_disagreements
from stages.lib.coco import load_coco, mask_to_rle
from stages.records.coco_dataset import CocoDataset
from stages.records.placements import PlacementsRecord
from tests.factories.shapes import SHAPE_NAMES, write_shapes_dataset

ROOT = Path(__file__).resolve().parents[1]


def edited(folder: Path, edit) -> Path:
    """The dataset in `folder` with its annotations.json changed by edit(dict) in place; returns the folder."""
    path = folder / CocoDataset.JSON
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))
    return folder


def test_the_card_counts_are_pycocotools_counts(tmp_path):
    folder = write_shapes_dataset(tmp_path / "shapes", 30, seed=3)
    coco = load_coco(folder)
    stats = dataset_stats(CocoDataset.read(folder))
    for counts in stats.classes:
        [cat_id] = coco.getCatIds(catNms=[counts.name])
        assert counts.instances == len(coco.getAnnIds(catIds=[cat_id]))
        assert counts.images == len(coco.getImgIds(catIds=[cat_id]))
    assert stats.instances == len(coco.getAnnIds()) and stats.images == len(coco.getImgIds())
    assert sum(c.share for c in stats.classes) == pytest.approx(1.0)
    assert sum(k * v for k, v in stats.objects_per_image.items()) == stats.instances
    areas = np.array([a["area"] for a in coco.loadAnns(coco.getAnnIds())])
    assert np.allclose(np.sort(stats.size_px), np.sort(np.sqrt(areas)))
    assert ((stats.centre >= 0) & (stats.centre <= 1)).all() and dataset_checks(stats) == []


def test_each_check_fires_on_a_dataset_made_to_trip_it(tmp_path):
    def starve(data):  # keep one red box only
        boxes = [a for a in data["annotations"] if a["category_id"] == 1]
        data["annotations"] = [a for a in data["annotations"] if a["category_id"] == 2] + boxes[:1]

    checks = dataset_checks(dataset_stats(CocoDataset.read(edited(write_shapes_dataset(tmp_path / "a", 20), starve))))
    assert any(line.startswith(f"class '{SHAPE_NAMES[0]}' has 1 instances") for line in checks), checks
    assert any("images without an instance" in line for line in checks)

    def break_two(data):  # one empty mask, one box reaching out of the image
        data["annotations"][0]["segmentation"] = mask_to_rle(np.zeros((96, 96), bool))
        data["annotations"][1]["segmentation"] = None
        data["annotations"][1]["bbox"] = [80.0, 10.0, 40.0, 20.0]

    checks = dataset_checks(dataset_stats(CocoDataset.read(edited(write_shapes_dataset(tmp_path / "b", 8), break_two))))
    assert any("annotation 1 (0000.png): empty mask" in line for line in checks), checks
    assert any("annotation 2 (" in line and "outside the 96x96 image" in line for line in checks), checks


def test_an_annotation_the_generator_kept_must_exist(tmp_path):
    folder = write_shapes_dataset(tmp_path / "kept", 6)
    dataset = CocoDataset.read(folder)
    names = {c["id"]: c["name"] for c in dataset.categories}
    files = {image["id"]: image["file_name"] for image in dataset.images}
    placed = {image["file_name"]: [] for image in dataset.images}
    for ann in dataset.annotations:
        placed[files[ann["image_id"]]].append({"object": names[ann["category_id"]], "kept": True, "why": ""})
    placed[files[1]].append({"object": "blue_disc", "kept": False, "why": "hidden_by_objects"})
    PlacementsRecord(placed).write(folder)
    assert record_disagreements(dataset, PlacementsRecord.read(folder)) == []
    deleted = dataset.annotations.pop(0)
    found = record_disagreements(dataset, PlacementsRecord.read(folder))
    assert found == [f"{files[deleted['image_id']]}: kept but not annotated: {names[deleted['category_id']]}"]
    assert write_card(folder).checks == []  # the files on disk still agree
    titled = write_card(folder, tmp_path / "titled", title="dataset[full]").path.read_text()
    assert titled.startswith("# Dataset card: dataset[full]") and str(folder) not in titled  # no temporary folder
    edited(folder, lambda data: data["annotations"].pop(0))
    assert any(line.startswith("record: ") for line in write_card(folder).checks)


def test_the_command_writes_a_card_beside_a_test_set(tmp_path):
    train = write_shapes_dataset(tmp_path / "train", 12, seed=1)
    test = write_shapes_dataset(tmp_path / "test", 5, seed=2)
    done = subprocess.run([sys.executable, "-m", "stages.app.dataset_card", str(train), "--compare", str(test), "--out",
                           str(tmp_path / "card"), "--samples", "4"], cwd=ROOT, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == f"card: {tmp_path / 'card' / CARD}"
    page = (tmp_path / "card" / CARD).read_text()
    assert "| class | instances | images | share | test instances | test share |" in page
    assert all((tmp_path / "card" / name).stat().st_size > 1000 for name in (HISTOGRAMS, EXAMPLES))
    edited(train, lambda data: data["annotations"].clear())
    done = subprocess.run([sys.executable, "-m", "stages.app.dataset_card", str(train)], cwd=ROOT, capture_output=True,
                          text=True)
    assert done.returncode == 1 and "check: 12 images without an instance" in done.stdout
    done = subprocess.run([sys.executable, "-m", "stages.app.dataset_card", str(tmp_path / "nowhere")], cwd=ROOT,
                          capture_output=True, text=True)
    assert done.returncode == 2 and "annotations.json" in done.stderr
