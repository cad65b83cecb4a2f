"""Stress cases of issue 9 (`+experiment=stability`) on the real stages, with tiny inputs.

Each test pins what a stress input does: a clear StageError naming the file, a counted fallback, or a
result. The input builders (tests/factories/) are shared with benchmarks/stability.py, which runs the
same cases larger and writes the table in benchmarks/results/stability.md.
"""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmarks.lib.evaluation import score
from stages.contract.errors import StageError
from stages.extract import run as extract
from stages.frames import run as frames
from stages.lib.gaussians.ply import read_ply
from stages.lib.objects.pointcloud import nearest_distance
from tests.factories.backgrounds import write_background
from tests.factories.media import noise_video
from tests.factories.orbits import render_orbit_video
from tests.factories.runs import depth_planes_compose, frames_sfm_run, stage_ctx
from tests.factories.splats import synthetic_scene, write_splat_folder

TINY_ORBIT = {"num_frames": 36, "width": 240, "height": 180}  # 10 degree steps: registers in ~3 s
SFM_FAST = {"num_threads": 1, "robust_fallback": False}


def test_few_frames_is_a_clear_frames_error(tmp_path):
    """Case 1: a 5-frame capture (< frames.min_frames = 8) stops in frames, naming the video."""
    video = tmp_path / "short_capture.mp4"
    render_orbit_video(video, 5, 160, 120)
    with pytest.raises(StageError, match=r"short_capture\.mp4 gives 5 usable frames, at least 8 are needed: "
                                         r"only 5 frames could be read"):
        frames.run(stage_ctx("frames", {"video": video}, tmp_path / "frames"))


def test_plain_white_floor_uses_the_object_base_plane(tmp_path):
    """Case 3: a splat whose white floor got only 300 Gaussians: no RANSAC plane, the plane at the object's
    base is used (and reported), and the object is still cut out."""
    scene = synthetic_scene(seed=1, floor_points=300)
    scene.colors[:300] = 1.0                                      # the floor Gaussians come first
    write_splat_folder(tmp_path / "splat", scene)
    metrics = extract.run(stage_ctx("extract", {"splat": tmp_path / "splat"}, tmp_path / "out"))
    assert metrics["plane_source"] == "object_base"
    assert json.loads((tmp_path / "out" / "extract.json").read_text())["plane_source"] == "object_base"
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
    """Case 5: no sidecar and bg_depth.model=none: bg_depth writes provider "none" (no depth.npy), planes
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
                             {"duplicate_threshold": 0}, SFM_FAST)
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
