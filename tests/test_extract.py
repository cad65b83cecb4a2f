"""Tests of the `extract` stage: synthetic scenes with a known object, degenerate inputs, run() end to end."""
from __future__ import annotations

import json

import numpy as np
import pytest

from benchmarks.lib.evaluation import angle_deg, score
from stages.contract.errors import StageError
from stages.engine.context import Context
from stages.extract.run import run
from stages.extract.spec import ExtractConfig
from stages.lib.gaussians.ply import read_ply
from stages.lib.objects.clusters import STEPS, pick_central_cluster, regrow
from stages.lib.objects.cut import extract_object
from stages.lib.objects.pointcloud import nearest_distance, ransac_plane
from tests.factories.splats import scene_intrinsics, synthetic_scene, write_splat_folder



def _extract(scene, **params):
    return extract_object(scene.means, scene.opacities, scene.scales, ExtractConfig(**params), scene.viewmats, seed=0)


@pytest.mark.parametrize("variant", [{}, {"wall_points": 20000}], ids=["textured_floor", "room_walls"])
def test_separates_object_from_textured_floor(variant):
    scene = synthetic_scene(seed=3, **variant)
    extraction = _extract(scene)
    figures = score(extraction.keep, scene.is_object)
    assert figures["precision"] >= 0.98 and figures["recall"] >= 0.95, figures
    assert extraction.plane_source == "ransac"
    assert angle_deg(extraction.normal, scene.normal) < 2.0
    assert extraction.height == pytest.approx(scene.height, rel=0.1)  # faint halo on top must not count
    # the base point lies on the floor under the object's axis (object radius is 0.1 m before scaling)
    assert np.linalg.norm(extraction.base_point - scene.base_point) < 0.05 * scene.height / 0.3
    counts = extraction.counts
    assert counts["removed_below_plane"] >= 150  # the 200 floaters under the floor (some within the margin)
    assert counts["kept"] + sum(counts[f"removed_{step}"] for step in STEPS[1:]) == counts["total"]


def test_a_layer_over_a_fuzzy_floor_does_not_cut_the_base_off():
    """An under-trained floor's upper layer (an eighth of its Gaussians, 3.5 cm up; seen in the captures of seeds 104
    and 105) is a smaller plane over the floor that the object's base reaches under: the floor stays the support,
    and the object's lowest part stays in the cut."""
    scene = synthetic_scene(seed=2, transform=False)
    rng = np.random.default_rng(0)
    angle, distance = rng.uniform(0, 2 * np.pi, 2500), 1.5 * np.sqrt(rng.uniform((0.1 / 1.5) ** 2, 1, 2500))
    layer = np.stack([distance * np.cos(angle), distance * np.sin(angle), rng.normal(0.035, 0.002, 2500)], 1)
    means = np.concatenate([scene.means, layer])
    opacities = np.concatenate([scene.opacities, rng.uniform(0.3, 1.0, 2500)])
    scales = np.concatenate([scene.scales, np.full((2500, 3), 0.004)])
    is_object = np.concatenate([scene.is_object, np.zeros(2500, dtype=bool)])
    lowest = is_object & (means[:, 2] > 0.005) & (means[:, 2] < 0.035)  # above the floor plane's 5 mm, under the layer
    extraction = extract_object(means, opacities, scales, ExtractConfig(), scene.viewmats, seed=0)
    assert extraction.plane_source == "ransac" and extraction.keep[lowest].mean() > 0.99
    assert score(extraction.keep, is_object)["precision"] > 0.95
    layer_taken = extract_object(means, opacities, scales, ExtractConfig(max_core_below_smaller=0.25),
                                 scene.viewmats, seed=0)  # the largest plane's limit takes the layer for the support
    assert layer_taken.keep[lowest].mean() < 0.1


def test_plain_floor_falls_back_to_the_object_base():
    scene = synthetic_scene(seed=1, floor_points=300)
    extraction = _extract(scene)
    figures = score(extraction.keep, scene.is_object)
    assert extraction.plane_source == "object_base"
    assert figures["precision"] >= 0.98 and figures["recall"] >= 0.95, figures
    assert angle_deg(extraction.normal, scene.normal) < 2.0


def test_faint_gaussians_under_a_plain_floor_do_not_lower_the_ground():
    """Never-seen Gaussians under the floor keep their faint initial opacity (splat_train's object seeds):
    the plane is fit to opaque Gaussians only (the old lowest-layer fallback sank when fit to all of them)."""
    scene = synthetic_scene(seed=1, floor_points=300, transform=False)
    rng = np.random.default_rng(5)
    direction = rng.normal(size=(1500, 3))
    direction[:, 2] = -np.abs(direction[:, 2])
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    unseen = direction * 0.35 * rng.uniform(0, 1, (1500, 1)) ** (1 / 3) + [0.0, 0.0, -0.005]  # [1500, 3]
    means = np.concatenate([scene.means, unseen]).astype(np.float32)
    opacities = np.concatenate([scene.opacities, np.full(1500, 0.01)]).astype(np.float32)
    scales = np.concatenate([scene.scales, np.full((1500, 3), 0.01)]).astype(np.float32)
    is_object = np.concatenate([scene.is_object, np.zeros(1500, dtype=bool)])
    extraction = extract_object(means, opacities, scales, ExtractConfig(), scene.viewmats)
    assert extraction.height == pytest.approx(scene.height, rel=0.1)
    assert score(extraction.keep, is_object)["precision"] >= 0.995


def test_statistical_filter_ratio_is_configurable():
    scene = synthetic_scene(seed=2)
    gentle = _extract(scene, stat_std_ratio=3.0, regrow_fraction=0.0).counts["removed_stat"]
    paper = _extract(scene, stat_std_ratio=0.1, regrow_fraction=0.0).counts["removed_stat"]
    assert paper > gentle


def test_central_cluster_beats_a_ring_around_the_object():
    rng = np.random.default_rng(0)
    blob = rng.normal(0, 0.05, (200, 3))
    angle = rng.uniform(0, 2 * np.pi, 2000)
    ring = np.stack([np.cos(angle), np.sin(angle), np.zeros_like(angle)], 1)  # centroid at the origin too
    points = np.concatenate([ring, blob])
    labels = np.concatenate([np.zeros(2000, dtype=np.int64), np.ones(200, dtype=np.int64)])
    keep = pick_central_cluster(points, labels, np.zeros(3))
    assert keep[2000:].all() and not keep[:2000].any()


def test_object_split_into_pieces_stays_whole():
    rng = np.random.default_rng(1)
    body = rng.normal(0, 0.05, (1000, 3)) + [0.12, 0, 0]  # the object's body, slightly off-centre
    fragment = rng.normal(0, 0.005, (50, 3)) + [-0.02, 0, 0]  # a piece of its side, nearest the centre
    far_noise = rng.normal(0, 0.01, (80, 3)) + [1.5, 0, 0]
    points = np.concatenate([body, fragment, far_noise])
    labels = np.repeat([0, 1, 2], [1000, 50, 80])
    keep = pick_central_cluster(points, labels, np.zeros(3), merge_distance=0.09)
    assert keep[:1050].all() and not keep[1050:].any()
    assert pick_central_cluster(points, labels, np.zeros(3))[1000:1050].all()  # without joining: the fragment only


def test_regrow_gives_back_sparse_neighbours_only():
    kept = np.stack([np.linspace(0, 1, 50), np.zeros(50), np.zeros(50)], axis=1)  # [50, 3] the object
    near, far = [[0.5, 0.1, 0.0]], [[0.5, 0.5, 0.0]]
    points = np.concatenate([kept, near, near, far, far])  # [54, 3]
    removed_by = np.array([0] * 50 + [STEPS.index("stat"), STEPS.index("cluster")] * 2)
    noise = np.zeros(54, dtype=bool)
    noise[[51, 53]] = True  # the cluster-removed ones were DBSCAN noise
    assert sorted(regrow(points, removed_by, 0.15, noise)) == [50, 51]
    assert sorted(regrow(points, removed_by, 0.15)) == [50]  # noise not offered: only the stat one
    assert sorted(regrow(points, removed_by, 0.05, noise)) == []


def _with_sparse_room(scene, rng, count: int = 12000):
    """The untransformed synthetic scene plus a sparse room of background Gaussians above the floor,
    none within 0.35 m of the object's axis, a third of them faint (a densified background's floaters)."""
    room = rng.uniform([-1.5, -1.5, 0.05], [1.5, 1.5, 1.2], (3 * count, 3))
    room = room[np.linalg.norm(room[:, :2], axis=1) > 0.35][:count]  # [count, 3]
    opacities = np.where(rng.random(count) < 1 / 3, rng.uniform(0.01, 0.15, count), rng.uniform(0.3, 1.0, count))
    return (np.concatenate([scene.means, room]).astype(np.float32),
            np.concatenate([scene.opacities, opacities]).astype(np.float32),
            np.concatenate([scene.scales, np.full((count, 3), 0.004)]).astype(np.float32),
            np.concatenate([scene.is_object, np.zeros(count, dtype=bool)]))


def test_sparse_background_does_not_widen_the_cluster_radius():
    scene = synthetic_scene(seed=3, transform=False)
    means, opacities, scales, is_object = _with_sparse_room(scene, np.random.default_rng(4))
    central = extract_object(means, opacities, scales, ExtractConfig(), scene.viewmats)
    whole = extract_object(means, opacities, scales, ExtractConfig(spacing_radius=0.0), scene.viewmats,
                           enforce_checks=False)
    assert score(central.keep, is_object)["precision"] >= 0.98 and score(central.keep, is_object)["recall"] >= 0.95
    assert whole.dbscan_eps > 2 * central.dbscan_eps  # spacing over the whole room: the radius balloons ...
    assert score(whole.keep, is_object)["precision"] < 0.9  # ... and the room joins the object ...
    assert "footprint" in whole.checks["refused"] and "footprint" not in central.checks.get("refused", "")
    with pytest.raises(StageError, match="self-check, footprint: its footprint radius is"):  # ... which is refused
        extract_object(means, opacities, scales, ExtractConfig(spacing_radius=0.0), scene.viewmats)


def test_ransac_plane_is_seeded_and_finds_the_dominant_plane():
    rng = np.random.default_rng(3)
    tilt = np.deg2rad(10.0)
    normal = np.array([0.0, np.sin(tilt), np.cos(tilt)])  # [3]
    basis = np.linalg.svd(normal[None])[2][1:]  # [2, 3] in-plane axes
    floor = rng.uniform(-1, 1, (3000, 2)) @ basis + 0.5 * normal + rng.normal(0, 0.002, (3000, 1)) * normal
    wall = rng.uniform(-1, 1, (1500, 3)) * [0.005, 1, 1] + [1.0, 0, 0]  # a smaller plane x = 1
    clutter = rng.uniform(-1, 1, (1500, 3))
    points = np.concatenate([floor, wall, clutter])  # [6000, 3]
    plane, inliers = ransac_plane(points, 0.01, 300, seed=5)
    again, again_inliers = ransac_plane(points, 0.01, 300, seed=5)
    assert np.array_equal(plane, again) and np.array_equal(inliers, again_inliers)
    assert angle_deg(plane[:3] * np.sign(plane[:3] @ normal), normal) < 0.5
    assert inliers[:3000].mean() > 0.99 and inliers[3000:4500].mean() < 0.05
    with pytest.raises(ValueError, match="collinear"):
        ransac_plane(np.outer(np.arange(10.0), [1, 2, 3]), 0.01, 50, seed=0)


def test_flat_scene_fails_clearly():
    rng = np.random.default_rng(0)
    means = np.concatenate([rng.uniform(-1, 1, (5000, 2)), np.zeros((5000, 1))], 1)  # the z = 0 floor only
    cameras = synthetic_scene(seed=0, transform=False).viewmats  # z up, looking at the floor's centre
    with pytest.raises(StageError, match="plane step removed 5000 of 5000"):
        extract_object(means, np.ones(5000), np.full((5000, 3), 0.01), ExtractConfig(), cameras)


@pytest.mark.parametrize("count", [0, 20])
def test_too_few_gaussians_fail_clearly(count):
    with pytest.raises(StageError, match=f"only {count} Gaussians"):
        extract_object(np.zeros((count, 3)), np.ones(count), np.ones((count, 3)), ExtractConfig())


def test_already_cut_object_fails_clearly():
    scene = synthetic_scene(seed=0, floor_points=0, halo_points=0, floater_points=0)
    with pytest.raises(StageError, match="removed only"):
        _extract(scene)


def test_run_writes_object_ply_json_and_panels(tmp_path):
    scene = synthetic_scene(seed=4)
    write_splat_folder(tmp_path / "splat", scene)
    out = tmp_path / "out"
    out.mkdir()
    ctx = Context(stage="extract", item="cylinder", params={}, inputs={"splat": tmp_path / "splat"}, out=out)
    metrics = run(ctx)
    summary = json.loads((out / "extract.json").read_text())
    obj = read_ply(out / "object.ply")
    assert obj.num == metrics["kept"] == summary["counts"]["kept"]
    kept = nearest_distance(scene.means, obj.means.numpy()) == 0  # [N] scene Gaussians written to object.ply
    figures = score(kept, scene.is_object)
    assert figures["precision"] >= 0.98 and figures["recall"] >= 0.95, figures
    assert angle_deg(np.asarray(summary["normal"]), scene.normal) < 2.0
    assert summary["height"] == pytest.approx(scene.height, rel=0.3)
    assert summary["scene_scale"] > 0 and len(summary["base_point"]) == 3
    assert (out / "filtering.png").stat().st_size > 10_000


GREY = [0.7, 0.7, 0.7]


def _grey_room(scene) -> tuple[np.ndarray, np.ndarray]:
    """Colours [N, 3] and scales [N, 3] of a synthetic scene whose floor and walls are grey and covered by their
    Gaussians (so the background renders grey behind the object); the object keeps its own."""
    background = ~scene.is_object[:, None]
    return np.where(background, GREY, scene.colors), np.where(background, 0.03, scene.scales)


def _grey_and_green(scene, grey: np.ndarray, green: np.ndarray, opacities: np.ndarray, scale: float):
    """The scene in its grey room (_grey_room) with Gaussians added beside the object: `grey` [M, 3] in the room's
    colour, then `green` [M, 3] in a leaf's; opacities [2M], all `scale` wide. Returns its means, opacities, scales
    (float32) and colours, the masks [N] of the grey and the green ones, and the object's mask [N]."""
    colors, scales = _grey_room(scene)
    added = len(grey) + len(green)
    means = np.concatenate([scene.means, grey, green]).astype(np.float32)
    colors = np.concatenate([colors, np.repeat([GREY], len(grey), axis=0), np.repeat([[0.2, 0.7, 0.2]], len(green), 0)])
    grey_mask, green_mask = np.zeros((2, len(means)), dtype=bool)
    grey_mask[len(scene.means):len(scene.means) + len(grey)] = True
    green_mask[len(scene.means) + len(grey):] = True
    return (means, np.concatenate([scene.opacities, opacities]).astype(np.float32),
            np.concatenate([scales, np.full((added, 3), scale)]).astype(np.float32), colors, grey_mask, green_mask,
            np.concatenate([scene.is_object, np.zeros(added, dtype=bool)]))


def test_background_haze_beside_the_object_goes_and_a_leaf_stays():
    """A wall-coloured haze of semi-transparent Gaussians touching the object's side (a trained scene's stand-in
    for the wall behind it; the real plush dog at 320 px) and a green "leaf" of the same shape on the other side:
    the clusters keep both, since they touch the body in 3D. In the capture views both lie outside the solid
    body's silhouette; the haze has the background's colour there and goes, the leaf does not and stays."""
    scene = synthetic_scene(seed=4, transform=False, wall_points=20000)
    rng = np.random.default_rng(9)
    direction = rng.normal(size=(600, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    cloud = direction * 0.045 * rng.uniform(0, 1, (600, 1)) ** (1 / 3)  # [600, 3] m
    sides = np.repeat([[0.155, 0.0, 0.18], [-0.155, 0.0, 0.18]], 300, axis=0)  # from 0.11 m off the axis
    means, opacities, scales, colors, haze, leaf, is_object = _grey_and_green(
        scene, (sides + cloud)[:300], (sides + cloud)[300:], rng.uniform(0.2, 0.45, 600), 0.01)
    blind = extract_object(means, opacities, scales, ExtractConfig(), scene.viewmats)
    assert blind.keep[haze].mean() > 0.9 and blind.keep[leaf].mean() > 0.9  # what the clusters leave
    seeing = extract_object(means, opacities, scales, ExtractConfig(), scene.viewmats,
                            intrinsics=scene_intrinsics(scene), colors=colors)
    assert seeing.keep[haze].mean() < 0.3, seeing.keep[haze].mean()
    assert seeing.keep[leaf].mean() > 0.9, seeing.keep[leaf].mean()
    assert seeing.counts["removed_background_haze"] >= 0.7 * 300
    assert score(seeing.keep, is_object)["recall"] >= 0.95
    off = extract_object(means, opacities, scales, ExtractConfig(silhouette_distance=0.0), scene.viewmats,
                         intrinsics=scene_intrinsics(scene), colors=colors)
    assert np.array_equal(off.keep, blind.keep)


def test_a_solid_backdrop_coloured_sheet_joined_to_the_object_goes_and_a_solid_fin_stays():
    """A solid sheet with the colour of the room, standing out from the object's side (the real_dog experiment's
    dog: a backdrop stand-in the splat grew beside it), and a solid green fin of the same shape on the other side. Both
    are opaque and touch the body, so the clusters and the haze test (which takes them for body) keep them; in the
    capture views the sheet changes nothing where it lies, outside the object's visible footprint, and goes."""
    scene = synthetic_scene(seed=4, transform=False, wall_points=20000)
    rng = np.random.default_rng(11)
    slab = rng.uniform([0.1, -0.01, 0.12], [0.24, 0.01, 0.26], (800, 3))  # [800, 3] m, from the cylinder's +x side
    means, opacities, scales, colors, sheet, leaf, is_object = _grey_and_green(
        scene, slab, slab * [-1.0, 1.0, 1.0], rng.uniform(0.6, 1.0, 1600), 0.008)  # the fin: on its -x side
    cameras = {"intrinsics": scene_intrinsics(scene), "colors": colors}
    blind = extract_object(means, opacities, scales, ExtractConfig(max_outside_share=1.0), scene.viewmats, **cameras)
    assert blind.keep[sheet].mean() > 0.9 and blind.keep[leaf].mean() > 0.9, blind.counts  # what the others leave
    seeing = extract_object(means, opacities, scales, ExtractConfig(), scene.viewmats, **cameras)
    assert seeing.keep[sheet].mean() < 0.3, seeing.keep[sheet].mean()
    assert seeing.keep[leaf].mean() > 0.9, seeing.keep[leaf].mean()
    assert seeing.counts["removed_outside_footprint"] >= 0.7 * 800
    assert score(seeing.keep, is_object)["recall"] >= 0.95


@pytest.mark.parametrize("object_colour", [None, [0.72, 0.72, 0.72]], ids=["its_own", "the_room_grey"])
def test_the_footprint_carve_leaves_a_clean_cut_as_it_is(object_colour):
    """Without a cloud, the carve finds a few Gaussians at most (fewer than a DBSCAN cluster's minimum) and carves
    none: the cut is the one without it (the default job's five objects and their object.ply, byte-identical). An
    object coloured like the room lies outside its own footprint everywhere: the views cannot tell, nothing goes."""
    scene = synthetic_scene(seed=4, transform=False, wall_points=20000)
    colors, scales = _grey_room(scene)
    if object_colour is not None:
        colors[scene.is_object] = object_colour
    cameras = {"intrinsics": scene_intrinsics(scene), "colors": colors}
    carving = extract_object(scene.means, scene.opacities, scales, ExtractConfig(), scene.viewmats, **cameras)
    without = extract_object(scene.means, scene.opacities, scales, ExtractConfig(max_outside_share=1.0),
                             scene.viewmats, **cameras)
    assert carving.counts["removed_outside_footprint"] == 0 and np.array_equal(carving.keep, without.keep)


def test_a_floor_coloured_semi_transparent_base_is_left_to_the_support_checks():
    """The object's lowest band semi-transparent and coloured like the floor (a tapering plant pot's bottom on a
    brown rug): in side views it lies outside the solid body's silhouette with the background's colour, yet it
    stands in the body's footprint below its middle, so the haze test leaves it (the base checks judge it)."""
    scene = synthetic_scene(seed=4, transform=False, wall_points=20000)
    colors, scales = _grey_room(scene)
    band = scene.is_object & (scene.means[:, 2] < 0.09)  # the lowest 30 % of the cylinder's side
    opacities = scene.opacities.copy()
    opacities[band] = np.random.default_rng(3).uniform(0.2, 0.45, band.sum())
    colors[band] = GREY
    extraction = extract_object(scene.means, opacities, scales, ExtractConfig(), scene.viewmats,
                                intrinsics=scene_intrinsics(scene), colors=colors, enforce_checks=False)
    assert extraction.keep[band].mean() > 0.9, extraction.keep[band].mean()


def test_a_sparse_faint_base_is_not_halo():
    """One side of the object's lowest band seen by few cameras and trained into few, large, faint Gaussians (a
    plant pot's bottom in the sample's other renders): the lowest of them lie farther than the cluster radius
    from any opaque Gaussian, as halo does, but over the body's footprint below its middle. The halo step keeps
    them; a halo above the floor beside the object still goes."""
    scene = synthetic_scene(seed=4, transform=False)
    rng = np.random.default_rng(5)
    band = scene.is_object & (scene.means[:, 2] < 0.05) & (scene.means[:, 0] < 0)  # [N] a sixth of the height
    rows = ~(band & (rng.uniform(size=len(band)) > 0.12))  # thinned out to one in eight
    means, opacities, scales = scene.means[rows], scene.opacities[rows].copy(), scene.scales[rows].copy()
    band, is_object = band[rows], scene.is_object[rows]
    opacities[band] = rng.uniform(0.05, 0.19, band.sum())  # below halo_opacity
    scales[band] = 0.012
    lowest = band & (means[:, 2] < 0.03)  # [N] farther than the cluster radius from the opaque side above
    extraction = extract_object(means, opacities, scales, ExtractConfig(), scene.viewmats)
    assert extraction.keep[band].mean() > 0.85 and extraction.keep[lowest].mean() > 0.8, extraction.removed_by[band]
    assert score(extraction.keep, is_object)["precision"] > 0.99  # the halo (scene.halo) still goes


def test_run_reports_missing_scene(tmp_path):
    ctx = Context(stage="extract", item="nothing", params={}, inputs={"splat": tmp_path}, out=tmp_path)
    with pytest.raises(StageError, match="scene.ply not found"):
        run(ctx)


def test_flat_sheet_discs_around_the_base_are_support():
    """A plain sheet whose few Gaussians are flat discs (the real plush dog's case): no RANSAC plane, the
    object-base plane, and the discs lying on it go with the plane instead of framing the object."""
    scene = synthetic_scene(seed=1, floor_points=300, transform=False)
    means, scales = scene.means.copy(), scene.scales.copy()
    means[:300, 2] += 0.01  # the floor Gaussians come first: a sheet lying 1 cm above the object's base ...
    scales[:300] = [0.03, 0.03, 0.001]  # ... of wide, flat, horizontal discs
    extraction = extract_object(means, scene.opacities, scales, ExtractConfig(), scene.viewmats)
    assert extraction.plane_source == "object_base"
    assert extraction.counts["removed_flat_contact"] > 0
    assert not extraction.keep[:300].any()
    assert score(extraction.keep, scene.is_object)["recall"] >= 0.95


def test_a_fallback_through_the_object_fails_naming_object_step_and_fix(tmp_path):
    """An object-base plane at the middle of the object (base_percentile 50, as a core split at a thin waist
    would give) cuts it: run() stops with the object's name, the step and what to do, instead of handing on
    half an object. (Here the layer check fires first: the removed layer is thick against what is left; with
    a thinner contact layer the cut-density check does.)"""
    write_splat_folder(tmp_path / "splat", synthetic_scene(seed=1, floor_points=300))
    for params, failure in (({}, "removed a layer 27% of the object's height thick"),
                            ({"contact_layer": 0.5}, "cut into the object")):
        ctx = Context(stage="extract", item="cylinder", params={"base_percentile": 50.0, **params},
                      inputs={"splat": tmp_path / "splat"}, out=tmp_path / str(len(params)))
        with pytest.raises(StageError, match=rf"extract\[cylinder\].*the plane step {failure}.*"
                                             r"objects\[\]\.up in the data config"):
            run(ctx)


def test_model_without_cameras_keeps_the_object_and_takes_up_from_the_config(tmp_path):
    """A given model (objects[].splat) of an object on a textured floor, without cameras: up from up_hint,
    the floor removed, the object kept whole; without up_hint the largest plane gives the same up. (The model
    is taken to be the object: a halo linked to it would stay, so this one has none.)"""
    scene = synthetic_scene(seed=3, halo_points=0)
    write_splat_folder(tmp_path / "splat", scene)
    model = tmp_path / "splat" / "scene.ply"
    results = []
    for name, params in (("hint", {"up_hint": scene.normal.tolist()}), ("estimated", {})):
        out = tmp_path / name
        out.mkdir()
        run(Context(stage="extract", item="cylinder", params=params, inputs={"model": model}, out=out))
        kept = nearest_distance(scene.means, read_ply(out / "object.ply").means.numpy()) == 0
        figures = score(kept, scene.is_object)
        assert figures["precision"] >= 0.98 and figures["recall"] >= 0.95, (name, figures)
        results.append(json.loads((out / "extract.json").read_text()))
    assert all(angle_deg(np.asarray(r["normal"]), scene.normal) < 2.0 for r in results)


def test_cut_out_model_without_up_fails_clearly(tmp_path):
    scene = synthetic_scene(seed=0, floor_points=0, halo_points=0, floater_points=0)
    write_splat_folder(tmp_path / "splat", scene)
    ctx = Context(stage="extract", item="cylinder", params={}, inputs={"model": tmp_path / "splat" / "scene.ply"},
                  out=tmp_path)
    with pytest.raises(StageError, match=r"extract\[cylinder\].*no up direction.*objects\[\]\.up"):
        run(ctx)


@pytest.mark.parametrize("model", ["plush_dog/inria_point_cloud.ply", "splats/plant.splat"])
def test_real_models_without_cameras_stay_whole(model, tmp_path, real):
    """Given models (objects[].splat) of the plush dog (3DGS PLY, cleaned by hand) and a plant (.splat, object
    only), up -y from the config: the support layer under them goes, almost all the rest stays."""
    path = real / model
    metrics = run(Context(stage="extract", item=path.stem, params={"up_hint": [0.0, -1.0, 0.0]},
                          inputs={"model": path}, out=tmp_path))
    record = json.loads((tmp_path / "extract.json").read_text())
    assert metrics["plane_source"] == "object_base"
    assert metrics["kept"] > 0.9 * metrics["total"]  # the models are already cut out: little should go
    assert angle_deg(np.asarray(record["normal"]), np.array([0.0, -1.0, 0.0])) < 1e-6


def test_mask_fringe_below_the_base_is_counted_in_rows():
    from benchmarks.lib.cut_scoring import below_bottom_px
    truth = np.zeros((20, 10), bool)
    truth[5:15, 2:8] = True
    fringe = truth.copy()
    fringe[15:17, 2:8] = True                                    # two rows under the base
    beside = truth.copy()
    beside[15:18, 0:2] = True                                    # under no column of the object
    assert below_bottom_px(truth, truth) == 0.0
    assert below_bottom_px(fringe, truth) == 2.0
    assert below_bottom_px(beside, truth) == 0.0
