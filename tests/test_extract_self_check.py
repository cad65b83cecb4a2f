"""Extract's self-check (stages/lib/objects/self_check.py): a cut the capture cameras did not film is refused or
replaced by the next cluster, never handed on; a good cut passes with its figures in extract.json."""
from __future__ import annotations

import json

import numpy as np
import pytest

from benchmarks.lib.evaluation import score
from stages.contract.errors import StageError
from stages.engine.context import Context
from stages.extract.run import run
from stages.extract.spec import ExtractConfig
from stages.lib.objects.cut import extract_object
from stages.lib.objects.self_check import SelfCheckConfig, failed_checks, footprint_radius, view_share, wall_share
from stages.lib.geometry import look_at_viewmat
from tests.factories.hard_cuts import bridged_scene, ring_scene, wall_scene
from tests.factories.splats import SCENE_IMAGE_SIZE, SCENE_K, scene_intrinsics, synthetic_scene, write_splat_folder


def _cut(scene, enforce_checks: bool = True, **params):
    return extract_object(scene.means, scene.opacities, scene.scales, ExtractConfig(**params), scene.viewmats,
                          seed=0, intrinsics=scene_intrinsics(scene), colors=scene.colors,
                          enforce_checks=enforce_checks)


def test_view_share_counts_the_views_whose_image_holds_a_point():
    eyes = [np.array([1.0, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])]
    viewmats = np.stack([look_at_viewmat(eye, np.zeros(3)) for eye in eyes])  # all three look at the origin
    Ks, sizes = np.tile(SCENE_K, (3, 1, 1)), np.tile(SCENE_IMAGE_SIZE, (3, 1))
    assert view_share(np.zeros((5, 3)), viewmats, Ks, sizes) == 1.0
    behind_first = np.array([[3.0, 0.0, 0.0]])  # behind camera 1, far out of frame of camera 3, seen by camera 2
    assert view_share(behind_first, viewmats, Ks, sizes) == pytest.approx(1 / 3)


def test_footprint_radius_is_the_90th_percentile_distance_from_the_vertical_axis():
    rng = np.random.default_rng(0)
    angle = rng.uniform(0, 2 * np.pi, 10000)
    ring = np.stack([0.3 * np.cos(angle), 0.3 * np.sin(angle), rng.uniform(0, 5, 10000)], 1)  # tall: height ignored
    assert footprint_radius(ring + [2.0, -1.0, 0.0], np.array([0.0, 0.0, 1.0])) == pytest.approx(0.3, abs=0.01)


def test_wall_share_counts_an_upright_plane_seen_from_one_side_only():
    """A blob (the object) with a patch of wall behind it: filmed from the front (a half orbit) the wall counts;
    filmed all around, a plane through the same points has cameras on both sides and nothing counts; a level
    patch (a table top, cameras above it) never counts."""
    rng = np.random.default_rng(4)
    blob = rng.normal(0.0, 0.05, (500, 3))
    wall = np.stack([np.full(800, 0.15), rng.uniform(-0.3, 0.3, 800), rng.uniform(-0.3, 0.3, 800)], 1)
    up = np.array([0.0, 0.0, 1.0])
    front = np.stack([[-np.cos(a), np.sin(a), 0.1] for a in np.linspace(-1.2, 1.2, 20)])  # x < 0: the room side
    around = np.stack([[np.cos(a), np.sin(a), 0.3] for a in np.linspace(0, 2 * np.pi, 24, endpoint=False)])
    points = np.concatenate([blob, wall])
    assert wall_share(points, up, front, 0.01, seed=0) == pytest.approx(800 / 1300, abs=0.02)
    assert wall_share(points, up, around, 0.01, seed=0) == 0.0
    table = wall[:, [1, 2, 0]] * [1, 1, 0] + [0, 0, -0.1]  # the same patch lying level under the blob
    assert wall_share(np.concatenate([blob, table]), up, front + [0, 0, 0.5], 0.01, seed=0) == 0.0


def test_a_good_cut_passes_with_its_figures():
    extraction = _cut(synthetic_scene(seed=3))
    checks = extraction.checks
    assert checks["candidate"] == 0 and "refused" not in checks and "passed_over" not in checks
    assert checks["view_share"] == 1.0 and checks["footprint"] < 0.2 and checks["look_at_gap"] < 1.0
    assert 0.0 < checks["kept_share"] < 0.3
    assert checks["wall_share"] == 0.0  # filmed all around: no plane through it has every camera on one side
    assert min(checks[f"margin_{name}"] for name in ("view_share", "look_at_gap", "footprint", "wall_share")) > 0.3


def test_an_object_on_a_plain_sheet_is_most_of_its_scene_and_passes():
    """Few floor Gaussians: the object is 80 % of the scene. kept_share is reported, not checked."""
    extraction = _cut(synthetic_scene(seed=1, floor_points=300))
    assert extraction.checks["kept_share"] > 0.7 and "refused" not in extraction.checks


def test_an_object_hanging_on_a_wall_is_refused():
    """No floor: the plane is the box's own base, the wall stays with it (84 % of the scene, every support check
    passes); the self-check refuses it, naming what failed."""
    scene = wall_scene()
    looked_at = _cut(scene, enforce_checks=False)
    assert looked_at.plane_source == "object_base" and looked_at.checks["kept_share"] > 0.8
    assert looked_at.checks["footprint"] > 1.0 and looked_at.checks["view_share"] < 0.5
    with pytest.raises(StageError, match=r"self-check, view_share: .*footprint: .*standing on a surface"):
        _cut(scene)


def test_the_next_cluster_replaces_one_the_cameras_do_not_aim_at():
    """The pebble lies nearer the look-at point than the ring around it, but is far from it for its size; the
    ring, the next cluster, passes and is kept, and extract.json says why."""
    scene = ring_scene()
    extraction = _cut(scene)
    assert extraction.checks["candidate"] == 1
    assert extraction.checks["passed_over"].startswith("look_at_gap: the cameras' look-at point lies")
    figures = score(extraction.keep, scene.is_object)
    assert figures["recall"] >= 0.8 and figures["precision"] >= 0.9, figures  # its bottom goes with the floor
    only_nearest = _cut(scene, enforce_checks=False, self_check_candidates=1)  # no other candidate: refused
    assert only_nearest.checks["refused"].startswith("extract: the cut fails its self-check, look_at_gap")
    assert only_nearest.keep[scene.is_object].mean() < 0.1


def test_clutter_bridged_to_the_object_is_cut_off_at_a_tighter_radius():
    """A rod of points (a chair's leg, say) joins a box of clutter to the object at the DBSCAN radius: the cut is as
    wide as the orbit and fails the footprint check, no other cluster passes, and the nearest cluster at 0.75x the
    radius is the object alone (seed 114's vase). With no tighter radius the cut is refused."""
    alone = _cut(bridged_scene(None))
    rod_step = 0.2 * alone.dbscan_eps * alone.scene_scale  # a rod dense enough to bridge at the radius, not at 3/4
    scene = bridged_scene(rod_step)
    extraction = _cut(scene)
    assert extraction.checks["radius_scale"] == 0.75 and extraction.checks["candidate"] == 0
    assert extraction.checks["passed_over"].startswith("footprint:")
    figures = score(extraction.keep, scene.is_object)
    assert figures["precision"] > 0.95 and figures["recall"] > 0.95, figures
    bridged = _cut(scene, enforce_checks=False, self_check_tighter=1.0)
    assert bridged.checks["refused"].startswith("extract: the cut fails its self-check, footprint")
    assert score(bridged.keep, scene.is_object)["precision"] < 0.7


def test_failed_checks_name_each_figure_beyond_its_limit():
    cfg = SelfCheckConfig()
    assert failed_checks({"view_share": 1.0, "look_at_gap": 0.1, "footprint": 0.1, "kept_share": 0.9}, cfg) == []
    failures = failed_checks({"view_share": 0.5, "look_at_gap": 2.0, "footprint": 0.5, "wall_share": 0.3}, cfg)
    assert [failure.split(":")[0] for failure in failures] == ["view_share", "look_at_gap", "footprint", "wall_share"]
    assert "30% of it lies on one upright surface" in failures[-1]
    with pytest.raises(ValueError, match="min_view_share"):
        SelfCheckConfig(min_view_share=1.5)


def test_the_stage_refuses_the_wall_and_writes_the_figures_of_a_good_cut(tmp_path):
    """run(): the refusal names the item and the scene file and writes nothing; a good cut's extract.json holds
    the self-check's figures and its panel the kept set."""
    for name, scene in (("wall", wall_scene()), ("good", synthetic_scene(seed=3))):
        write_splat_folder(tmp_path / name, scene)
        (tmp_path / f"out_{name}").mkdir()
    wall = Context(stage="extract", item="clock", params={}, inputs={"splat": tmp_path / "wall"},
                   out=tmp_path / "out_wall")
    with pytest.raises(StageError, match=r"extract\[clock\] \(.*scene.ply\): extract: the cut fails its self-check"):
        run(wall)
    assert not any((tmp_path / "out_wall").iterdir())
    run(Context(stage="extract", item="can", params={}, inputs={"splat": tmp_path / "good"}, out=tmp_path / "out_good"))
    checks = json.loads((tmp_path / "out_good" / "extract.json").read_text())["checks"]
    assert {"view_share", "look_at_gap", "footprint", "kept_share", "candidate"} <= set(checks)
    assert (tmp_path / "out_good" / "filtering.png").stat().st_size > 10000
