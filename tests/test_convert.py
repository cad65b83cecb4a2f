"""Conversions of COCO dataset folders (stages/lib/dataset_formats/, `python -m stages.app.convert`): YOLO polygons and boxes against
the COCO masks and boxes, BOP poses reprojected into the amodal masks, Ultralytics' checker where it is installed."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from benchmarks.convert import (bop_reprojection, inside_fraction, read_yolo_labels, single_polygon_ceiling,
                               ultralytics_check, yolo_box_errors, yolo_polygon_ious)
from stages.app.convert import main as export_main
from stages.app.convert import object_model_points
from stages.compose import run as compose
from stages.contract.errors import StageError
from stages.engine.context import Context
from stages.lib.coco import rle_to_mask
from stages.lib.dataset_formats.polygons import mask_iou, mask_polygon, polygon_mask
from stages.records.coco_dataset import CocoDataset
from tests.factories.backgrounds import write_floor_scene
from tests.factories.shapes import write_shapes_dataset


@pytest.fixture(scope="module")
def composed(tmp_path_factory) -> tuple[Path, Path]:
    """A compose dataset of 8 images (plane and random poses, objects large enough to hide each other) and the
    object.ply it was made from."""
    root = tmp_path_factory.mktemp("compose")
    inputs = write_floor_scene(root / "in")
    params = {"objects": [{"name": "blob", "height_m": 0.9}], "num_images": 8, "image_size": [320, 240],
              "min_objects": 2, "max_objects": 3, "random_placement_share": 0.25, "preview_count": 2, "workers": 1}
    (root / "out").mkdir()
    compose.run(Context(stage="compose", item="full", params=params, inputs=inputs, out=root / "out", seed=3))
    return root / "out", root / "in" / "extract" / "object.ply"


def test_polygon_of_a_mask_with_holes_and_pieces_fills_back_to_it():
    """Holes come back exactly (even-odd fill of a bridged loop); pieces are joined by zero-width bridges along
    the shortest joins: only the pixels a bridge crosses are extra, and the polygon keeps the mask's box."""
    mask = np.zeros((120, 160), np.uint8)
    cv2.circle(mask, (60, 60), 40, 1, -1)
    cv2.circle(mask, (50, 50), 8, 0, -1)  # a hole
    cv2.circle(mask, (75, 70), 5, 0, -1)  # another
    mask = mask.astype(bool)
    polygon = mask_polygon(mask)
    assert polygon.loops == 3
    np.testing.assert_array_equal(polygon_mask(polygon.points, 160, 120), mask)
    pieces = mask.copy()
    pieces[50:70, 104:120] = True  # 4 px right of the disc
    pieces[25:30, 110:115] = True  # a square 17 px from the disc
    pieces[5:7, 150:152] = True  # a 4-pixel speck 36 px from the square
    polygon = mask_polygon(pieces)
    filled = polygon_mask(polygon.points, 160, 120)
    assert polygon.loops == 6 and (pieces & ~filled).sum() == 0
    assert (filled & ~pieces).sum() <= 3 + 17 + 36  # the three bridges' pixels outside the mask
    assert polygon.points.min(0).tolist() == [20.5, 5.5] and polygon.points.max(0).tolist() == [151.5, 100.5]
    single = np.zeros((10, 10), bool)
    single[4, 6] = True
    assert mask_polygon(single).points.tolist() == [[6.5, 4.5]] * 3  # pixel centres, three points for YOLO


def test_yolo_segment_export_matches_the_coco_masks_and_boxes(composed, tmp_path):
    dataset, _ = composed
    assert export_main([str(dataset), "--format", "yolo-segment", "--out", str(tmp_path / "yolo")]) == 0
    ious = yolo_polygon_ious(tmp_path / "yolo", "train", dataset)
    coco = CocoDataset.read(dataset)
    assert len(ious) == len(coco.annotations) > 8 and min(iou for iou, _ in ious) >= 0.95
    assert yolo_box_errors(tmp_path / "yolo", "train", dataset, "segment").max() <= 0.501  # pixel centres, 6 decimals
    data = yaml.safe_load((tmp_path / "yolo" / "data.yaml").read_text())
    assert data == {"train": "images/train", "val": "images/train", "names": {0: "blob"}}
    assert sorted(p.name for p in (tmp_path / "yolo" / "images" / "train").iterdir()) == \
        sorted(image["file_name"] for image in coco.images)
    summary = json.loads((tmp_path / "yolo" / "convert.json").read_text())["splits"]["train"]
    assert summary["instances"] == len(ious) and summary["polygon_iou_min"] == pytest.approx(min(iou for iou, _ in ious), abs=1e-4)


def test_yolo_detect_export_with_test_sets_and_class_names(composed, tmp_path):
    """Boxes equal the COCO boxes; a test set's categories map by name onto the train split's class ids."""
    dataset, _ = composed
    shapes = write_shapes_dataset(tmp_path / "shapes", 3, names=["blob", "disc"])
    with pytest.raises(SystemExit):  # argparse: an unknown format
        export_main([str(dataset), "--format", "yolo", "--out", str(tmp_path / "bad")])
    assert export_main([str(dataset), "--format", "yolo-detect", "--out", str(tmp_path / "bad"),
                        "--test", str(shapes)]) == 1  # "disc" is not a train category
    assert export_main([str(shapes), "--format", "yolo-detect", "--out", str(tmp_path / "yolo"),
                        "--val", str(dataset)]) == 0
    assert yolo_box_errors(tmp_path / "yolo", "train", shapes, "detect").max() < 1e-3  # 6 decimals
    assert yolo_box_errors(tmp_path / "yolo", "val", dataset, "detect").max() < 1e-3  # 6 decimals
    coco = CocoDataset.read(shapes)
    first = read_yolo_labels(tmp_path / "yolo" / "labels" / "train" / "0000.txt")
    assert [c for c, _ in first] == [a["category_id"] - 1 for a in coco.annotations if a["image_id"] == 1]
    assert {c for path in (tmp_path / "yolo" / "labels" / "val").iterdir() for c, _ in read_yolo_labels(path)} == {0}
    assert yaml.safe_load((tmp_path / "yolo" / "data.yaml").read_text())["names"] == {0: "blob", 1: "disc"}


def test_compose_poses_reproject_into_the_amodal_masks(composed):
    dataset_folder, ply = composed
    dataset = CocoDataset.read(dataset_folder)
    points = object_model_points(dataset_folder, dataset, "blob", ply)  # [N, 3] metres, the poses' frame
    assert abs(np.ptp(points[:, 2]) - 0.9) < 0.05 and np.abs(points.max(0) + points.min(0)).max() < 1e-9
    images = {image["id"]: image for image in dataset.images}
    shares = []
    for ann in dataset.annotations:
        amodal, visible = rle_to_mask(ann["amodal_segmentation"]), rle_to_mask(ann["segmentation"])
        assert (visible & ~amodal).sum() == 0  # the visible part lies inside the mask before occlusion
        shares.append(inside_fraction(points, np.asarray(ann["pose"]["R"]), np.asarray(ann["pose"]["t"]),
                                      np.asarray(images[ann["image_id"]]["K"]), amodal))
    assert min(s for s in shares if s is not None) >= 0.98


def test_bop_export_follows_the_format_and_its_poses_reproject(composed, tmp_path):
    dataset_folder, ply = composed
    out = tmp_path / "bop"
    with pytest.raises(StageError, match="needs a compose dataset"):
        from stages.app.convert import export
        export(write_shapes_dataset(tmp_path / "shapes", 2), "bop", tmp_path / "shapes_bop")
    assert export_main([str(dataset_folder), "--format", "bop", "--out", str(out), "--model", f"blob={ply}"]) == 0
    scene = out / "train" / "000000"
    gt, info, camera = (json.loads((scene / f"{name}.json").read_text())
                        for name in ("scene_gt", "scene_gt_info", "scene_camera"))
    dataset = CocoDataset.read(dataset_folder)
    assert sorted(gt, key=int) == [str(k) for k in range(len(dataset.images))] and set(camera) == set(gt)
    first = dataset.annotations[0]
    assert gt["0"][0]["obj_id"] == first["category_id"] == 1
    np.testing.assert_allclose(gt["0"][0]["cam_t_m2c"], 1000 * np.asarray(first["pose"]["t"]), atol=1e-3)
    assert len(camera["0"]["cam_K"]) == 9 and len(gt["0"][0]["cam_R_m2c"]) == 9
    visible = cv2.imread(str(scene / "mask_visib" / "000000_000000.png"), cv2.IMREAD_GRAYSCALE) > 0
    np.testing.assert_array_equal(visible, rle_to_mask(first["segmentation"]))
    assert info["0"][0]["px_count_visib"] == first["area"] and 0 < info["0"][0]["visib_fract"] <= 1
    assert (scene / "rgb" / "000000.jpg").read_bytes() == (dataset_folder / "images" / "000000.jpg").read_bytes()
    models = json.loads((out / "models" / "models_info.json").read_text())
    assert abs(models["1"]["size_z"] - 900) < 50 and models["1"]["diameter"] > models["1"]["size_z"]
    assert min(bop_reprojection(out)) >= 0.98
    assert min(bop_reprojection(out, slack_px=0.5)) >= min(bop_reprojection(out))  # slack counts at least as many in


def test_ultralytics_checker_accepts_the_yolo_exports(composed, tmp_path, monkeypatch):
    """Ultralytics (AGPL-3.0, not a dependency: `pip install ultralytics` in a venv of its own) checks its data.yaml
    and reads every label. Its config folder gets a font file so that its checker does not try to download one."""
    (tmp_path / "config").mkdir()
    (tmp_path / "config" / "Arial.ttf").write_bytes(b"")
    monkeypatch.setenv("YOLO_CONFIG_DIR", str(tmp_path / "config"))
    monkeypatch.setenv("YOLO_OFFLINE", "1")
    pytest.importorskip("ultralytics", reason="ultralytics is not installed (AGPL-3.0; a venv of its own)")
    dataset, _ = composed
    instances = len(CocoDataset.read(dataset).annotations)
    for task in ("segment", "detect"):
        assert export_main([str(dataset), "--format", f"yolo-{task}", "--out", str(tmp_path / task)]) == 0
        check = ultralytics_check(tmp_path / task, task)
        assert check["names"] == ["blob"] and check["train"]["instances"] == instances
        assert check["train"]["segments"] == (instances if task == "segment" else 0)


def test_a_polygon_fills_its_mask_from_the_normalised_label(composed):
    """The label's normalised coordinates, scaled back and truncated as Ultralytics does, give the same pixels
    as the polygon in pixels: the pixel centres survive 6 decimals."""
    dataset_folder, _ = composed
    ann = CocoDataset.read(dataset_folder).annotations[0]
    mask = rle_to_mask(ann["segmentation"])
    points = mask_polygon(mask).points
    size = np.array([mask.shape[1], mask.shape[0]], dtype=np.float64)
    normalised = np.asarray([float(f"{v:.6f}") for v in (points / size).ravel()]).reshape(-1, 2)
    assert mask_iou(polygon_mask(normalised * size, *mask.shape[::-1]), mask) == 1.0


def test_single_polygon_ceiling_counts_the_gap_a_bridge_must_fill():
    """Two 2x2 squares three rows apart: one polygon fills at least the 3 pixels between them (IoU <= 8/11),
    better than dropping a square (4/8); one component or squares touching at a corner reach 1."""
    mask = np.zeros((10, 10), bool)
    mask[1:3, 1:3] = True
    assert single_polygon_ceiling(mask) == 1.0
    mask[6:8, 1:3] = True
    assert single_polygon_ceiling(mask) == pytest.approx(8 / 11)
    corner = np.zeros((6, 6), bool)
    corner[1:3, 1:3] = corner[3:5, 3:5] = True
    assert single_polygon_ceiling(corner) == 1.0


def test_inside_fraction_slack_counts_points_within_half_a_pixel():
    """A point 0.3 px right of a one-pixel mask is outside it, but within half a pixel of it."""
    mask = np.zeros((4, 4), bool)
    mask[1, 1] = True
    K = np.eye(3)
    points = np.array([[1.5, 1.5, 1.0], [2.3, 1.5, 1.0]])  # pixel (1, 1)'s centre; 0.3 px right of its edge
    assert inside_fraction(points, np.eye(3), np.zeros(3), K, mask) == 0.5
    assert inside_fraction(points, np.eye(3), np.zeros(3), K, mask, slack_px=0.5) == 1.0
