"""benchmarks/class_gap.py: on the whole test set the gap is the eval stage's, the draws spread around it only
where the classes' masks differ from image to image, and a mask that is slightly off loses AP at the strict IoU
thresholds only."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from benchmarks.class_gap import ap_by_iou, evaluate_masks, gap_on_draw, resampled_gaps
from stages.eval.run import coco_metrics
from stages.lib.coco import load_coco, mask_to_rle, rle_to_mask
from tests.factories.shapes import write_shapes_dataset


@pytest.fixture(scope="module")
def testset(tmp_path_factory):
    return load_coco(write_shapes_dataset(tmp_path_factory.mktemp("test"), 12, size=96, seed=3))


def predictions(coco, spoiled_discs: int) -> list[dict]:
    """The true objects as predictions, the masks of the first `spoiled_discs` blue discs a 2x2 speck."""
    results, spoiled = [], 0
    for a in coco.dataset["annotations"]:
        segmentation = a["segmentation"]
        if coco.cats[a["category_id"]]["name"] == "blue_disc" and spoiled < spoiled_discs:
            speck = np.zeros((96, 96), bool)
            speck[int(a["bbox"][1]):int(a["bbox"][1]) + 2, int(a["bbox"][0]):int(a["bbox"][0]) + 2] = True
            segmentation, spoiled = mask_to_rle(speck), spoiled + 1
        results.append({"image_id": a["image_id"], "category_id": a["category_id"], "bbox": a["bbox"],
                        "segmentation": segmentation, "score": 1.0})
    return results


def test_the_whole_test_set_gives_the_eval_stages_gap(testset):
    results = predictions(testset, spoiled_discs=3)
    per_class = coco_metrics(testset, results, testset.getImgIds())["segm"]["per_class"]
    evaluator = evaluate_masks(testset, results)
    whole = gap_on_draw(evaluator, np.arange(len(testset.getImgIds())), "blue_disc")
    assert whole == pytest.approx(per_class["red_box"] - per_class["blue_disc"])
    assert whole > 10


def test_draws_spread_only_where_the_masks_differ_between_images(testset):
    perfect = evaluate_masks(testset, predictions(testset, spoiled_discs=0))
    partly = evaluate_masks(testset, predictions(testset, spoiled_discs=3))
    whole, drawn = resampled_gaps([perfect, partly], "blue_disc", draws=40, seed=0)
    assert whole[0] == pytest.approx(0.0) and np.allclose(drawn[:, 0], 0.0)
    assert drawn.shape == (40, 2) and drawn[:, 1].std() > 1.0
    assert drawn[:, 1].min() < whole[1] < drawn[:, 1].max()


def test_a_slightly_eroded_mask_loses_only_at_the_strict_thresholds(testset):
    results = predictions(testset, spoiled_discs=0)
    for r in results:  # every red box's mask loses its outermost ring of pixels
        if testset.cats[r["category_id"]]["name"] == "red_box":
            mask = rle_to_mask(r["segmentation"]).astype(np.uint8)
            r["segmentation"] = mask_to_rle(cv2.erode(mask, np.ones((3, 3), np.uint8)).astype(bool))
    table = ap_by_iou(evaluate_masks(testset, results))
    assert table["blue_disc"] == pytest.approx([100.0] * 10)
    assert table["red_box"][0] == pytest.approx(100.0) and table["red_box"][-1] < 50.0
    assert table["red_box"] == sorted(table["red_box"], reverse=True)
