"""Tests of the eval stage: real COCOeval, real (tiny) detectors."""
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from benchmarks.inference_size import box_ap_by_size
from benchmarks.mask_refinement import mask_ap_by_setting
from stages.engine.context import Context
from stages.lib.coco import load_coco, mask_to_rle
from stages.lib.detection.model import build_maskrcnn, load_detector, save_detector
from stages.lib.detection.model_config import ModelConfig
from tests.factories.shapes import SHAPE_NAMES, write_shapes_dataset
from stages.contract.errors import StageError
from stages.eval.run import category_mapping, coco_metrics, predict, run, to_coco_results

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


@pytest.fixture(scope="module")
def testset(tmp_path_factory) -> Path:
    return write_shapes_dataset(tmp_path_factory.mktemp("test"), 6, size=96, seed=1)


def model_folder(folder: Path, names: list[str]) -> Path:
    """An untrained (randomly initialised) detector saved as a train_maskrcnn output."""
    folder.mkdir(parents=True, exist_ok=True)
    cfg = ModelConfig(pretrained=False, image_size=96, box_score_thresh=0.0)
    torch.manual_seed(0)
    save_detector(folder / "model.pt", build_maskrcnn(cfg, len(names)), cfg, names)
    return folder


def evaluate(model: Path, testset: Path, out: Path, params: dict | None = None) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    return run(Context("eval", "test", {"threads": 1, **(params or {})}, {"model": model, "testset": testset}, out))


def test_ground_truth_as_predictions_scores_100(testset):
    coco = load_coco(testset / "annotations.json")
    results = [{"image_id": a["image_id"], "category_id": a["category_id"], "bbox": a["bbox"],
                "segmentation": a["segmentation"], "score": 1.0} for a in coco.dataset["annotations"]]
    metrics = coco_metrics(coco, results, coco.getImgIds())
    for iou_type in ("bbox", "segm"):
        assert metrics[iou_type]["AP"] == pytest.approx(100.0)
        assert metrics[iou_type]["AP50"] == pytest.approx(100.0)
        assert metrics[iou_type]["per_class"] == pytest.approx({name: 100.0 for name in SHAPE_NAMES})


def test_shifted_boxes_score_below_100(testset):
    coco = load_coco(testset / "annotations.json")
    results = [{"image_id": a["image_id"], "category_id": a["category_id"], "score": 1.0,
                "bbox": [a["bbox"][0] + a["bbox"][2] * 0.3, *a["bbox"][1:]], "segmentation": a["segmentation"]}
               for a in coco.dataset["annotations"]]
    metrics = coco_metrics(coco, results, coco.getImgIds())
    assert metrics["bbox"]["AP"] < 60 and metrics["segm"]["AP"] == pytest.approx(100.0)


def test_mask_score_ranks_the_masks_and_the_box_score_the_boxes(testset):
    coco = load_coco(testset / "annotations.json")
    results = []
    for a in coco.dataset["annotations"]:  # per object: a crisp mask and a wrong one, both on the true box
        x, y = int(a["bbox"][0]), int(a["bbox"][1])
        speck = np.zeros((96, 96), bool)
        speck[y:y + 2, x:x + 2] = True
        common = {"image_id": a["image_id"], "category_id": a["category_id"], "bbox": a["bbox"]}
        results += [{**common, "segmentation": a["segmentation"], "score": 0.5, "mask_score": 0.9},
                    {**common, "segmentation": mask_to_rle(speck), "score": 0.9, "mask_score": 0.5}]
    by_mask_score = coco_metrics(coco, results, coco.getImgIds())
    by_box_score = coco_metrics(coco, [{k: v for k, v in r.items() if k != "mask_score"} for r in results],
                                coco.getImgIds())
    assert by_mask_score["segm"]["AP"] == pytest.approx(100.0) and by_box_score["segm"]["AP"] < 60
    assert by_mask_score["bbox"]["AP"] == by_box_score["bbox"]["AP"] == pytest.approx(100.0)


def test_maskness_is_the_mean_probability_inside_the_mask(testset, tmp_path):
    model, _, _ = load_detector(model_folder(tmp_path / "model", SHAPE_NAMES) / "model.pt")
    image = np.asarray(Image.open(next((testset / "images").iterdir())).convert("RGB"))
    detections = predict(model, image, "cpu", 0.5)
    with torch.no_grad():
        probability = model([torch.from_numpy(image.copy()).permute(2, 0, 1).float() / 255])[0]["masks"][:, 0].numpy()
    assert len(detections["scores"]) > 0
    for p, mask, maskness in zip(probability, detections["masks"], detections["maskness"]):
        assert maskness == pytest.approx(p[mask].mean() if mask.any() else 0.0, rel=1e-5)
    records = to_coco_results(1, detections, {1: 1, 2: 2}, "maskness")
    assert [r["mask_score"] for r in records] == pytest.approx(list(detections["scores"] * detections["maskness"]))
    assert all(r["mask_score"] == r["score"] for r in to_coco_results(1, detections, {1: 1, 2: 2}, "box"))


def test_categories_match_by_name_not_id(testset):
    coco = load_coco(testset / "annotations.json")  # ids: red_box 1, blue_disc 2
    assert category_mapping(["blue_disc", "red_box", "green_cone"], coco, "test") == {1: 2, 2: 1}
    with pytest.raises(ValueError, match="blue_disc"):
        category_mapping(["red_box"], coco, "test")


def test_run_writes_metrics_predictions_and_preview(testset, tmp_path):
    model = model_folder(tmp_path / "model", list(reversed(SHAPE_NAMES)))
    saved = evaluate(model, testset, tmp_path / "eval")  # the engine writes them as metrics.json
    assert not (tmp_path / "eval" / "metrics.json").exists()
    assert set(saved["bbox"]) == {"AP", "AP50", "AP75", "per_class"} and set(saved["segm"]["per_class"]) == set(SHAPE_NAMES)
    assert saved["images"] == 6 and saved["inference_seconds_per_image"] > 0
    predictions = json.loads((tmp_path / "eval" / "predictions.json").read_text())
    assert len(predictions) == saved["detections"] > 0
    coco = load_coco(testset / "annotations.json")
    coco.loadRes(predictions)  # valid COCO results: boxes, RLE masks, known ids
    assert {p["category_id"] for p in predictions} <= {1, 2}
    assert Image.open(tmp_path / "eval" / "predictions.png").size[0] == 4 * 320


def test_category_name_mismatch_is_a_clear_error(testset, tmp_path):
    model = model_folder(tmp_path / "model", ["red_box", "green_cone"])
    with pytest.raises(StageError, match="blue_disc.*not among the model's categories"):
        evaluate(model, testset, tmp_path / "eval")


def test_missing_model_is_a_clear_error(testset, tmp_path):
    with pytest.raises(StageError, match="model.pt"):
        evaluate(tmp_path / "nothing", testset, tmp_path / "eval")


@pytest.mark.slow
def test_onnx_export_matches_pytorch(testset, tmp_path):
    model = model_folder(tmp_path / "model", SHAPE_NAMES)
    out = tmp_path / "eval"
    out.mkdir()
    metrics = run(Context("eval", "test", {"threads": 1, "onnx": True, "max_images": 1},
                          {"model": model, "testset": testset}, out))
    check = metrics["onnx"]
    assert (out / "model.onnx").is_file() and check["detections"] == check["reference_detections"] > 0
    assert check["max_box_difference_px"] < 0.1 and check["min_mask_iou"] >= 0.99


def boxes_only(testset: Path, out: Path) -> Path:
    """A copy of `testset` whose annotations keep boxes and drop masks (like hand-drawn test sets)."""
    (out / "images").mkdir(parents=True)
    for image in (testset / "images").iterdir():
        (out / "images" / image.name).write_bytes(image.read_bytes())
    data = json.loads((testset / "annotations.json").read_text())
    for ann in data["annotations"]:
        ann.pop("segmentation")
    (out / "annotations.json").write_text(json.dumps(data))
    return out


def test_boxes_only_test_set_gives_box_ap_and_no_mask_ap(testset, tmp_path):
    boxes = boxes_only(testset, tmp_path / "boxes")
    coco = load_coco(boxes / "annotations.json")
    results = [{"image_id": a["image_id"], "category_id": a["category_id"], "bbox": a["bbox"], "score": 1.0,
                "segmentation": {"size": [96, 96], "counts": "PPP1"}} for a in coco.dataset["annotations"]]
    metrics = coco_metrics(coco, results, coco.getImgIds())
    assert metrics["bbox"]["AP"] == pytest.approx(100.0)
    assert metrics["segm"]["available"] is False and metrics["segm"]["AP"] is None
    stage_metrics = evaluate(model_folder(tmp_path / "model", SHAPE_NAMES), boxes, tmp_path / "out")
    per_class = [ap for ap in stage_metrics["bbox"]["per_class"].values() if ap is not None]  # classes with boxes
    assert stage_metrics["segm"]["AP"] is None and per_class
    assert stage_metrics["bbox"]["AP"] == pytest.approx(sum(per_class) / len(per_class))
    assert stage_metrics["segm"]["available"] is False


def test_inference_size_benchmark_matches_eval_at_the_models_own_size(testset, tmp_path):
    model = model_folder(tmp_path / "model", list(reversed(SHAPE_NAMES)))
    metrics = evaluate(model, testset, tmp_path / "eval")
    rows = box_ap_by_size(model / "model.pt", testset, [96, 64])
    assert [row["size"] for row in rows] == [96, 64]
    assert rows[0]["AP"] == metrics["bbox"]["AP"] and rows[0]["AP50"] == metrics["bbox"]["AP50"]
    assert rows[0]["detections"] > 0


def test_blurred_mask_grid_erases_thin_parts_first():
    from benchmarks.mask_ceiling import grid_round_trip
    mask = np.zeros((120, 120), bool)
    mask[10:110, 10:60] = True                                     # a block half the box wide
    mask[10:110, 100:104] = True                                   # a leaf: 4 px of a 100 px box
    box = [10.0, 10.0, 100.0, 100.0]
    sharp, blurred = grid_round_trip(mask, box, 28), grid_round_trip(mask, box, 28, blur_cells=2.0)
    assert sharp[:, 100:104].sum() > 0.5 * mask[:, 100:104].sum()    # the grid alone keeps the leaf
    assert blurred[:, 95:110].sum() == 0                             # the blurred grid loses it
    assert (blurred & mask).sum() > 0.9 * mask[:, :60].sum()  # and keeps the block


def test_mask_refinement_benchmark_gives_the_eval_stages_masks_and_figures(testset, tmp_path):
    model = model_folder(tmp_path / "model", SHAPE_NAMES)
    table = mask_ap_by_setting(model / "model.pt", testset, [(0.0, 3e-4, None), (6.0, 3e-4, 0.5)])
    masks = []
    for row in table["rows"]:
        out = tmp_path / f"eval{row['radius']}"
        metrics = evaluate(model, testset, out, {"mask_refine_radius": row["radius"],
                                                 "mask_owner_score": row["owner_score"]})
        assert row["results"] == json.loads((out / "predictions.json").read_text())
        assert row["AP"] == pytest.approx(metrics["segm"]["AP"]) and table["box_AP"] == pytest.approx(metrics["bbox"]["AP"])
        masks.append([r["segmentation"]["counts"] for r in row["results"]])
    assert masks[0] != masks[1]  # the refinement changed the masks
