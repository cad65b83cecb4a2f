"""Round trips of the records the stages hand to each other (stages/records/)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from stages.contract.errors import StageError
from stages.lib.coco import CocoBuilder, load_coco, rle_to_mask
from stages.records.cameras import CameraFrame, CamerasRecord
from stages.records.capture_truth import CaptureTruth
from stages.records.coco_dataset import CocoDataset
from stages.records.depth import DepthRecord
from stages.records.extract import ExtractRecord
from stages.records.frames import FrameEntry, FramesRecord
from stages.records.planes import PlacementPlane, PlanesRecord
from stages.records.sfm import SfmRecord

K = np.array([[60.0, 0.0, 32.0], [0.0, 60.0, 24.0], [0.0, 0.0, 1.0]])


def test_depth_round_trip(tmp_path):
    depth = np.linspace(0.5, 4.0, 64 * 48, dtype=np.float32).reshape(48, 64)
    DepthRecord("sidecar", True, K, 64, 48, depth).write(tmp_path)
    record = DepthRecord.read(tmp_path)
    assert (record.provider, record.metric, record.width, record.height) == ("sidecar", True, 64, 48)
    np.testing.assert_array_equal(record.K, K)
    np.testing.assert_array_equal(record.depth, depth)
    record.check_size(tmp_path, 64, 48)
    with pytest.raises(StageError, match="depth.json is for a 64x48 image"):
        record.check_size(tmp_path, 32, 24)


def test_depth_without_map_and_broken_maps(tmp_path):
    DepthRecord("none", False, K, 64, 48).write(tmp_path)
    assert not (tmp_path / "depth.npy").exists() and DepthRecord.read(tmp_path).depth is None
    DepthRecord("onnx", False, K, 64, 48, np.zeros((48, 64), np.float32)).write(tmp_path)
    with pytest.raises(StageError, match="no valid depth"):
        DepthRecord.read(tmp_path)
    np.save(tmp_path / "depth.npy", np.ones((10, 10), np.float32))
    with pytest.raises(StageError, match="depth.npy: shape"):
        DepthRecord.read(tmp_path)


def test_planes_round_trip(tmp_path):
    points = np.array([[0.1, 1.0, 3.0], [0.2, 1.0, 3.5]])
    pixels = np.array([[34.0, 44.0], [35.43, 41.14]])
    plane = PlacementPlane(np.array([0.0, -1.0, 0.0]), points.mean(0), 2.5, points, pixels)
    PlanesRecord(K, 64, 48, np.array([0.0, -1.0, 0.0]), True, [plane]).write(tmp_path)
    record = PlanesRecord.read(tmp_path)
    assert (record.width, record.height, record.metric, len(record.planes)) == (64, 48, True, 1)
    np.testing.assert_array_equal(record.K, K)
    read = record.planes[0]
    assert read.area == 2.5
    for name in ("normal", "center", "points", "pixels"):
        np.testing.assert_allclose(getattr(read, name), getattr(plane, name), atol=1e-2)
    info = json.loads((tmp_path / "planes.json").read_text())
    info["planes"][0]["points"] = []
    (tmp_path / "planes.json").write_text(json.dumps(info))
    with pytest.raises(StageError, match="plane 0 has no points"):
        PlanesRecord.read(tmp_path)


def test_extract_round_trip(tmp_path):
    written = ExtractRecord(np.array([0.0, 0.6, 0.8]), np.array([1.0, 2.0, 3.0]), 0.3, {"kept": 10}, 2.0,
                            np.array([0.5, 0.5, 0.5]), "ransac", 0.03, {"dbscan_eps": 0.03})
    written.write(tmp_path)
    read = ExtractRecord.read(tmp_path)
    for name in ("normal", "base_point", "scene_centre"):
        np.testing.assert_array_equal(getattr(read, name), getattr(written, name))
    assert (read.height, read.counts, read.scene_scale, read.plane_source, read.dbscan_eps, read.config) == \
        (0.3, {"kept": 10}, 2.0, "ransac", 0.03, {"dbscan_eps": 0.03})
    ExtractRecord(np.zeros(3), np.zeros(3), 0.3).write(tmp_path)
    with pytest.raises(StageError, match="bad normal or height"):
        ExtractRecord.read(tmp_path)


def test_cameras_round_trip(tmp_path):
    viewmat = np.eye(4)
    viewmat[:3, 3] = [0.1, 0.2, 3.0]
    frames = [CameraFrame("0000.jpg", K, viewmat, 64, 48), CameraFrame("0001.jpg", K, np.eye(4), 64, 48)]
    CamerasRecord(64, 48, frames, ["0001.jpg"]).write(tmp_path)
    read = CamerasRecord.read(tmp_path)
    assert CamerasRecord.exists(tmp_path) and read.held_out == ["0001.jpg"] and (read.width, read.height) == (64, 48)
    assert [f.file for f in read.frames] == ["0000.jpg", "0001.jpg"]
    np.testing.assert_array_equal(read.viewmats, np.stack([viewmat, np.eye(4)]))
    np.testing.assert_array_equal(read.frames[1].K, K)
    info = json.loads((tmp_path / "cameras.json").read_text())
    info["frames"][0]["viewmat"] = [[1, 0], [0, 1]]
    (tmp_path / "cameras.json").write_text(json.dumps(info))
    with pytest.raises(StageError, match="cannot read camera poses"):
        CamerasRecord.read(tmp_path)


def test_frames_round_trip(tmp_path):
    entries = [FrameEntry("images/0000.jpg", 3, 0.3, 120.5, "video.mp4", 0.5),
               FrameEntry("images/0001.jpg", 7, None, 99.0, "video.mp4", 0.5)]
    FramesRecord(entries).write(tmp_path)
    assert FramesRecord.read(tmp_path).frames == entries
    (tmp_path / "frames.json").write_text("[{}]")
    with pytest.raises(StageError, match="frames.json: malformed"):
        FramesRecord.read(tmp_path)


def test_capture_truth_round_trip(tmp_path):
    viewmats = {0: np.eye(4), 3: np.diag([1.0, -1.0, -1.0, 1.0])}
    written = CaptureTruth("vase", 0.22, K, 64, 48, 10.0, viewmats, np.array([0.0, 0.0, 1.0]), np.zeros(3),
                           "object_points.npy", "table", 0.8, 7)
    written.write(tmp_path)
    np.save(tmp_path / "object_points.npy", np.ones((5, 3), np.float32))
    read = CaptureTruth.read(tmp_path)
    assert (read.name, read.height_m, read.width, read.height, read.fps, read.support, read.orbit_radius_m, read.seed) == \
        ("vase", 0.22, 64, 48, 10.0, "table", 0.8, 7)
    assert sorted(read.viewmats) == [0, 3] and np.array_equal(read.viewmats[3], viewmats[3])
    np.testing.assert_array_equal(read.K, K)
    assert read.object_points(tmp_path).shape == (5, 3)


def test_sfm_round_trip_and_what_read_refuses(tmp_path):
    staging, folder = tmp_path / "undistorted", tmp_path / "sfm"
    for sub in ("sparse", "images"):
        (staging / sub).mkdir(parents=True)
    (staging / "images" / "0000.jpg").write_bytes(b"jpeg")
    folder.mkdir()
    camera = {"model": "PINHOLE", "width": 64, "height": 48, "params": [50.0, 50.0, 32.0, 24.0]}
    summary = {"registered": 1, "total": 2, "camera": camera, "source_camera": {**camera, "model": "SIMPLE_RADIAL"}}
    SfmRecord.write(folder, summary, staging / "sparse", staging / "images")
    back = SfmRecord.read(folder)
    assert back.summary == summary and back.source_camera["model"] == "SIMPLE_RADIAL"
    assert back.image("0000.jpg").read_bytes() == b"jpeg" and back.sparse_dir.is_dir()

    (folder / "sfm.json").write_text(json.dumps({k: v for k, v in summary.items() if k != "source_camera"}))
    with pytest.raises(StageError, match=r"sfm\.json: malformed \(no source_camera\)"):
        SfmRecord.read(folder)
    (folder / "sfm.json").write_text(json.dumps(summary))
    (folder / "sparse").rmdir()
    with pytest.raises(StageError, match=r"sparse: missing"):
        SfmRecord.read(folder)
    with pytest.raises(StageError, match=r"sfm\.json: missing or not JSON"):
        SfmRecord.read(tmp_path)


def _coco_folder(tmp_path, masks: list[np.ndarray]) -> CocoDataset:
    """A one-image dataset of 64x48 with an instance per mask, written through the builder into tmp_path."""
    (tmp_path / "images").mkdir()
    (tmp_path / "images" / "0000.png").write_bytes(b"an image")  # read checks that it exists, not its pixels
    builder = CocoBuilder(["mug", "vase"], info={"stage": "test"})
    image_id = builder.add_image("0000.png", 64, 48, K=K.tolist())
    for k, mask in enumerate(masks):
        builder.add_instance(image_id, k % 2 + 1, mask, visible_fraction=0.5)
    builder.dataset.write(tmp_path)
    return builder.dataset


def test_coco_dataset_round_trip(tmp_path):
    mask = np.zeros((48, 64), bool)
    mask[10:20, 5:30] = True
    written = _coco_folder(tmp_path, [mask, ~mask])
    read = CocoDataset.read(tmp_path)
    assert read == written and read.category_names == ["mug", "vase"]
    assert (tmp_path / "annotations.json").read_text() == json.dumps(written.to_dict())
    assert read.annotations[0]["bbox"] == [5.0, 10.0, 25.0, 10.0] and read.annotations[0]["area"] == 250
    np.testing.assert_array_equal(rle_to_mask(read.annotations[1]["segmentation"]), ~mask)
    assert CocoDataset.image_file(tmp_path, read.images[0]) == tmp_path / "images" / "0000.png"
    assert {k: [a["id"] for a in anns] for k, anns in read.annotations_by_image().items()} == {1: [1, 2]}
    assert load_coco(tmp_path).annToMask(read.annotations[0]).sum() == 250  # pycocotools reads the same file


@pytest.mark.parametrize("edit, cause", [
    (lambda d: d["annotations"][0]["segmentation"].update(size=[24, 32]), "annotation 1 \\(image 1\\): segmentation is "
                                                                         "not an RLE mask of its image's size \\[48, 64\\]"),
    (lambda d: d["annotations"][0].update(segmentation=[[1, 2, 3, 4]]), "neither an RLE mask nor a list of polygons"),
    (lambda d: d["annotations"][0].update(bbox=[1, 2, 3]), "bbox \\[1, 2, 3\\] is not"),
    (lambda d: d["categories"].append({"id": 3, "name": "mug"}), "repeated category names \\['mug'\\]"),
    (lambda d: d.update(categories=[]), "no categories"),
    (lambda d: d["images"][0].pop("height"), "lacks the key 'height'"),
    (lambda d: d["images"][0].update(file_name="gone.png"), "1 of 1 images are not in .*images \\(first: gone.png\\)"),
])
def test_coco_dataset_errors_name_the_file_and_the_problem(tmp_path, edit, cause):
    _coco_folder(tmp_path, [np.eye(48, 64, dtype=bool)])
    data = json.loads((tmp_path / "annotations.json").read_text())
    edit(data)
    (tmp_path / "annotations.json").write_text(json.dumps(data))
    with pytest.raises(StageError, match=f"{tmp_path / 'annotations.json'}: .*{cause}"):
        CocoDataset.read(tmp_path)


def test_coco_dataset_of_boxes_or_polygons_reads(tmp_path):
    """User test sets: boxes only (no segmentation) or polygon masks are valid."""
    _coco_folder(tmp_path, [np.eye(48, 64, dtype=bool)])
    data = json.loads((tmp_path / "annotations.json").read_text())
    data["annotations"][0].pop("segmentation")
    data["annotations"].append({**data["annotations"][0], "id": 2, "segmentation": [[1, 1, 9, 1, 9, 9]]})
    (tmp_path / "annotations.json").write_text(json.dumps(data))
    assert [a.get("segmentation") for a in CocoDataset.read(tmp_path).annotations] == [None, [[1, 1, 9, 1, 9, 9]]]
