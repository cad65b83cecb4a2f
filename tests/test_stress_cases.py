"""Stress cases of issue 9 (`+experiment=stability`) on the real stages, with tiny inputs.

Each test pins what a stress input does: a clear StageError naming the file, a counted fallback, or a
result. The input builders here are shared with benchmarks/stability.py, which runs the same cases
larger and writes the table in benchmarks/results/stability.md.
"""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from benchmarks.extract import score, synthetic_scene
from stages import bg_depth, compose, extract, frames, planes
from stages.context import Context, StageError
from stages.engine import Engine, Node, Record
from stages.fan_in import fan_in
from stages.gaussians.ply import read_ply, write_ply
from stages.pipeline import STAGES
from stages.pointcloud import nearest_distance
from stages.records.extract import ExtractRecord
from test_compose import make_blob
from test_extract import _write_scene as write_splat_folder
from test_frames import write_video
from test_sfm import render_orbit_video

BLOB_HEIGHT_M = 0.3
TINY_ORBIT = {"num_frames": 36, "width": 240, "height": 180}  # 10 degree steps: registers in ~3 s
SFM_FAST = {"num_threads": 1, "robust_fallback": False}


# ------------------------------------------------------------------------------------ input builders

def stage_ctx(stage: str, inputs: dict, out: Path, params: dict | None = None, item: str = "stress") -> Context:
    """A Context for calling a stage's `run` directly, writing into a fresh `out` folder."""
    out.mkdir(parents=True, exist_ok=True)
    return Context(stage=stage, item=item, params=dict(params or {}), inputs=inputs, out=out, seed=0)


def read_video_frames(path: Path) -> list[np.ndarray]:
    """All frames of a video as BGR uint8 [H, W, 3]."""
    capture = cv2.VideoCapture(str(path))
    images = []
    while True:
        ok, image = capture.read()
        if not ok:
            break
        images.append(image)
    capture.release()
    return images


def blurred_copy(source: Path, target: Path, sigma: float) -> Path:
    """`source` re-encoded with every frame Gaussian-blurred (cv2.GaussianBlur, sigma in pixels)."""
    return write_video(target, [cv2.GaussianBlur(image, (0, 0), sigma) for image in read_video_frames(source)])


def noise_video(path: Path, count: int, width: int, height: int, seed: int = 0) -> Path:
    """`count` frames of independent colour noise: distinct frames that no SfM can match."""
    rng = np.random.default_rng(seed)
    return write_video(path, [rng.integers(0, 256, (height, width, 3), dtype=np.uint8) for _ in range(count)])


def corner_wall_depth(width: int, height: int, K: np.ndarray, corner_distance: float = 3.0) -> np.ndarray:
    """Depth [H, W] (metres) of a room corner seen from inside: two vertical walls at +-45 degrees
    meeting `corner_distance` ahead, no floor or other horizontal surface in view.

    Walls z = corner_distance -+ x; a pixel ray (x', y', 1) hits the nearer one at z = d / (1 + |x'|).
    """
    u = np.arange(width) + 0.5
    x_over_z = (u - K[0, 2]) / K[0, 0]                                   # [W]
    depth_row = corner_distance / (1.0 + np.abs(x_over_z))
    return np.repeat(depth_row[None, :], height, axis=0).astype(np.float32)


def write_background(folder: Path, name: str, width: int, height: int, with_wall_depth: bool) -> dict[str, Path]:
    """A textured photo `<name>.png` with `<name>.json` intrinsics and, optionally, a corner-wall
    `<name>.depth.npy` sidecar. Returns bg_depth's inputs {"image", ["depth"], "intrinsics"}."""
    folder.mkdir(parents=True, exist_ok=True)
    K = np.array([[0.9 * width, 0.0, width / 2], [0.0, 0.9 * width, height / 2], [0.0, 0.0, 1.0]])
    rng = np.random.default_rng(3)
    photo = cv2.resize(rng.integers(40, 220, (height // 8, width // 8, 3), dtype=np.uint8), (width, height),
                       interpolation=cv2.INTER_CUBIC)
    inputs = {"image": folder / f"{name}.png", "intrinsics": folder / f"{name}.json"}
    cv2.imwrite(str(inputs["image"]), photo)
    inputs["intrinsics"].write_text(json.dumps({"K": K.tolist()}))
    if with_wall_depth:
        inputs["depth"] = folder / f"{name}.depth.npy"
        np.save(inputs["depth"], corner_wall_depth(width, height, K))
    return inputs


def write_blob_object(folder: Path) -> Path:
    """An extract output folder (object.ply + extract.json) holding test_compose's opaque cylinder."""
    folder.mkdir(parents=True, exist_ok=True)
    write_ply(folder / "object.ply", make_blob())
    ExtractRecord(np.array([0.0, 0.0, 1.0]), np.zeros(3), 2.0).write(folder)
    return folder


def depth_planes_compose(root: Path, photo: dict[str, Path], num_images: int) -> dict:
    """bg_depth (provider auto, no onnx) -> planes -> compose on one photo; the three stages' metrics."""
    depth_out, planes_out, compose_out = root / "bg_depth", root / "planes", root / "compose"
    depth_metrics = bg_depth.run(stage_ctx("bg_depth", photo, depth_out, {"provider": "auto", "onnx_path": ""}))
    planes_metrics = planes.run(stage_ctx("planes", {"depth": depth_out, "image": photo["image"]}, planes_out))
    compose_inputs = {**fan_in({"blob": {"object": write_blob_object(root / "extract")}}, compose.INPUTS.per_object),
                      **fan_in({"bg": {"background": photo["image"], "planes": planes_out, "depth": depth_out}},
                               compose.INPUTS.per_photo)}
    compose_params = {"objects": [{"name": "blob", "height_m": BLOB_HEIGHT_M}], "num_images": num_images,
                      "preview_count": 2}
    compose_metrics = compose.run(stage_ctx("compose", compose_inputs, compose_out, compose_params))
    return {"bg_depth": depth_metrics, "planes": planes_metrics, "compose": compose_metrics,
            "planes_json": json.loads((planes_out / "planes.json").read_text()),
            "stats_json": json.loads((compose_out / "stats.json").read_text())}


def frames_sfm_run(cache: Path, videos: dict[str, Path], frames_params: dict, sfm_params: dict) -> list[Record]:
    """frames -> sfm nodes per object (the pipeline's stages) in one Engine run with partial=True."""
    targets = []
    for name, video in videos.items():
        frames_node = Node(STAGES["frames"], name, frames_params, {"video": video})
        targets.append(Node(STAGES["sfm"], name, sfm_params, {"frames": frames_node}))
    return Engine(cache, partial=True).run(targets)


# -------------------------------------------------------------------------------------------- tests

def test_few_frames_is_a_clear_frames_error(tmp_path):
    """Case 1: a 5-frame capture (< frames.min_frames = 8) stops in frames, naming the video."""
    video = tmp_path / "short_capture.mp4"
    render_orbit_video(video, 5, 160, 120)
    with pytest.raises(StageError, match=r"short_capture\.mp4 gives 5 usable frames, at least 8 are needed: "
                                         r"only 5 frames could be read"):
        frames.run(stage_ctx("frames", {"video": video}, tmp_path / "frames"))


def test_plain_white_floor_uses_the_camera_up_fallback(tmp_path):
    """Case 3: a splat whose white floor got only 300 Gaussians: no RANSAC plane, the camera-up layer
    fallback is used (and reported), and the object is still cut out."""
    scene = synthetic_scene(seed=1, floor_points=300)
    scene.colors[:300] = 1.0                                      # the floor Gaussians come first
    write_splat_folder(tmp_path / "splat", scene)
    metrics = extract.run(stage_ctx("extract", {"splat": tmp_path / "splat"}, tmp_path / "out"))
    assert metrics["plane_source"] == "camera_up_layer"
    assert json.loads((tmp_path / "out" / "extract.json").read_text())["plane_source"] == "camera_up_layer"
    kept = nearest_distance(scene.means, read_ply(tmp_path / "out" / "object.ply").means.numpy()) == 0
    figures = score(kept, scene.is_object)
    assert figures["precision"] >= 0.98 and figures["recall"] >= 0.95, figures


def test_wall_only_photo_has_no_planes_and_compose_places_at_random(tmp_path):
    """Case 4: a room corner without horizontal surfaces gives "planes": [] and every compose image
    falls back to random placement, counted in stats.json."""
    photo = write_background(tmp_path / "photos", "corner", 160, 120, with_wall_depth=True)
    result = depth_planes_compose(tmp_path, photo, num_images=3)
    assert result["bg_depth"]["provider"] == "sidecar" and result["bg_depth"]["valid_fraction"] == 1.0
    assert result["planes"]["planes"] == 0 and result["planes_json"]["planes"] == []
    stats = result["stats_json"]
    assert stats["placement"] == {"random": 3}
    assert stats["random_placement_fallbacks"] == {"no planes found": 3}
    assert stats["instances"] >= 1


def test_missing_depth_gives_provider_none_and_compose_places_at_random(tmp_path):
    """Case 5: no sidecar and no onnx model: bg_depth writes provider "none" (no depth.npy), planes
    has no planes, compose places every object at random and counts the "no depth" fallback."""
    photo = write_background(tmp_path / "photos", "nodepth", 160, 120, with_wall_depth=False)
    result = depth_planes_compose(tmp_path, photo, num_images=3)
    assert result["bg_depth"]["provider"] == "none" and result["bg_depth"]["valid_fraction"] == 0.0
    assert not (tmp_path / "bg_depth" / "depth.npy").exists()
    assert result["planes"]["up_source"] == "none" and result["planes_json"]["planes"] == []
    stats = result["stats_json"]
    assert stats["placement"] == {"random": 3}
    assert stats["random_placement_fallbacks"] == {"no depth": 3}
    assert stats["instances"] >= 1


def test_object_that_fails_sfm_does_not_stop_the_other(tmp_path):
    """Case 6: of two objects, the noise video fails in sfm with a message naming it; the orbit's
    frames and sfm nodes complete in the same Engine run."""
    orbit = tmp_path / "orbit.mp4"
    render_orbit_video(orbit, TINY_ORBIT["num_frames"], TINY_ORBIT["width"], TINY_ORBIT["height"])
    noise = noise_video(tmp_path / "static_noise.mp4", 10, TINY_ORBIT["width"], TINY_ORBIT["height"])
    records = frames_sfm_run(tmp_path / "cache", {"good": orbit, "bad": noise},
                             {"num_frames": TINY_ORBIT["num_frames"], "duplicate_threshold": 0}, SFM_FAST)
    status = {(r.stage, r.item): r.status for r in records}
    assert status == {("frames", "good"): "ran", ("sfm", "good"): "ran",
                      ("frames", "bad"): "ran", ("sfm", "bad"): "failed"}
    failed = next(r for r in records if r.status == "failed")
    assert "static_noise.mp4" in failed.error and "slower camera motion" in failed.error
    assert "StageError" in failed.traceback
    good = next(r for r in records if r.stage == "sfm" and r.item == "good")
    sfm_json = json.loads((Path(good.path) / "sfm.json").read_text())
    assert sfm_json["registered"] == sfm_json["total"] == TINY_ORBIT["num_frames"]
    assert not (tmp_path / "cache" / "sfm" / failed.key).exists()
