"""Tests of the embedded sample: layout, determinism, ground-truth consistency and COCO validity."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from stages.bg_depth import run as bg_depth
from stages.bg_frames import run as bg_frames
from stages.contract.errors import StageError
from stages.engine.context import Context
from stages.lib.capture.video_frames import header_frame_count
from stages.lib.coco import load_coco, rle_to_mask
from stages.lib.geometry import camera_centres
from stages.lib.sample_scene.cameras import project
from stages.lib.sample_scene.capture import build_capture_scene
from stages.lib.sample_scene.objects import OBJECT_CLASSES, build_object
from stages.lib.sample_scene.raytrace import TracedScene
from stages.lib.sample_scene.rooms import make_room
from stages.records import sample_layout as layout
from stages.records.bg_frames import BgFramesRecord
from stages.records.sample_layout import closeup_indices
from stages.sample.run import run
from stages.sample.spec import SampleConfig
from tests.factories.media import read_mp4

TINY = {"width": 160, "height": 120, "num_frames": 8, "num_backgrounds": 4, "num_indomain": 2, "num_test": 3,
        "photos_per_room": 4, "test_rooms": 1, "wall_closeup_fraction": 0.25, "workers": 1, "walk_seconds": 1.2,
        "objects": [{"name": "bottle", "height_m": 0.25}, {"name": "plant", "height_m": 0.30},
                    {"name": "soda_can", "height_m": 0.12}]}


def _run(out: Path, **overrides) -> Path:
    out.mkdir(parents=True)
    run(Context("sample", "sample", {**TINY, **overrides}, {}, out))
    return out


@pytest.fixture(scope="module")
def sample_dir(tmp_path_factory) -> Path:
    return _run(tmp_path_factory.mktemp("sample") / "a")


def test_layout_follows_the_contract(sample_dir: Path):
    for spec in TINY["objects"]:
        folder = sample_dir / layout.object_folder(spec["name"])
        gt = json.loads((folder / "gt.json").read_text())
        assert gt["name"] == spec["name"] and gt["height_m"] == spec["height_m"]
        assert len(gt["frames"]) == TINY["num_frames"] and np.array(gt["frames"][0]["viewmat"]).shape == (4, 4)
        assert gt["ground_normal"] == [0.0, 0.0, 1.0] and len(gt["ground_point"]) == 3
        points = np.load(folder / gt["object_points_file"])
        assert points.dtype == np.float32 and points.shape[1] == 3
        assert points[:, 2].min() >= -1e-4 and abs(points[:, 2].max() - spec["height_m"]) < 0.02 * spec["height_m"]
        frames = read_mp4(sample_dir / layout.video(spec["name"]))
        assert len(frames) == TINY["num_frames"] and frames[0].shape == (TINY["height"], TINY["width"], 3)
        masks = sorted((sample_dir / layout.capture_masks(spec["name"])).glob("*.png"))
        assert len(masks) == TINY["num_frames"]
        assert set(np.unique(cv2.imread(str(masks[0]), cv2.IMREAD_UNCHANGED))) <= {0, 255}
    for kind in ("generic", "indomain"):  # every file where the layout the pipeline reads says it is
        for pid in layout.background_ids(SampleConfig(**TINY), kind):
            depth = cv2.imread(str(sample_dir / layout.depth(kind, pid)), cv2.IMREAD_UNCHANGED)
            assert depth.dtype == np.uint16 and depth.shape == (TINY["height"], TINY["width"])
            assert (sample_dir / layout.photo(kind, pid)).is_file() and (sample_dir / layout.support(kind, pid)).is_file()
            assert np.array(json.loads((sample_dir / layout.intrinsics(kind, pid)).read_text())["K"]).shape == (3, 3)
    for camera in layout.TEST_CAMERAS:
        assert (sample_dir / layout.test_set(camera) / "annotations.json").is_file()
    for part in ("objects", "backgrounds", "indomain", "test_a", "test_b"):
        assert (sample_dir / f"contact_{part}.png").is_file()
    summary = json.loads((sample_dir / "sample.json").read_text())
    assert summary["test_a"]["images"] == TINY["num_test"] and summary["wall_closeups"] == 1


def test_regeneration_is_byte_identical(sample_dir: Path, tmp_path: Path):
    again = _run(tmp_path / "b", workers=2)  # also: the output does not depend on the worker count
    files = sorted(p.relative_to(sample_dir) for p in sample_dir.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(again) for p in again.rglob("*") if p.is_file())
    for rel in files:
        if rel.name == "sample.json":
            first, second = (json.loads((d / rel).read_text()) for d in (sample_dir, again))
            for d in (first, second):
                d.pop("timings_s"), d.pop("total_s"), d["config"].pop("workers")
            assert first == second
        else:
            assert (sample_dir / rel).read_bytes() == (again / rel).read_bytes(), f"{rel} differs between runs"


def test_object_points_project_into_the_masks(sample_dir: Path):
    offsets = [(0.0, 0.0), (-0.5, 0.0), (0.5, 0.0), (0.0, -0.5), (0.0, 0.5), (20.0, 0.0)]
    rates = {offset: [] for offset in offsets}
    dilated_rates = []
    for spec in TINY["objects"]:
        folder = sample_dir / layout.object_folder(spec["name"])
        gt = json.loads((folder / "gt.json").read_text())
        K = np.array(gt["K"])
        points = np.load(folder / "object_points.npy")[::10]
        scene = build_capture_scene(spec["name"], spec["height_m"], 0, K[1, 1], gt["height"])
        traced = TracedScene(scene.meshes)
        for frame in gt["frames"]:
            viewmat = np.array(frame["viewmat"])
            mask = cv2.imread(str(folder / "masks" / f"{frame['index']:04d}.png"), cv2.IMREAD_UNCHANGED) > 0
            dilated = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
            centre = camera_centres(viewmat).astype(np.float32)
            toward = centre - points
            near_points = points + 0.002 * toward / np.linalg.norm(toward, axis=1, keepdims=True)
            visible = ~traced.occluded(near_points, np.broadcast_to(centre, points.shape).copy())
            pix, z = project(points[visible], K, viewmat)
            for offset in offsets:
                # pixel index = floor(coordinate): the top-left pixel's centre is (0.5, 0.5)
                col, row = np.floor(pix[:, 0] + offset[0]).astype(int), np.floor(pix[:, 1] + offset[1]).astype(int)
                inside = (col >= 0) & (row >= 0) & (col < gt["width"]) & (row < gt["height"]) & (z > 0)
                rates[offset].append(mask[row[inside], col[inside]].mean())
                if offset == (0.0, 0.0):
                    dilated_rates.append(dilated[row[inside], col[inside]].mean())
    # within a pixel of the mask (silhouette pixels are ambiguous; sub-pixel plant stems can fall between centres)
    assert np.mean(dilated_rates) > 0.98 and min(dilated_rates) > 0.9, dilated_rates
    mean = {offset: float(np.mean(r)) for offset, r in rates.items()}
    assert mean[(0.0, 0.0)] > 0.9 and all(mean[(0.0, 0.0)] >= mean[o] for o in offsets), mean  # pixel-centre convention
    assert mean[(20.0, 0.0)] < 0.8 * mean[(0.0, 0.0)], mean  # a wrong pose is caught


def test_depth_sidecars_lie_on_the_room_geometry(sample_dir: Path):
    cfg = SampleConfig(**TINY)
    closeups = closeup_indices(cfg.num_backgrounds, cfg.wall_closeup_fraction)
    room = make_room(np.random.default_rng([cfg.seed, 21, 0]))  # all 4 photos share room 0
    traced = TracedScene(room.meshes)
    for i, pid in enumerate(layout.background_ids(cfg, "generic")):
        meta = json.loads((sample_dir / "backgrounds" / f"{pid}.json").read_text())
        depth = cv2.imread(str(sample_dir / "backgrounds" / f"{pid}.depth.png"), cv2.IMREAD_UNCHANGED) / 1000.0
        support = cv2.imread(str(sample_dir / "backgrounds" / f"{pid}.support.png"), cv2.IMREAD_UNCHANGED) > 0
        K, viewmat = np.array(meta["K"]), np.array(meta["viewmat"])
        v, u = np.nonzero(depth > 0)
        cam = np.stack([(u + 0.5 - K[0, 2]) / K[0, 0], (v + 0.5 - K[1, 2]) / K[1, 1], np.ones(len(u))], 1) * depth[v, u, None]
        world = (cam - viewmat[:3, 3]) @ viewmat[:3, :3]
        distance = traced.distance(world)
        assert len(u) > 0.95 * depth.size and np.percentile(distance, 95) < 0.002, (pid, np.percentile(distance, 95))
        wrong = traced.distance((cam * 1.05 - viewmat[:3, 3]) @ viewmat[:3, :3])
        assert np.percentile(wrong, 50) > 0.01  # the check can tell a wrong depth scale
        if i in closeups:
            assert meta["kind"] == "wall_closeup" and not support.any()
        else:
            assert support.any()
            tops = np.array([m.vertices[:, 2].max() for m in room.meshes if m.support])
            support_z = world[support[v, u], 2]
            assert np.abs(support_z[:, None] - tops[None]).min(1).max() < 0.005  # on a support mesh's top face


def test_coco_test_sets_load_and_areas_match(sample_dir: Path):
    names = [o["name"] for o in TINY["objects"]]
    per_set = {}
    for camera in ("a", "b"):
        coco = load_coco(sample_dir / f"test_{camera}" / "annotations.json")
        assert [coco.cats[i]["name"] for i in sorted(coco.cats)] == names and sorted(coco.cats) == [1, 2, 3]
        assert len(coco.imgs) == TINY["num_test"]
        for image_id, image in coco.imgs.items():
            anns = coco.imgToAnns[image_id]
            assert len(anns) in (1, 2, 3)
            assert (sample_dir / f"test_{camera}" / "images" / image["file_name"]).is_file()
            for ann in anns:
                mask = rle_to_mask(ann["segmentation"])
                assert mask.shape == (image["height"], image["width"])
                assert ann["area"] == int(mask.sum()) == int(coco.annToMask(ann).sum()) > 0
                assert ann["visible_fraction"] >= 0.3
        per_set[camera] = [sorted(a["category_id"] for a in coco.imgToAnns[i]) for i in sorted(coco.imgs)]
        per_set[camera + "_focal"] = coco.imgs[1]["K"][0][0]
    assert per_set["a"] == per_set["b"]  # same object distribution in both sets
    assert per_set["a_focal"] != per_set["b_focal"]


def test_objects_have_their_real_height():
    for name in OBJECT_CLASSES:
        meshes = build_object(name, 0.2, seed=3)
        vertices = np.concatenate([m.vertices for m in meshes])
        assert abs(vertices[:, 2].min()) < 1e-6 and abs(vertices[:, 2].max() - 0.2) < 1e-6
        assert all(m.label == 1 for m in meshes)


def test_wall_closeup_share():
    assert len(closeup_indices(40, 0.15)) == 6 and len(closeup_indices(10, 0.1)) == 1
    assert len(closeup_indices(0, 0.15)) == 0


def test_bad_config_is_a_clear_error(tmp_path: Path):
    with pytest.raises(StageError, match="teapot"):
        run(Context("sample", "sample", {**TINY, "objects": [{"name": "teapot", "height_m": 0.1}]}, {}, tmp_path))
    with pytest.raises(StageError, match="height_m"):
        run(Context("sample", "sample", {**TINY, "objects": [{"name": "vase", "height_m": 0}]}, {}, tmp_path))


def test_the_walk_is_a_video_with_the_ray_tracers_depth_and_none_of_its_frames_is_a_test_photo(sample_dir: Path):
    count = layout.walk_frames(SampleConfig(**TINY))
    frames = read_mp4(sample_dir / layout.walk_video())
    assert len(frames) == count == header_frame_count(sample_dir / layout.walk_video()) == 12
    camera = json.loads((sample_dir / layout.walk_camera()).read_text())
    assert [f["index"] for f in camera["frames"]] == list(range(count)) and np.array(camera["K"]).shape == (3, 3)
    room = make_room(np.random.default_rng([TINY.get("seed", 0), 31, 0]))  # the in-domain (test) room it walks in
    traced = TracedScene(room.meshes)
    K = np.array(camera["K"])
    for index in (0, count - 1):
        depth = cv2.imread(str(sample_dir / layout.walk_depth(index)), cv2.IMREAD_UNCHANGED) / 1000.0
        viewmat = np.array(camera["frames"][index]["viewmat"])
        v, u = np.nonzero(depth > 0)
        cam = np.stack([(u + 0.5 - K[0, 2]) / K[0, 0], (v + 0.5 - K[1, 2]) / K[1, 1], np.ones(len(u))], 1) * depth[v, u, None]
        assert len(u) > 0.95 * depth.size
        assert np.percentile(traced.distance((cam - viewmat[:3, 3]) @ viewmat[:3, :3]), 95) < 0.002
    tests = [cv2.imread(str(p))[..., ::-1].astype(np.int16)
             for camera_name in layout.TEST_CAMERAS for p in (sample_dir / layout.test_set(camera_name) / "images").iterdir()]
    assert min(np.abs(frame.astype(np.int16) - test).mean() for frame in frames for test in tests) > 5


def test_the_walk_leaves_every_other_file_of_the_sample_as_it_was(sample_dir: Path, tmp_path: Path):
    without = _run(tmp_path / "no_walk", walk_seconds=0)
    assert not (without / layout.WALK_FOLDER).exists()
    for path in without.rglob("*"):
        if path.is_file() and path.name != layout.SUMMARY:
            assert path.read_bytes() == (sample_dir / path.relative_to(without)).read_bytes(), path


def test_the_frames_of_the_walk_take_its_depth_and_camera(sample_dir: Path, tmp_path: Path):
    """bg_frames on the walk with its per-frame depth: each slot's depth sidecar is its frame's ray-traced depth, and
    bg_depth reads it with the walk's camera, without a depth model."""
    walk = {"video": sample_dir / layout.walk_video(), "depth": sample_dir / layout.walk_depth_folder()}
    (tmp_path / "frames").mkdir()
    bg_frames.run(Context("bg_frames", "walk", {"count": 4}, walk, tmp_path / "frames"))
    record = BgFramesRecord.read(tmp_path / "frames")
    assert [slot.empty for slot in record.slots] == [""] * 4
    for k, slot in enumerate(record.slots):
        assert ((tmp_path / "frames" / BgFramesRecord.depth(k)).read_bytes()
                == (sample_dir / layout.walk_depth(slot.source_index)).read_bytes())
    (tmp_path / "depth").mkdir()
    metrics = bg_depth.run(Context("bg_depth", "walk#0", {"model": "none"},
                                   {"image": tmp_path / "frames" / BgFramesRecord.image(0),
                                    "depth": tmp_path / "frames" / BgFramesRecord.depth(0),
                                    "intrinsics": sample_dir / layout.walk_camera()}, tmp_path / "depth"))
    assert metrics["provider"] == "sidecar" and metrics["K_source"] == "json"
