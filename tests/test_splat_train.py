"""The splat_train stage on a rendered synthetic scene written as a real COLMAP model (pycolmap)."""
from __future__ import annotations

import json
import shutil
from dataclasses import asdict

import numpy as np
import pycolmap
import pytest
import torch

from stages.app.pipeline import build_graph
from stages.contract.errors import StageError
from stages.engine.context import Context
from stages.engine.scheduler import Engine
from stages.lib.gaussians import rasterize
from stages.lib.gaussians.ply import read_ply
from stages.lib.gaussians.rasterize_gsplat import gsplat_unavailable
from stages.splat_train import run as splat_train
from stages.splat_train.spec import CUDA_BUDGET, SplatTrainConfig, for_device
from tests.factories.configs import ROOT, compose_cfg
from tests.factories.splats import orbit_viewmats, random_blob_scene, write_synthetic_sfm

WIDTH, HEIGHT = 48, 36
# A few dozen iterations at 40x30: faster rates and a gradient threshold for such tiny images.
PARAMS = dict(iterations=40, train_long_side=40, sh_degree=1, sh_degree_every=10, densify_from=5,
              densify_until=25, densify_every=10, grad_threshold=2e-3, opacity_reset_every=0, eval_every=10,
              lr_opacity=0.2, lr_sh_dc=0.02, max_gaussians=400, plateau_patience=0, backend="auto")


@pytest.fixture(scope="module")
def sfm_dir(tmp_path_factory):
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("synthetic") / "sfm"
    K = torch.tensor([[52.0, 0, WIDTH / 2], [0, 52.0, HEIGHT / 2], [0, 0, 1]])
    write_synthetic_sfm(root, random_blob_scene(150, seed=2), orbit_viewmats(12, radius=3.2, height=1.2), K,
                        WIDTH, HEIGHT, num_points=120, point_noise=0.05, seed=3)
    return root


def run_stage(sfm, out, device="cpu", **overrides):
    out.mkdir(parents=True, exist_ok=True)
    ctx = Context(stage="splat_train", item="blobs", params={**PARAMS, **overrides}, inputs={"sfm": sfm},
                  out=out, seed=7, device=device)
    return splat_train.run(ctx)


def test_splat_train_writes_contract_outputs(sfm_dir, tmp_path):
    metrics = run_stage(sfm_dir, tmp_path / "out")
    stats = json.loads((tmp_path / "out" / "train_stats.json").read_text())
    curve = [p for _, p in stats["psnr_curve"]]
    assert curve[-1] > curve[0] + 1.0, curve
    assert metrics["final_psnr"] == curve[-1] and metrics["iterations_run"] == 40
    assert stats["train_resolution"] == [40, 30] and stats["num_held_out"] == 2  # frames 0 and 8 of 12
    assert stats["seconds_per_iteration"] > 0 and len(stats["gaussian_curve"]) == len(curve)

    scene = read_ply(tmp_path / "out" / "scene.ply")
    assert scene.num == metrics["num_gaussians"] and 120 < scene.num <= 400 and scene.sh_degree == 1
    assert torch.isfinite(scene.means).all()

    cameras = json.loads((tmp_path / "out" / "cameras.json").read_text())
    assert (cameras["width"], cameras["height"]) == (WIDTH, HEIGHT)
    assert cameras["held_out"] == ["0000.png", "0008.png"] and len(cameras["frames"]) == 12
    reconstruction = pycolmap.Reconstruction(str(sfm_dir / "sparse"))
    image = reconstruction.find_image_with_name("0005.png")
    frame = next(f for f in cameras["frames"] if f["file"] == "0005.png")
    np.testing.assert_allclose(np.asarray(frame["viewmat"])[:3], image.cam_from_world().matrix(), atol=1e-9)
    np.testing.assert_allclose(frame["K"], reconstruction.cameras[1].calibration_matrix(), atol=1e-9)


def test_seeds_fade_out_where_sfm_already_fills_the_seed_ball():
    counts = [splat_train.seed_count(3000, in_ball, 1500, 3000) for in_ball in (0, 1160, 1500, 2250, 2847, 3000, 5000)]
    assert counts == [3000, 3000, 3000, 1500, 306, 0, 0]
    assert splat_train.seed_count(400, 1160, 1500, 3000) == 400  # the point counts, not the budget, decide
    with pytest.raises(ValueError, match="seed_fade_to"):
        splat_train.seed_count(3000, 0, 1500, 1500)


def test_object_seed_points_fill_the_ball_reproducibly():
    centre = np.array([1.0, -2.0, 0.5])
    points = splat_train.object_seed_points(centre, 0.3, 4000, seed=5)  # [4000, 3]
    radii = np.linalg.norm(points - centre, axis=1)
    assert points.shape == (4000, 3) and radii.max() <= 0.3
    assert abs(np.median(radii) - 0.3 * 0.5 ** (1 / 3)) < 0.01  # uniform in volume, not clumped at the centre
    np.testing.assert_array_equal(points, splat_train.object_seed_points(centre, 0.3, 4000, seed=5))
    assert not np.array_equal(points, splat_train.object_seed_points(centre, 0.3, 4000, seed=6))


def test_splat_train_seeds_the_object_ball(sfm_dir, tmp_path):
    run_stage(sfm_dir, tmp_path / "none", seed_share=0.0, iterations=1, densify_until=0)
    run_stage(sfm_dir, tmp_path / "seeded", seed_share=1.0, iterations=1, densify_until=0)
    run_stage(sfm_dir, tmp_path / "filled", seed_share=1.0, iterations=1, densify_until=0, seed_fade_from=50,
              seed_fade_to=100)
    plain, seeded, filled = (json.loads((tmp_path / name / "train_stats.json").read_text())
                             for name in ("none", "seeded", "filled"))
    assert plain["num_seed_points"] == 0 and seeded["num_seed_points"] == 400  # 1.0 x max_gaussians 400
    assert filled["num_seed_points"] == 0  # its 120 SfM points, all in the ball, reach seed_fade_to
    assert seeded["num_sfm_points"] == plain["num_sfm_points"] == 120
    scene = read_ply(tmp_path / "seeded" / "scene.ply")
    assert scene.num == 520  # nothing pruned in one step; the seeds are the last rows and start faint
    assert float(scene.opacities[-400:].max()) < 0.02 < float(scene.opacities[:120].min())
    # in the ball of seed_radius x mean camera distance (= focus_radius / its factor) around the look-at point
    defaults = SplatTrainConfig()
    radius = defaults.seed_radius * seeded["focus_radius"] / defaults.focus_radius
    offsets = scene.means[-100:].detach().numpy() - np.asarray(seeded["focus_centre"])  # [100, 3]
    assert np.linalg.norm(offsets, axis=1).max() <= 1.01 * radius


def test_splat_train_resumes_from_checkpoint_dir(sfm_dir, tmp_path):
    ckpt = tmp_path / "ckpt"
    short = run_stage(sfm_dir, tmp_path / "a", iterations=10, densify_until=8, densify_every=4, eval_every=5,
                      checkpoint_dir=str(ckpt))
    assert short["iterations_run"] == 10 and len(list(ckpt.glob("blobs-*.pt"))) == 1
    longer = run_stage(sfm_dir, tmp_path / "b", iterations=20, densify_until=8, densify_every=4, eval_every=5,
                       checkpoint_dir=str(ckpt))
    stats = json.loads((tmp_path / "b" / "train_stats.json").read_text())
    assert stats["resumed_from"] == 10 and longer["iterations_run"] == 20
    assert [it for it, _ in stats["psnr_curve"]][:3] == [0, 5, 10]  # the first run's curve carried over


class ThreadSwitchingContext(Context):
    """A Context whose progress loops change torch's thread count at every step (1, 2, 3, ...), as the
    engine's elastic lanes may (stages/engine/worker_lanes.py)."""

    def progress(self, iterable, **kwargs):
        for step, item in enumerate(super().progress(iterable, **kwargs)):
            torch.set_num_threads(1 + step % 3)
            yield item


def test_splat_train_gives_the_same_bits_when_threads_change_while_it_runs(sfm_dir, tmp_path):
    """What lets the engine give splat_train the cores of idle lanes (Stage.elastic_threads)."""
    run_stage(sfm_dir, tmp_path / "one")
    ctx = ThreadSwitchingContext(stage="splat_train", item="blobs", params=PARAMS, inputs={"sfm": sfm_dir},
                                 out=tmp_path / "switching", seed=7)
    ctx.out.mkdir()
    try:
        splat_train.run(ctx)
    finally:
        torch.set_num_threads(1)
    assert (tmp_path / "one" / "scene.ply").read_bytes() == (tmp_path / "switching" / "scene.ply").read_bytes()
    one, switching = (json.loads((tmp_path / name / "train_stats.json").read_text()) for name in ("one", "switching"))
    assert one["psnr_curve"] == switching["psnr_curve"]


def test_splat_train_bad_inputs_name_the_path(sfm_dir, tmp_path):
    broken = tmp_path / "no_sparse"
    shutil.copytree(sfm_dir / "images", broken / "images")
    shutil.copy(sfm_dir / "sfm.json", broken / "sfm.json")
    with pytest.raises(StageError, match=str(broken / "sparse")):
        run_stage(broken, tmp_path / "out1")
    missing_image = tmp_path / "missing_image"
    shutil.copytree(sfm_dir, missing_image)
    (missing_image / "images" / "0003.png").unlink()
    with pytest.raises(StageError, match="0003.png"):
        run_stage(missing_image, tmp_path / "out2")


def test_cuda_budget_applies_only_on_a_gpu():
    params = asdict(SplatTrainConfig())
    on_cpu, on_gpu = for_device(params, "cpu"), for_device(params, "cuda")
    assert "cuda" not in on_cpu and "cuda" not in on_gpu
    assert on_cpu == {k: v for k, v in params.items() if k != "cuda"}  # the CPU settings as they were
    assert {k: on_gpu[k] for k in params["cuda"]} == params["cuda"] == CUDA_BUDGET
    assert on_gpu["train_long_side"] > on_cpu["train_long_side"]  # the capture's own resolution
    assert {k: v for k, v in on_gpu.items() if k != "train_long_side"} == {
        k: v for k, v in on_cpu.items() if k != "train_long_side"}  # today's schedule (longer ones lose on the dog)


def test_unknown_cuda_settings_fail_naming_them():
    params = asdict(SplatTrainConfig())
    with pytest.raises(ValueError, match=r"splat_train.cuda: unknown settings \['iteratons'\]"):
        for_device({**params, "cuda": {"iteratons": 5000}}, "cpu")
    with pytest.raises(ValueError, match="iteratons"):  # a key added on the command line: at start-up
        build_graph(compose_cfg(["+splat_train.cuda.iteratons=5000"]), ROOT, "cpu")
    with pytest.raises(Exception, match="iteratons"):  # without the +, Hydra refuses a key the budget lacks
        compose_cfg(["splat_train.cuda.iteratons=5000"])


def test_each_device_has_its_own_cache_keys(tmp_path):
    """The budgets differ, so do the keys of splat_train and what reads it; the CPU keys stay as they were
    without a GPU budget (a `cuda` override does not touch them)."""
    keys = {}
    for name, overrides, device in (("cpu", [], "cpu"), ("cuda", [], "cuda"),
                                    ("cpu, other cuda budget", ["splat_train.cuda.iterations=123"], "cpu")):
        engine = Engine(tmp_path / "cache")
        graph = build_graph(compose_cfg(overrides), ROOT, device)
        keys[name] = {(n.stage.name, n.item): engine.key(n) for nodes in graph.nodes.values() for n in nodes}
    item = compose_cfg([]).data.objects[0].name
    assert keys["cpu"][("sfm", item)] == keys["cuda"][("sfm", item)]
    assert keys["cpu"][("splat_train", item)] != keys["cuda"][("splat_train", item)]
    assert keys["cpu"][("extract", item)] != keys["cuda"][("extract", item)]
    assert keys["cpu"] == keys["cpu, other cuda budget"]


GSPLAT_GPU = pytest.mark.skipif(
    not torch.cuda.is_available() or gsplat_unavailable(torch.device("cuda"), torch.float32) is not None,
    reason="no CUDA device, or gsplat cannot run here (pip install -e \".[gpu]\"; its build needs nvcc)")


@pytest.mark.parametrize("device, backends", [("cpu", ("cpp", "torch")),
                                              pytest.param("cuda", ("cuda", "gsplat"), marks=GSPLAT_GPU)])
def test_splat_train_gives_the_same_psnr_through_both_backends(sfm_dir, tmp_path, device, backends):
    """Without densification: with it, rounding alone sends the two runs to different Gaussian sets (measured:
    cpp and torch, which differ only in float rounding, ended 0.4-0.7 dB apart after 200 iterations, and
    0.003 dB apart without). The densification decisions are compared step by step in
    tests/gaussians/test_rasterize_gsplat.py."""
    if device == "cpu" and rasterize.choose_backend("auto", torch.device("cpu"), torch.float32) != "cpp":
        pytest.skip("the C++ rasterizer is not built here")
    psnr = {}
    for backend in backends:
        metrics = run_stage(sfm_dir, tmp_path / backend, device=device, backend=backend, iterations=150,
                            densify_until=0, eval_every=50)
        curve = [p for _, p in json.loads((tmp_path / backend / "train_stats.json").read_text())["psnr_curve"]]
        assert metrics["iterations_run"] == 150 and curve[-1] > curve[0] + 3.0, curve
        psnr[backend] = metrics["final_psnr"]
    assert abs(psnr[backends[0]] - psnr[backends[1]]) <= 0.3, psnr
