"""The rendered-training benchmark (benchmarks/rendered_training.py): its dataset is a valid COCO training set drawn
by the sample's renderer, repeatable; its gap table measures one class against the others' mean, its overlays
colour truth against prediction and its neighbour table measures masks that take in a touching object."""
from __future__ import annotations

import json

import numpy as np
import pytest

from benchmarks.rendered_training import class_gaps, gaps_table, neighbour_leaks, overlay_row, render_dataset
from stages.lib.coco import CocoBuilder, load_coco, mask_to_rle, rle_to_mask
from stages.sample.spec import SampleConfig
from tests.factories.media import write_image


@pytest.fixture()
def sample_folder(tmp_path):
    """A sample entry's sample.json at a small image size (the renderer needs nothing else from the folder)."""
    folder = tmp_path / "sample"
    folder.mkdir()
    config = {**SampleConfig().__dict__, "width": 128, "height": 96, "supersample": 1}
    (folder / "sample.json").write_text(json.dumps({"config": config}))
    return folder


def test_the_rendered_dataset_is_a_coco_training_set_and_repeats(sample_folder, tmp_path):
    counts = render_dataset(sample_folder, tmp_path / "a", images=3, workers=1)
    assert counts["images"] == 3 and counts["instances"] == sum(counts["per_class"].values()) >= 3
    coco = load_coco(tmp_path / "a" / "annotations.json")
    assert [c["name"] for c in coco.dataset["categories"]] == ["bottle", "eyedrops", "plant", "soda_can", "vase"]
    for ann in coco.dataset["annotations"]:
        mask = rle_to_mask(ann["segmentation"])
        assert mask.shape == (96, 128) and mask.sum() == ann["area"] > 0
    classes_per_image = {image_id: [a["category_id"] for a in coco.imgToAnns[image_id]] for image_id in coco.imgs}
    assert len(classes_per_image) == 3  # every image shows 1-3 objects, each of another class
    assert all(1 <= len(found) <= 3 and len(set(found)) == len(found) for found in classes_per_image.values())
    assert all((tmp_path / "a" / "images" / image["file_name"]).is_file() for image in coco.imgs.values())
    render_dataset(sample_folder, tmp_path / "b", images=3, workers=1)
    for name in ("0000.png", "0002.png"):
        assert (tmp_path / "a" / "images" / name).read_bytes() == (tmp_path / "b" / "images" / name).read_bytes()
    assert (tmp_path / "a" / "annotations.json").read_bytes() == (tmp_path / "b" / "annotations.json").read_bytes()


def row(seed: int, plant: float, others: list[float]) -> dict:
    """One benchmarks.detector runs row with mask AP per class on test_a."""
    per_class = dict(zip(["bottle", "eyedrops", "soda_can", "vase"], others), plant=plant)
    return {"name": "default", "seed": seed,
            "test_a": {"box_AP": 60.0, "mask_AP": float(np.mean([plant, *others])), "mask_per_class": per_class}}


def test_the_gap_is_the_others_mean_minus_the_class():
    rows = [row(0, 30.0, [60.0, 62.0, 58.0, 60.0]), row(1, 40.0, [64.0, 66.0, 62.0, 64.0])]
    gaps = class_gaps(rows, "test_a", "plant")
    assert gaps["cls"] == [30.0, 40.0] and gaps["others"] == [60.0, 64.0] and gaps["seeds"] == [0, 1]
    table = gaps_table({"rendered": rows}, "plant")
    assert "| rendered | default | test_a | 2 | 35.0 ± 7.1 | 62.0 | **27.0** |" in table


def test_an_overlay_colours_truth_against_prediction():
    image = np.full((60, 80, 3), 128, np.uint8)
    truth = np.zeros((60, 80), bool)
    truth[20:40, 20:40] = True
    shifted = np.roll(truth, 10, axis=1)  # half of it right, half of it beside the truth
    row = overlay_row(image, truth, [shifted, None], [20, 20, 20, 20], height=100)
    assert row.shape[0] == 100 and row.shape[1] > 2.9 * 100  # the crop and two overlays, side by side
    third = row.shape[1] // 3
    compared, missing = row[:, third:2 * third], row[:, 2 * third:]
    colours = {tuple(c) for c in compared.reshape(-1, 3)}
    assert {(0, 200, 0), (230, 0, 0), (0, 90, 255)} <= colours  # both, truth only, prediction only
    assert (0, 200, 0) not in {tuple(c) for c in missing.reshape(-1, 3)}  # no prediction: all truth is missed


def test_a_mask_that_takes_in_its_neighbour_leaks(tmp_path):
    """Two touching objects and one alone: the touching plant's predicted mask covers a quarter of the vase."""
    builder = CocoBuilder(["plant", "vase"])
    image = builder.add_image("0000.png", 60, 40)
    plant, vase, lone = (np.zeros((40, 60), bool) for _ in range(3))
    plant[5:25, 5:20], vase[5:25, 20:30], lone[30:38, 45:55] = True, True, True
    for category, mask in ((1, plant), (2, vase), (2, lone)):
        builder.add_instance(image, category, mask)
    (tmp_path / "test" / "images").mkdir(parents=True)
    write_image(tmp_path / "test" / "images" / "0000.png", np.zeros((40, 60, 3), np.uint8))
    builder.dataset.write(tmp_path / "test")
    predicted = plant.copy()
    predicted[5:25, 20:25] = True  # half of the vase's width: 100 of its 400 pixels
    results = [{"image_id": image, "category_id": 1, "score": 0.9, "segmentation": mask_to_rle(predicted)},
               {"image_id": image, "category_id": 2, "score": 0.9, "segmentation": mask_to_rle(lone)}]
    (tmp_path / "eval").mkdir()
    (tmp_path / "eval" / "predictions.json").write_text(json.dumps(results))
    table = neighbour_leaks(tmp_path / "test", tmp_path / "eval")
    assert table["plant"]["touching"] == {"instances": 1, "iou": 0.75, "leak": 0.25}
    assert table["vase"]["alone"] == {"instances": 1, "iou": 1.0, "leak": 0.0}
    assert table["vase"]["touching"]["iou"] == 0.0  # no vase predicted over the touching vase
