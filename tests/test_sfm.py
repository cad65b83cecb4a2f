"""Tests of the sfm stage: a rendered orbit video through frames + sfm, against the true poses."""
from __future__ import annotations

import json
import logging
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pycolmap
import pytest
from scipy.ndimage import map_coordinates

from benchmarks.poses import pose_errors, registered_viewmats
from stages import frames, sfm
from stages.context import Context, StageError
from stages.geometry import camera_centres, look_at_viewmat

REAL = Path(__file__).resolve().parents[2] / "shared" / "real"


def textured_box_scene(seed: int) -> tuple[o3d.t.geometry.RaycastingScene, np.ndarray, np.ndarray]:
    """A textured ground slab with a few boxes, plus a random colour grid for a solid texture.

    Returns (scene, coarse noise [3, 24, 24, 24], fine noise [3, 72, 72, 72]) over the cube [-1.5, 1.5]^3.
    """
    rng = np.random.default_rng(seed)
    scene = o3d.t.geometry.RaycastingScene()
    boxes = [((3.0, 3.0, 0.1), (-1.5, -1.5, -0.1)), ((0.5, 0.4, 0.6), (-0.3, -0.2, 0.0)),
             ((0.3, 0.3, 0.3), (0.4, 0.3, 0.0)), ((0.25, 0.5, 0.2), (-0.7, 0.4, 0.0))]
    for (sx, sy, sz), corner in boxes:
        box = o3d.geometry.TriangleMesh.create_box(sx, sy, sz).translate(corner)
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(box))
    return scene, rng.random((3, 24, 24, 24)), rng.random((3, 72, 72, 72))


def render_view(scene, coarse: np.ndarray, fine: np.ndarray, K: np.ndarray, viewmat: np.ndarray,
                width: int, height: int) -> np.ndarray:
    """Ray-cast one view; returns a BGR uint8 image [H, W, 3] with solid-noise texture and Lambert shading."""
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    pixels = np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3)     # [H*W, 3]
    cam_dirs = pixels @ np.linalg.inv(K).T
    rotation = viewmat[:3, :3]
    eye = camera_centres(viewmat)
    dirs = cam_dirs @ rotation                                        # world directions [H*W, 3]
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    rays = np.concatenate([np.broadcast_to(eye, dirs.shape), dirs], 1).astype(np.float32)
    hits = scene.cast_rays(o3d.core.Tensor(rays))
    t_hit = hits["t_hit"].numpy()
    hit = np.isfinite(t_hit)
    points = eye + dirs[hit] * t_hit[hit, None]                       # [M, 3]
    colour = np.zeros((len(dirs), 3))
    for grid, weight in ((coarse, 0.6), (fine, 0.4)):
        coords = ((points + 1.5) / 3.0 * (grid.shape[1] - 1)).T        # [3, M]
        colour[hit] += weight * np.stack([map_coordinates(grid[c], coords, order=1) for c in range(3)], 1)
    normals = hits["primitive_normals"].numpy()[hit]
    light = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])
    colour[hit] *= (0.35 + 0.65 * np.abs(normals @ light))[:, None]
    colour[~hit] = 0.55
    image = (colour.reshape(height, width, 3) * 255).clip(0, 255).astype(np.uint8)
    return image[..., ::-1].copy()


def render_orbit_video(path: Path, num_frames: int, width: int, height: int, seed: int = 0,
                       radius: float = 2.6, elevation: float = 1.3) -> dict:
    """Write an mp4v orbit video of the box scene; returns {"K": [3,3], "viewmats": [N,4,4]} (truth)."""
    scene, coarse, fine = textured_box_scene(seed)
    focal = 0.9 * width
    K = np.array([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1.0]])
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (width, height))
    viewmats = []
    for index in range(num_frames):
        angle = 2 * np.pi * index / num_frames
        eye = np.array([radius * np.cos(angle), radius * np.sin(angle), elevation])
        viewmat = look_at_viewmat(eye, np.array([0.0, 0.0, 0.15]))
        writer.write(render_view(scene, coarse, fine, K, viewmat, width, height))
        viewmats.append(viewmat)
    writer.release()
    return {"K": K, "viewmats": np.stack(viewmats)}


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
    frames.run(make_ctx("frames", {"video": orbit[0]}, out, num_frames=36))
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
    assert json.loads((out / "sfm.json").read_text())["points"] == metrics["points"] > 100
    assert sorted(p.name for p in out.iterdir()) == ["images", "sfm.json", "sparse"]

    rec = pycolmap.Reconstruction(out / "sparse")
    camera = next(iter(rec.cameras.values()))
    assert camera.model_name == "PINHOLE"
    assert camera.focal_length_x == pytest.approx(orbit[1]["K"][0, 0], rel=0.03)

    entries = {Path(e["file"]).name: e["source_index"] for e in json.loads((orbit_frames / "frames.json").read_text())}
    estimated = registered_viewmats(out / "sparse")
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


def test_sequential_pairs_window_and_loop():
    names = [f"{i}.jpg" for i in range(10)]
    pairs = sfm.sequential_pairs(names, overlap=2, loop_frames=2)
    assert ("0.jpg", "1.jpg") in pairs and ("0.jpg", "2.jpg") in pairs and ("0.jpg", "3.jpg") not in pairs
    assert {("0.jpg", "8.jpg"), ("0.jpg", "9.jpg"), ("1.jpg", "8.jpg"), ("1.jpg", "9.jpg")} <= set(pairs)
    assert len(pairs) == len(set(pairs)) == 9 + 8 + 4


def test_auto_matching_is_exhaustive_for_short_inputs():
    cfg = sfm.SfmConfig(exhaustive_max_images=5, sequential_overlap=2)
    assert sfm.plan_matching([f"{i}.jpg" for i in range(5)], cfg, robust=False).mode == "exhaustive"
    plan = sfm.plan_matching([f"{i}.jpg" for i in range(8)], cfg, robust=False)
    assert plan.mode == "sequential" and ("0.jpg", "2.jpg") in plan.pairs
    assert sfm.plan_matching([f"{i}.jpg" for i in range(8)], cfg, robust=True).mode == "exhaustive"
    with pytest.raises(StageError, match="unknown matching mode"):
        sfm.plan_matching(["a.jpg"], sfm.SfmConfig(matching="vocab"), robust=False)


def test_unregistrable_frames_fail_the_quality_gate(tmp_path):
    """Frames of pure noise cannot be matched: StageError naming the source and what to do."""
    rng = np.random.default_rng(0)
    folder = tmp_path / "noise"
    folder.mkdir()
    for index in range(10):
        cv2.imwrite(str(folder / f"{index:02d}.png"), rng.integers(0, 255, (120, 160, 3), dtype=np.uint8))
    frames.run(make_ctx("frames", {"video": folder}, tmp_path / "frames", num_frames=10, duplicate_threshold=0))
    with pytest.raises(StageError, match=r"noise.*slower camera motion"):
        sfm.run(make_ctx("sfm", {"frames": tmp_path / "frames"}, tmp_path / "sfm", num_threads=1,
                         robust_fallback=False))


def test_missing_frames_folder_is_an_error(tmp_path):
    with pytest.raises(StageError, match="not a frames output"):
        sfm.run(make_ctx("sfm", {"frames": tmp_path / "nothing"}, tmp_path / "sfm"))


@pytest.mark.heavy
def test_plush_dog_registers(tmp_path):
    """The real capture registers (robust fallback included); takes minutes."""
    images = REAL / "plush_dog" / "images"
    if not images.is_dir():
        pytest.skip("../shared/real not present")
    frames.run(make_ctx("frames", {"video": images}, tmp_path / "frames", num_frames=100))
    metrics = sfm.run(make_ctx("sfm", {"frames": tmp_path / "frames"}, tmp_path / "sfm"))
    logging.getLogger(__name__).info("plush dog: %s", metrics)
    assert metrics["registered"] >= 0.9 * metrics["total"]
    assert metrics["mean_reprojection_error_px"] < 1.5
