"""benchmarks/opensplat.py's parts: the reasons it skips, the COLMAP project it hands OpenSplat (the training
frames only, every SfM point), the PLY count it reads, its summary rows; and, on demand (heavy: a build of some
three minutes), OpenSplat built from ../shared/third_party and trained a few steps on a synthetic capture."""
from __future__ import annotations

import pycolmap
import pytest
import torch

import benchmarks.lib.opensplat_build as opensplat_build
from benchmarks.lib.splat_runs import held_out_psnr
from benchmarks.opensplat import ours_settings, summary_rows
from stages.lib.gaussians.ply import write_ply
from stages.records.sfm import SfmRecord
from tests.factories.splats import orbit_viewmats, random_blob_scene, write_synthetic_sfm

WIDTH, HEIGHT = 64, 48


@pytest.fixture(scope="module")
def sfm_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("synthetic") / "sfm"
    K = torch.tensor([[60.0, 0, WIDTH / 2], [0, 60.0, HEIGHT / 2], [0, 0, 1]])
    write_synthetic_sfm(root, random_blob_scene(150, seed=2), orbit_viewmats(10, radius=3.2, height=1.2), K,
                        WIDTH, HEIGHT, num_points=120, seed=3)
    return root


def test_a_missing_archive_is_named_as_the_reason(tmp_path):
    missing = tmp_path / "opensplat-1.2.0.tar.gz"
    assert str(missing) in opensplat_build.missing_build_dependency(missing)


def test_the_project_holds_the_training_frames_and_every_point(sfm_dir, tmp_path):
    record = SfmRecord.read(sfm_dir)
    train_names = {f"{i:04d}.png" for i in range(10) if i % 3}
    project = opensplat_build.colmap_project(record.sparse_dir, record.images_dir, train_names, tmp_path / "p")
    model = pycolmap.Reconstruction(str(project / "sparse" / "0"))
    assert {image.name for image in model.images.values()} == train_names
    assert model.num_points3D() == pycolmap.Reconstruction(str(record.sparse_dir)).num_points3D() == 120
    assert {path.name for path in (project / "images").iterdir()} == train_names
    assert all((project / "images" / name).read_bytes() == (record.images_dir / name).read_bytes()
               for name in train_names)
    with pytest.raises(ValueError, match="0042.png"):
        opensplat_build.colmap_project(record.sparse_dir, record.images_dir, {"0042.png"}, tmp_path / "q")


def test_the_ply_count_is_the_header_s(tmp_path):
    write_ply(tmp_path / "scene.ply", random_blob_scene(37, seed=1))
    assert opensplat_build.ply_vertex_count(tmp_path / "scene.ply") == 37
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nend_header\n")
    with pytest.raises(ValueError, match="bad.ply"):
        opensplat_build.ply_vertex_count(tmp_path / "bad.ply")


def test_summary_compares_each_variant_with_ours_at_its_thread_count():
    runs = [{"trainer": "ours", "threads": 1, "seconds_per_step": 0.02, "num_gaussians": 900, "held_out_psnr": 25.0},
            {"trainer": "ours", "threads": 1, "seconds_per_step": 0.04, "num_gaussians": 1100, "held_out_psnr": 25.2},
            {"trainer": "opensplat", "threads": 1, "seconds_per_step": 0.12, "num_gaussians": 500,
             "held_out_psnr": 25.2},
            {"trainer": "opensplat", "threads": 1, "seconds_per_step": 0.08, "num_gaussians": 500,
             "held_out_psnr": 25.4},
            {"trainer": "ours", "threads": 2, "seconds_per_step": 0.02, "num_gaussians": 1000, "held_out_psnr": 24.0},
            {"trainer": "opensplat", "threads": 2, "seconds_per_step": 0.05, "num_gaussians": 400,
             "held_out_psnr": 24.5}]
    one, two = summary_rows(runs)
    assert (one["threads"], one["speedup"], one["psnr_gap_db"], one["ours_gaussians"]) == (1, 3.33, -0.2, 1000)
    assert one["met"]  # 3.33x and 0.2 dB below
    assert (two["threads"], two["speedup"], two["psnr_gap_db"], two["met"]) == (2, 2.5, -0.5, False)


def test_a_changed_setting_of_ours_is_compared_beside_the_defaults():
    settings = ours_settings({"prune_opacity": 0.005, "iterations": 2000}, [("prune_opacity", 0.05)])
    assert settings == {"ours": {"prune_opacity": 0.005, "iterations": 2000},
                        "ours: prune_opacity=0.05": {"prune_opacity": 0.05, "iterations": 2000}}
    runs = [{"trainer": "ours", "threads": 1, "seconds_per_step": 0.04, "num_gaussians": 900, "held_out_psnr": 25.0},
            {"trainer": "ours: prune_opacity=0.05", "threads": 1, "seconds_per_step": 0.02, "num_gaussians": 500,
             "held_out_psnr": 25.1},
            {"trainer": "opensplat", "threads": 1, "seconds_per_step": 0.1, "num_gaussians": 400,
             "held_out_psnr": 25.0}]
    defaults, changed = summary_rows(runs)
    assert (defaults["ours"], defaults["speedup"], defaults["met"]) == ("ours", 2.5, False)
    assert (changed["ours"], changed["speedup"], changed["psnr_gap_db"], changed["met"]) == (
        "ours: prune_opacity=0.05", 5.0, 0.1, True)


def test_an_unknown_setting_or_a_value_unlike_its_default_is_refused_by_name():
    with pytest.raises(SystemExit, match="--ours-set prune_opacty=...: 'prune_opacty' is not a setting"):
        ours_settings({"prune_opacity": 0.005}, [("prune_opacty", 0.05)])
    with pytest.raises(SystemExit, match="'low' is not a float like its default 0.005"):
        ours_settings({"prune_opacity": 0.005}, [("prune_opacity", "low")])


@pytest.mark.heavy
def test_opensplat_builds_and_trains_on_a_capture(sfm_dir, tmp_path):
    missing = opensplat_build.missing_build_dependency()
    if missing:
        pytest.skip(missing)
    binary = opensplat_build.build(tmp_path / "opensplat")
    record = SfmRecord.read(sfm_dir)
    names = {f"{i:04d}.png" for i in range(10)}
    project = opensplat_build.colmap_project(record.sparse_dir, record.images_dir, names - {"0000.png"},
                                             tmp_path / "project")
    run = opensplat_build.train(binary, project, 30, 1.0, {0}, tmp_path / "scene.ply")
    assert run.steps == 30 and run.seconds_per_step > 0 and run.num_gaussians > 0
    # its scene is in the capture's frame: rendered at the held-out frame it draws the blobs, far above noise
    assert held_out_psnr(run.ply, sfm_dir, ["0000.png"], WIDTH, "cpu") > 14.0
