"""Tests of the support plane's pieces (stages/lib/objects/support.py): the object-base plane, the contact layer, the
up direction of a model without cameras, and the checks that stop a bad cut."""
from __future__ import annotations

import numpy as np
import pytest

from stages.contract.errors import StageError
from stages.lib.objects import support
from stages.lib.objects.support import GroundPlane, SupportConfig

UP = np.array([0.0, 0.0, 1.0])


def shell(rng: np.random.Generator, count: int, bottom: float, top: float) -> np.ndarray:
    """Points [count, 3] on the side of a cylinder of radius 0.1 about z between the two heights."""
    angle = rng.uniform(0, 2 * np.pi, count)
    return np.stack([0.1 * np.cos(angle), 0.1 * np.sin(angle), rng.uniform(bottom, top, count)], 1)


def test_object_base_plane_sits_at_the_core_percentile():
    core = shell(np.random.default_rng(0), 2000, 0.0, 0.3)
    plane = support.object_base_plane(core, UP, SupportConfig(base_percentile=1.0))
    assert plane.source == "object_base"
    assert plane.height(np.zeros((1, 3)))[0] == pytest.approx(0.0, abs=0.01)


def test_choose_plane_keeps_a_ransac_plane_only_under_the_object():
    core = shell(np.random.default_rng(0), 2000, 0.0, 0.3)
    cfg = SupportConfig()
    floor = GroundPlane(UP, 0.0, "ransac", cfg.plane_distance)  # z = 0: the object rests on it
    assert support.choose_plane(floor, core, UP, cfg) is floor
    deep = GroundPlane(UP, 0.2, "ransac", cfg.plane_distance)  # z = -0.2: a floor under the object's table
    assert support.choose_plane(deep, core, UP, cfg).source == "object_base"
    assert support.choose_plane(None, core, UP, cfg).source == "object_base"


def test_ransac_support_skips_a_plane_through_the_object():
    """Of the planes under the origin, the highest one wins unless the object reaches well below it (another
    surface at the height of the object's middle); a thick floor's upper slab, which a little of the core
    reaches under, still wins over its lower slab."""
    rng = np.random.default_rng(0)
    core = np.concatenate([shell(rng, 2000, -0.4, -0.1), shell(rng, 100, -0.41, -0.4)])  # object on z = -0.4
    cfg = SupportConfig()
    through = (UP, 0.3)  # z = -0.3: a third of the object below it
    floor, lower_slab = (UP, 0.395), (UP, 0.42)
    assert support.ransac_support([through, floor, lower_slab], UP, core, 0.02, cfg).offset == 0.395
    assert support.ransac_support([through], UP, core, 0.02, cfg) is None
    assert support.ransac_support([through], UP, core, 0.02, SupportConfig(max_core_below=0.5)).offset == 0.3


def test_a_smaller_plane_over_the_floor_must_hold_the_object_base():
    """A smaller plane above the largest level one is a table or a mat only when the object rests on it: a plane
    through a fuzzy floor's upper layer, a fifth of the object's height up, cuts its base off, so the floor under
    it wins (captures seed 105's bottle and seed 104's plant); a mat under the object still beats the floor."""
    rng = np.random.default_rng(2)
    core = shell(rng, 2000, -0.4, -0.1)  # the object stands on z = -0.4, 0.3 high
    cfg = SupportConfig()
    floor, fuzz_layer, mat = (UP, 0.4), (UP, 0.34), (UP, 0.405)
    assert support.ransac_support([floor, fuzz_layer], UP, core, 0.02, cfg).offset == 0.4
    assert support.ransac_support([floor, fuzz_layer], UP, core, 0.02, SupportConfig(max_core_below_smaller=0.25)
                                  ).offset == 0.34  # the limit of the largest plane would take the layer
    chosen = support.ransac_support([(UP, 0.41), mat], UP, core, 0.02, cfg)
    assert chosen.offset == 0.405 and chosen.smaller and chosen.core_below_limit(cfg) == cfg.max_core_below_smaller
    assert not support.ransac_support([floor], UP, core, 0.02, cfg).smaller


def test_a_floor_slab_beside_the_object_is_not_the_object_under_the_plane():
    """An under-trained splat's fuzzy floor joins the core around the object, reaching well under the floor plane:
    only what lies under the object's body counts as the object continuing below it."""
    rng = np.random.default_rng(1)
    body = shell(rng, 2000, 0.0, 0.4)  # the object on z = 0
    angle, radius = rng.uniform(0, 2 * np.pi, 1500), rng.uniform(0.15, 0.5, 1500)
    slab = np.stack([radius * np.cos(angle), radius * np.sin(angle), rng.uniform(-0.1, 0.0, 1500)], 1)
    core = np.concatenate([body, slab])
    across = support.plane_coordinates(core, UP)
    assert support.core_base_and_top(core[:, 2], SupportConfig())[0] < -0.09  # the slab's depth: 25 % of 0.4
    assert support.core_below(core[:, 2], across, 0.02, SupportConfig()) == 0.0
    through = core[:, 2] - 0.1  # a plane 0.1 up the object: its lowest quarter below it
    assert support.core_below(through, across, 0.02, SupportConfig()) == pytest.approx(0.25, abs=0.02)


def test_contact_layer_takes_flat_discs_only_on_an_object_base_plane():
    cfg = SupportConfig(contact_layer=2.0)
    heights = np.array([-0.01, 0.01, 0.01, 0.05])  # below; on the plane flat; on the plane round; above the layer
    along = np.array([0.001, 0.001, 0.01, 0.001])
    largest = np.full(4, 0.02)
    base = GroundPlane(UP, 0.0, "object_base", 0.005)
    mask, counts = support.support_mask(base, heights, along, largest, spacing=0.01, cfg=cfg)
    assert mask.tolist() == [True, True, False, False] and counts["removed_flat_contact"] == 1
    ransac = GroundPlane(UP, 0.0, "ransac", 0.005)
    assert support.support_mask(ransac, heights, along, largest, 0.01, cfg)[0].tolist() == [True, False, False, False]
    assert support.layer_thickness(base, 0.01, cfg) == pytest.approx(0.025)
    assert support.layer_thickness(ransac, 0.01, cfg) == pytest.approx(0.005)


def test_gaussians_hanging_under_the_plane_are_support():
    heights = np.array([0.01, 0.01])
    along = np.array([0.003, 0.02])  # 2 sigma reaches 0.004 above / 0.03 below the plane
    assert support.reaching_below(heights, along, spacing=0.01, cfg=SupportConfig()).tolist() == [False, True]


def test_estimated_up_points_to_the_object_side():
    rng = np.random.default_rng(1)
    floor = np.concatenate([rng.uniform(-1, 1, (3000, 2)), np.zeros((3000, 1))], 1)
    points = np.concatenate([floor, shell(rng, 1000, 0.0, 0.3)])
    planes = support.ransac_planes(points, SupportConfig(), seed=0)
    assert support.estimated_up(planes, points, 0.005) @ UP > 0.999
    with pytest.raises(StageError, match="no up direction"):
        support.estimated_up([], points, 0.005)


def test_cut_density_tells_a_plane_under_the_object_from_one_through_it():
    rng = np.random.default_rng(2)
    body = shell(rng, 4000, -0.3, 0.3)  # the object reaches 0.3 under the plane z = 0
    floor = np.concatenate([rng.uniform(-1, 1, (4000, 2)), rng.normal(0, 0.001, (4000, 1))], 1)
    for points, expected in ((np.concatenate([body[body[:, 2] >= 0], floor]), (0.0, 0.1)), (body, (0.7, 1.3))):
        heights = points[:, 2]
        kept, removed = heights >= 0.005, heights < 0.005
        density = support.cut_density(support.plane_coordinates(points, UP), heights, kept, removed,
                                      np.ones(len(points), dtype=bool), band=0.05, thickness=0.005, reach=0.01)
        assert expected[0] <= density <= expected[1]


@pytest.mark.parametrize("layer, density, message", [
    (0.01, 0.0, "base lies .* above the layer"),
    (0.2, 0.0, "removed a layer .* thick"),
    (0.01, 0.9, "cut into the object"),
])
def test_checks_name_the_failure_and_the_fix(layer, density, message):
    base = 0.2 if "base lies" in message else 0.0
    with pytest.raises(StageError, match=message + r".*objects\[\]\.up"):
        support.check_support(GroundPlane(UP, 0.0, "object_base", 0.005), base, 1.2, layer, density, SupportConfig())
    support.check_support(GroundPlane(UP, 0.0, "object_base", 0.005), 0.0, 1.0, 0.01, 0.1, SupportConfig())
    support.check_support(GroundPlane(UP, 0.0, "ransac", 0.005), 0.0, 1.0, 0.01, 0.9,
                          SupportConfig())  # a RANSAC plane is one the cameras saw: its cut density is not enforced


def test_what_the_filters_dropped_under_the_object_comes_back():
    """Under the object's lowest part, down to the removed layer: the sparse bottom of a pot (given back); beside
    the footprint or inside the layer, or not dropped by the filters: left as it is."""
    rng = np.random.default_rng(4)
    body = shell(rng, 800, 0.06, 0.3)  # the kept object starts at 0.06
    low = np.array([[0.0, 0.1, 0.03], [0.0, 0.1, 0.002], [0.5, 0.0, 0.03], [0.0, -0.1, 0.04]])  # under it; in the
    points = np.concatenate([body, low])  # layer; beside its footprint; under it but not dropped by the filters
    heights = points[:, 2]
    kept = np.r_[np.ones(len(body), bool), False, False, False, False]
    filtered = np.r_[np.zeros(len(body), bool), True, True, True, False]
    mask = support.under_object(support.plane_coordinates(points, UP), heights, filtered, kept, np.ones(len(points), bool),
                                layer=0.005, reach=0.03, cfg=SupportConfig())
    assert mask[-4:].tolist() == [True, False, False, False] and not mask[:len(body)].any()


def test_what_runs_off_beside_the_footprint_is_support():
    """In the contact layer of an object-base plane, a Gaussian under the object stays, one 5 spacings off
    its footprint (a sheet's edge) goes; above the layer nothing is touched."""
    rng = np.random.default_rng(3)
    body = shell(rng, 500, 0.03, 0.3)
    low = np.array([[0.1, 0.0, 0.01], [0.16, 0.0, 0.01], [0.0, 0.3, 0.1]])  # under the body, off it, above
    points = np.concatenate([body, low])
    heights, kept = points[:, 2], np.ones(len(points), dtype=bool)
    base = GroundPlane(UP, 0.0, "object_base", 0.005)
    cfg = SupportConfig(contact_layer=2.0, footprint_reach=1.5)
    mask = support.beyond_footprint(support.plane_coordinates(points, UP), heights, kept, kept, base, 0.01, cfg)
    assert mask[-3:].tolist() == [False, True, False] and not mask[:500].any()
    ransac = GroundPlane(UP, 0.0, "ransac", 0.005)
    assert not support.beyond_footprint(support.plane_coordinates(points, UP), heights, kept, kept, ransac, 0.01,
                                        cfg).any()


def test_the_base_is_how_low_the_footprint_reaches_not_where_most_gaussians_are():
    """A pot reaching the plane under a dense crown of leaves: its few low Gaussians set the base; the same
    object cut off at a third of its height, or floating, has its base there."""
    rng = np.random.default_rng(5)
    pot = shell(rng, 60, 0.0, 0.1)  # few Gaussians, radius 0.1
    leaves = np.concatenate([rng.uniform(-0.4, 0.4, (3000, 2)), rng.uniform(0.1, 0.3, (3000, 1))], 1)
    for points, expected in ((np.concatenate([pot, leaves]), 0.0), (leaves, 0.1), (pot + [0, 0, 0.2], 0.2)):
        base = support.footprint_base(support.plane_coordinates(points, UP), points[:, 2])
        assert abs(base - expected) < 0.03, (expected, base)
