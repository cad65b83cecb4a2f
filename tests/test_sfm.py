"""Tests of the sfm stage: a rendered orbit video through frames + sfm, against the true poses."""
from __future__ import annotations

import json
import logging
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from benchmarks.lib.evaluation import pose_errors, registered_viewmats
from stages.contract.errors import StageError
from stages.engine.context import Context
from stages.frames import run as frames
from stages.records.sfm import SfmRecord
from stages.sfm import run as sfm
from stages.sfm.spec import SfmConfig
from tests.factories.orbits import render_orbit_video



def make_ctx(stage: str, inputs: dict, out: Path, **params) -> Context:
    out.mkdir(parents=True, exist_ok=True)
    return Context(stage=stage, item="boxes", params=params, inputs=inputs, out=out, seed=1)


@pytest.fixture(scope="module")
def orbit(tmp_path_factory) -> tuple[Path, dict]:
    """A 36-frame 320x240 orbit video (10 degree steps) and its true poses."""
    folder = tmp_path_factory.mktemp("orbit")
    truth = render_orbit_video(folder / "orbit.mp4", 36, 320, 240)
    return folder / "orbit.mp4", truth


@pytest.fixture(scope="module")
def orbit_frames(orbit, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("frames")
    frames.run(make_ctx("frames", {"video": orbit[0]}, out))
    return out


def test_orbit_registers_with_true_poses(orbit, orbit_frames, tmp_path):
    """frames -> sfm on a rendered orbit: all frames register and poses match the truth."""
    out = tmp_path / "sfm"
    metrics = sfm.run(make_ctx("sfm", {"frames": orbit_frames}, out, matching="sequential",
                               sequential_overlap=6, loop_closure_frames=3, num_threads=1,
                               robust_fallback=False))
    assert metrics["total"] == 36
    assert metrics["registered"] >= 34
    assert metrics["mean_reprojection_error_px"] < 1.5
    assert metrics["matching"] == "sequential"
    # COLMAP 4 also writes rigs.bin and frames.bin beside the three classic files
    assert {"cameras.bin", "images.bin", "points3D.bin"} <= {p.name for p in (out / "sparse").iterdir()}
    assert len(list((out / "images").glob("*.jpg"))) == metrics["registered"]
    record = SfmRecord.read(out)  # the record every reader goes through reads what the stage wrote
    assert record.summary == json.loads(json.dumps(metrics)) and metrics["points"] > 100
    assert len(record.scene().frames) == metrics["registered"]
    assert sorted(p.name for p in out.iterdir()) == ["images", "sfm.json", "sparse"]

    rec = pycolmap.Reconstruction(out / "sparse")
    camera = next(iter(rec.cameras.values()))
    assert camera.model_name == "PINHOLE"
    assert camera.focal_length_x == pytest.approx(orbit[1]["K"][0, 0], rel=0.03)

    entries = {Path(e["file"]).name: e["source_index"] for e in json.loads((orbit_frames / "frames.json").read_text())}
    estimated = registered_viewmats(out)
    names = sorted(estimated)
    errors = pose_errors(np.stack([estimated[n] for n in names]),
                         orbit[1]["viewmats"][[entries[n] for n in names]])
    assert errors["rotation_deg_max"] < 2.0
    assert errors["position_pct_max"] < 2.0


def test_known_intrinsics_are_kept(orbit, orbit_frames, tmp_path):
    """Known intrinsics give a fixed PINHOLE camera with exactly those values."""
    fx, cx, cy = orbit[1]["K"][0, 0], orbit[1]["K"][0, 2], orbit[1]["K"][1, 2]
    out = tmp_path / "sfm"
    metrics = sfm.run(make_ctx("sfm", {"frames": orbit_frames}, out, intrinsics=[fx, fx, cx, cy],
                               matching="sequential", sequential_overlap=6, num_threads=1, robust_fallback=False))
    assert metrics["camera"]["model"] == "PINHOLE"
    assert metrics["camera"]["params"] == pytest.approx([fx, fx, cx, cy], abs=1e-3)
    assert metrics["registered"] >= 34


def test_default_sfm_is_bit_reproducible(orbit_frames, tmp_path):
    """With the default single thread, two runs write byte-identical COLMAP models (one cache key, one result)."""
    models = []
    for run in ("first", "second"):
        metrics = sfm.run(make_ctx("sfm", {"frames": orbit_frames}, tmp_path / run, matching="sequential",
                                   sequential_overlap=6, robust_fallback=False))
        assert metrics["bit_reproducible"] and metrics["source_camera"]["model"] == "SIMPLE_RADIAL"
        models.append({p.name: p.read_bytes() for p in (tmp_path / run / "sparse").iterdir()})
    assert models[0] == models[1]


def test_sequential_pairs_window_and_loop():
    names = [f"{i}.jpg" for i in range(10)]
    pairs = sfm.sequential_pairs(names, overlap=2, loop_frames=2)
    assert ("0.jpg", "1.jpg") in pairs and ("0.jpg", "2.jpg") in pairs and ("0.jpg", "3.jpg") not in pairs
    assert {("0.jpg", "8.jpg"), ("0.jpg", "9.jpg"), ("1.jpg", "8.jpg"), ("1.jpg", "9.jpg")} <= set(pairs)
    assert len(pairs) == len(set(pairs)) == 9 + 8 + 4
    quadratic = sfm.sequential_pairs(names, overlap=2, loop_frames=2, quadratic=True)
    assert set(quadratic) - set(pairs) == {(f"{i}.jpg", f"{i + step}.jpg") for step in (4, 8) for i in range(10 - step)
                                           if (i, i + step) not in {(0, 8), (1, 9)}}  # (0, 8), (1, 9): loop pairs


def test_auto_matching_is_exhaustive_for_short_inputs():
    cfg = SfmConfig(exhaustive_max_images=5, sequential_overlap=2)
    assert sfm.plan_matching([f"{i}.jpg" for i in range(5)], cfg, robust=False).mode == "exhaustive"
    plan = sfm.plan_matching([f"{i}.jpg" for i in range(8)], cfg, robust=False)
    assert plan.mode == "sequential" and ("0.jpg", "2.jpg") in plan.pairs
    assert sfm.plan_matching([f"{i}.jpg" for i in range(8)], cfg, robust=True).mode == "exhaustive"


def test_unregistrable_frames_fail_the_quality_gate(tmp_path):
    """Frames of pure noise cannot be matched: StageError naming the source and what to do."""
    rng = np.random.default_rng(0)
    folder = tmp_path / "noise"
    folder.mkdir()
    for index in range(10):
        cv2.imwrite(str(folder / f"{index:02d}.png"), rng.integers(0, 255, (120, 160, 3), dtype=np.uint8))
    frames.run(make_ctx("frames", {"video": folder}, tmp_path / "frames", duplicate_threshold=0))
    with pytest.raises(StageError, match=r"noise.*slower camera motion"):
        sfm.run(make_ctx("sfm", {"frames": tmp_path / "frames"}, tmp_path / "sfm", num_threads=1,
                         robust_fallback=False))


def test_missing_frames_folder_is_an_error(tmp_path):
    with pytest.raises(StageError, match="not a frames output"):
        sfm.run(make_ctx("sfm", {"frames": tmp_path / "nothing"}, tmp_path / "sfm"))


@pytest.mark.heavy
def test_plush_dog_registers(tmp_path, real):
    """The real capture registers with the defaults: all 84 photos kept, >= 95 % registered; takes minutes."""
    images = real / "plush_dog" / "images"
    frames.run(make_ctx("frames", {"video": images}, tmp_path / "frames"))
    metrics = sfm.run(make_ctx("sfm", {"frames": tmp_path / "frames"}, tmp_path / "sfm"))
    logging.getLogger(__name__).info("plush dog: %s", metrics)
    assert metrics["total"] == 84 and metrics["registered"] >= 0.95 * 84
    assert metrics["mean_reprojection_error_px"] < 1.5
