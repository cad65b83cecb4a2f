"""compose: placement geometry, occlusion, variants, COCO output and worker independence."""
from __future__ import annotations

import copy
import json
import logging
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from stages.compose import run as compose
from stages.compose.spec import ComposeConfig
from stages.contract.fan_in import input_name
from stages.engine.context import Context
from stages.lib.coco import load_coco, rle_to_mask
from stages.lib.composition.augment import PixelAugStrengths, augment_object
from stages.lib.composition.backgrounds import load_background
from stages.lib.composition.dataset import image_processes
from stages.lib.composition.occlusion import composite_layers, filtered_background_depth, occlude_by_background
from stages.lib.composition.placement import (ObjectFrame, footprint_radius, metric_frame, metric_pose, model_points,
                                              plane_under, pose_on_plane, random_rotation, rotation_aligning,
                                              sample_plane_pose, sample_pose_beside)
from stages.lib.composition.render_object import (object_window, posed_gaussians, render_object_layer, render_window,
                                                  supersample_factor)
from stages.lib.gaussians.model import Gaussians
from stages.lib.gaussians.rasterize import render
from stages.records.depth import DepthRecord
from stages.records.planes import PlacementPlane, PlanesRecord
from tests.factories.backgrounds import (CAMERA_HEIGHT, FLOOR_NORMAL, HEIGHT, K, WIDTH, floor_depth,
                                         write_floor_scene)
from tests.factories.media import write_image
from tests.factories.splats import make_blob

ROOT = Path(__file__).resolve().parents[1]
FRAME = ObjectFrame(np.array([0.0, 0.0, 1.0]), np.zeros(3), 2.0)  # blob: base at 0, up +z, 2 units tall


def variant_settings(variant: str) -> dict:
    """The compose settings a variant file (conf/variant/<variant>.yaml) sets."""
    return OmegaConf.to_container(OmegaConf.load(ROOT / "conf" / "variant" / f"{variant}.yaml").compose)


def params(**overrides) -> dict:
    base = {"objects": [{"name": "blob", "height_m": 0.4}], "num_images": 6, "image_size": None, "preview_count": 4}
    base.update(overrides)
    return base


def test_plane_pose_puts_base_on_point_and_normal_on_plane_normal():
    point = np.array([0.2, 1.0, 3.0])
    pose = pose_on_plane(FRAME, point, FLOOR_NORMAL, 1.1, 0.2)
    assert np.allclose(pose.apply(FRAME.base_point[None])[0], point)
    top = pose.apply((FRAME.base_point + FRAME.height * FRAME.normal)[None])[0]
    assert np.allclose(top - point, 0.4 * FLOOR_NORMAL)  # 2 units * 0.2 = 0.4 m straight up
    assert np.allclose(rotation_aligning(np.array([0, 0, 1.0]), np.array([0, 0, -1.0])) @ [0, 0, 1], [0, 0, -1])
    rotation = random_rotation(np.random.default_rng(3))
    assert np.allclose(rotation @ rotation.T, np.eye(3)) and np.isclose(np.linalg.det(rotation), 1.0)


def test_metric_size_and_near_objects_larger():
    g = make_blob()
    heights = []
    for z in (3.0, 5.0):
        pose = pose_on_plane(FRAME, np.array([0.0, 1.0, z]), FLOOR_NORMAL, 0.0, 0.15)  # 2 units -> 0.3 m
        layer = render_object_layer(g, pose, K, WIDTH, HEIGHT, None, 10**6)
        rows = layer.y0 + np.nonzero((layer.alpha > 0.5).any(axis=1))[0]
        centres = pose.apply(g.means.numpy().astype(np.float64))
        v = K[1, 1] * centres[:, 1] / centres[:, 2] + K[1, 2]  # projected Gaussian centres
        assert abs(rows.min() - v.min()) <= 3.0 and abs(rows.max() - v.max()) <= 3.0
        assert abs(v.max() - (K[1, 2] + K[1, 1] * CAMERA_HEIGHT / (z - 0.075))) <= 1.0  # base on the floor
        assert abs((v.max() - v.min()) - 0.3 * K[1, 1] / z) <= 1.5  # 0.3 m tall at depth z
        heights.append(rows.max() - rows.min() + 1)
    assert heights[0] > 1.4 * heights[1]


def test_opacity_is_the_white_render():
    posed = posed_gaussians(make_blob(), pose_on_plane(FRAME, np.array([0.0, 1.0, 3.0]), FLOOR_NORMAL, 0.4, 0.15))
    out = render(posed, torch.eye(4), torch.as_tensor(K, dtype=torch.float32), WIDTH, HEIGHT)
    white = render(posed, torch.eye(4), torch.as_tensor(K, dtype=torch.float32), WIDTH, HEIGHT,
                   colors=torch.ones(3))
    assert torch.allclose(white.rgb[..., 0], out.alpha, atol=1e-5)


def test_two_object_masks_are_the_visible_alpha_of_a_joint_render():
    g = make_blob()
    front_pose = pose_on_plane(FRAME, np.array([0.0, 1.0, 3.0]), FLOOR_NORMAL, 0.0, 0.3)  # 0.6 m at 3 m
    rear_pose = pose_on_plane(FRAME, np.array([0.12, 1.0, 4.5]), FLOOR_NORMAL, 0.0, 0.2)  # 0.4 m at 4.5 m
    layers = [render_object_layer(g, pose, K, WIDTH, HEIGHT, None, 10**6) for pose in (rear_pose, front_pose)]
    background = np.zeros((HEIGHT, WIDTH, 3), np.float32)
    image, visible = composite_layers(background, layers)
    masks = visible > 0.5
    # independent reference: one joint render, the object of interest white and the other black
    joint = Gaussians.cat([posed_gaussians(g, rear_pose), posed_gaussians(g, front_pose)])
    n_rear = make_blob().num
    for k, is_rear in enumerate((True, False)):
        colours = torch.zeros(joint.num, 3)
        colours[:n_rear] = 1.0 if is_rear else 0.0
        colours[n_rear:] = 0.0 if is_rear else 1.0
        reference = render(joint, torch.eye(4), torch.as_tensor(K, dtype=torch.float32), WIDTH, HEIGHT,
                           colors=colours).rgb[..., 0].numpy() > 0.5
        assert (masks[k] != reference).sum() <= 0.01 * reference.sum() + 2
    alone = np.zeros((HEIGHT, WIDTH), bool)
    rear = layers[0]
    alone[rear.y0:rear.y0 + rear.shape[0], rear.x0:rear.x0 + rear.shape[1]] = rear.alpha > 0.5
    assert masks[0].sum() < alone.sum() - 20  # the rear mask shrank where the front object covers it
    assert not (masks[0] & masks[1]).any()
    assert np.all(image >= 0) and np.all(image <= 1)


def test_near_background_region_occludes_object():
    layer = render_object_layer(make_blob(), pose_on_plane(FRAME, np.array([0.0, 1.0, 3.0]), FLOOR_NORMAL, 0.0, 0.3),
                                K, WIDTH, HEIGHT, None, 10**6)
    depth = floor_depth()
    depth[:, :80] = np.minimum(depth[:, :80], 1.5)  # a near box over the left half of the image
    filtered = filtered_background_depth(depth, 5)
    occluded = occlude_by_background(layer, filtered, 0.03, 0.02)
    columns = np.arange(layer.x0, layer.x0 + layer.shape[1])
    assert occluded.alpha[:, columns < 78].max() == 0.0
    contact_row = int(K[1, 2] + K[1, 1] * CAMERA_HEIGHT / (3.0 + 0.15))  # back of the base (0.15 m radius)
    above = np.arange(layer.y0, layer.y0 + layer.shape[0]) <= contact_row
    right = columns >= 82  # the floor cuts only what lies below the base's contact rows
    assert np.array_equal(occluded.alpha[above][:, right], layer.alpha[above][:, right])
    assert occluded.alpha.sum() < 0.7 * layer.alpha.sum()


def test_missing_depth_never_occludes():
    depth = floor_depth()
    depth[40:80] = 0.0
    filtered = filtered_background_depth(depth, 5)
    assert np.isinf(filtered[45:75]).all()


def test_augmentation_changes_colour_only():
    layer = render_object_layer(make_blob(), pose_on_plane(FRAME, np.array([0.0, 1.0, 3.0]), FLOOR_NORMAL, 0.0, 0.3),
                                K, WIDTH, HEIGHT, None, 10**6)
    augmented = augment_object(layer.rgb, layer.alpha, np.random.default_rng(0), PixelAugStrengths(blur_prob=1.0))
    assert augmented.shape == layer.rgb.shape and np.all(augmented <= layer.alpha[..., None] + 1e-5)
    assert np.abs(augmented - layer.rgb).mean() > 1e-3


def _assets(tmp_path: Path, variant: str, with_planes: bool = True, name: str = "scene") -> compose.ComposeAssets:
    inputs = write_floor_scene(tmp_path / name, with_planes)
    return compose.load_assets(ComposeConfig(**params(**variant_settings(variant))), 7, inputs)


def test_no_aug_renders_with_camera_directions_and_no_pixel_changes(tmp_path):
    assets = _assets(tmp_path, "no_aug")
    obj, background = assets.objects[0], assets.backgrounds[0]
    layer = compose.place_object(assets, obj, background, "plane", np.random.default_rng(11))
    rng = np.random.default_rng(11)
    pose = sample_plane_pose(obj.frame, obj.height_m, background.planes, True, background.K, HEIGHT, rng, (0.1, 0.4))
    expected = occlude_by_background(render_object_layer(obj.gaussians, pose, background.K, WIDTH, HEIGHT, None, 10**6,
                                                         supersample_min_side=ComposeConfig().supersample_min_side),
                                     background.depth, 0.03, 0.02)
    assert np.array_equal(layer.rgb, expected.rgb) and np.array_equal(layer.alpha, expected.alpha)
    full = _assets(tmp_path, "full", name="full")
    augmented = compose.place_object(full, full.objects[0], full.backgrounds[0], "plane", np.random.default_rng(11))
    assert np.array_equal(augmented.alpha, expected.alpha)  # same pose, same opacity ...
    assert np.abs(augmented.rgb - expected.rgb).max() > 0.05  # ... colour from a random SH direction


def test_no_placement_ignores_planes_and_depth(tmp_path):
    with_planes = _assets(tmp_path, "no_placement", True, "a")
    without = _assets(tmp_path, "no_placement", False, "b")
    without.backgrounds[0].depth = None
    (tmp_path / "a_images").mkdir()
    (tmp_path / "b_images").mkdir()
    for index in range(3):
        a = compose.compose_image(with_planes, index, tmp_path / "a_images")
        b = compose.compose_image(without, index, tmp_path / "b_images")
        assert a.info["placement"] == "random" and a.info["fallback"] is None
        assert [i.category_id for i in a.instances] == [i.category_id for i in b.instances]
        assert all(np.array_equal(x.mask, y.mask) for x, y in zip(a.instances, b.instances))
        assert (tmp_path / "a_images" / f"{index:06d}.jpg").read_bytes() == \
            (tmp_path / "b_images" / f"{index:06d}.jpg").read_bytes()
    full = _assets(tmp_path, "full", False, "c")
    assert compose.compose_image(full, 0, tmp_path / "a_images").info["fallback"] == "no planes found"


def test_smart_placement_draws_only_backgrounds_with_planes(tmp_path):
    assets = _assets(tmp_path, "full")
    wall = copy.copy(assets.backgrounds[0])
    wall.plane_issue, wall.bg_id = "no planes found", "wall"
    backgrounds = [wall, assets.backgrounds[0], wall]
    rng = np.random.default_rng(0)
    full = ComposeConfig(**params(**variant_settings("full")))
    assert {compose.pick_background(full, backgrounds, rng).bg_id for _ in range(30)} == {assets.backgrounds[0].bg_id}
    random_poses = ComposeConfig(**params(**variant_settings("no_placement")))
    assert "wall" in {compose.pick_background(random_poses, backgrounds, rng).bg_id for _ in range(30)}
    assert compose.pick_background(full, [wall], rng).bg_id == "wall"  # none placeable: random poses


def _run(tmp_path: Path, name: str, **overrides) -> Path:
    inputs = write_floor_scene(tmp_path / f"{name}_in")
    out = tmp_path / name
    out.mkdir()
    compose.run(Context(stage="compose", item="full", params=params(**overrides), inputs=inputs, out=out, seed=5))
    return out


def test_run_writes_valid_coco_identical_for_one_and_two_workers(tmp_path):
    one = _run(tmp_path, "one", workers=1, random_placement_share=0.3)
    two = _run(tmp_path, "two", workers=2, random_placement_share=0.3)
    coco = load_coco(one / "annotations.json")
    assert len(coco.getImgIds()) == 6 and len(coco.getAnnIds()) >= 6
    for ann in coco.loadAnns(coco.getAnnIds()):
        mask = rle_to_mask(ann["segmentation"])
        assert ann["area"] == int(mask.sum()) > 0
        assert 0.25 <= ann["visible_fraction"] <= 1.0 and ann["placement"] in ("plane", "random")
    stats = json.loads((one / "stats.json").read_text())
    assert stats["images"] == 6 and stats["images_per_s"] > 0 and (one / "preview.png").is_file()
    assert (one / "annotations.json").read_bytes() == (two / "annotations.json").read_bytes()
    for path in sorted((one / "images").glob("*.jpg")):
        assert path.read_bytes() == (two / "images" / path.name).read_bytes()


def test_auto_workers_use_every_core_only_for_enough_images():
    assert image_processes(0, 1000, cores=2) == 2  # the default dataset: both cores of this machine
    assert image_processes(0, 1000, cores=16) == 10  # at least 100 images per process
    assert image_processes(0, 150, cores=2) == 1 and image_processes(0, 6, cores=2) == 1
    assert image_processes(3, 6, cores=2) == 3  # an explicit count is kept


def test_bad_inputs_raise_clear_errors(tmp_path):
    from stages.contract.errors import StageError
    with pytest.raises(StageError, match="min_objects <= max_objects"):
        ComposeConfig(**params(min_objects=3, max_objects=2))
    inputs = write_floor_scene(tmp_path / "s")
    photo, planes, depth = (inputs[input_name(kind, "floor")] for kind in ("background", "planes", "depth"))
    np.save(depth / "depth.npy", np.zeros((10, 10), np.float32))
    with pytest.raises(StageError, match="depth.npy"):
        load_background("floor", photo, planes, depth, 5)


def test_background_without_depth_falls_back_to_random(tmp_path):
    inputs = write_floor_scene(tmp_path / "s")
    photo, planes, depth = (inputs[input_name(kind, "floor")] for kind in ("background", "planes", "depth"))
    (depth / "depth.npy").unlink()
    DepthRecord("none", False, K, WIDTH, HEIGHT).write(depth)
    background = load_background("floor", photo, planes, depth, 5,
                                 (2 * WIDTH, 2 * HEIGHT))
    assert background.depth is None and background.plane_issue == "no depth"
    assert background.size == (2 * WIDTH, 2 * HEIGHT) and np.allclose(background.K[:2, :3], 2 * K[:2, :3])
    cfg = ComposeConfig(**params())
    assert compose.placement_mode(cfg, background, np.random.default_rng(0)) == ("random", "no depth")


def test_a_left_out_object_keeps_its_category_and_is_listed(tmp_path):
    """The engine left out object `ghost` (its extract failed): the dataset is made of `blob`, the categories
    stay those of the data config, stats.json says what was left out and why."""
    objects = [{"name": "ghost", "height_m": 0.2}, {"name": "blob", "height_m": 0.4}]
    out = tmp_path / "out"
    out.mkdir()
    compose.run(Context(stage="compose", item="full", params=params(objects=objects), out=out, seed=5,
                        inputs=write_floor_scene(tmp_path / "in"), left_out={"object ghost": "extract[ghost] failed"}))
    coco = load_coco(out / "annotations.json")
    assert [c["name"] for c in coco.loadCats(coco.getCatIds())] == ["ghost", "blob"]
    assert coco.getAnnIds() and {ann["category_id"] for ann in coco.loadAnns(coco.getAnnIds())} == {2}
    assert json.loads((out / "stats.json").read_text())["left_out"] == {"object ghost": "extract[ghost] failed"}


def test_photos_without_a_plane_are_left_out_and_said_so(tmp_path, caplog):
    """placement 'plane' composes only onto photos with a plane while there is one: a photo without depth is
    not drawn (the warning and stats.json say so); with placement 'random' it is."""
    inputs = write_floor_scene(tmp_path / "in")
    hall = tmp_path / "hall"
    (hall / "depth").mkdir(parents=True)
    (hall / "planes").mkdir()
    write_image(hall / "hall.png", np.full((HEIGHT, WIDTH, 3), 128, np.uint8))
    DepthRecord("none", False, K, WIDTH, HEIGHT).write(hall / "depth")
    PlanesRecord(K, WIDTH, HEIGHT, FLOOR_NORMAL, False, []).write(hall / "planes")
    inputs.update({input_name("background", "hall"): hall / "hall.png", input_name("depth", "hall"): hall / "depth",
                   input_name("planes", "hall"): hall / "planes"})
    used = {}
    for placement in ("plane", "random"):
        out = tmp_path / placement
        out.mkdir()
        compose.run(Context(stage="compose", item="x", params=params(placement=placement, num_images=8), out=out,
                            inputs=inputs, seed=5))
        annotations = json.loads((out / "annotations.json").read_text())["annotations"]
        used[placement] = {ann["background"] for ann in annotations}
        stats = json.loads((out / "stats.json").read_text())
        assert stats["photos_without_plane"] == ({"hall": "no depth"} if placement == "plane" else {})
    assert used == {"plane": {"floor"}, "random": {"floor", "hall"}}
    assert "placement 'plane' leaves out 1 of 2 photos, which have no placement plane: hall (no depth)" in caplog.text


def test_metric_pose_projects_like_the_rendered_pose():
    """The exported rigid pose of the real-size object gives the pixels of the similarity compose rendered with,
    whatever the render scale; at render scale 1 (metric plane placement) it is the object's place itself."""
    means = make_blob().means.numpy().astype(np.float64)
    halo = np.random.default_rng(0).normal(0.0, 3.0, (200, 3))  # faint Gaussians around it: not model points
    points = model_points(np.concatenate([means, halo]), np.r_[np.full(len(means), 0.98), np.full(200, 0.1)])
    assert np.array_equal(points, means)
    frame = metric_frame(FRAME, points, 0.4)  # 2 model units -> 0.4 m
    object_points = frame.from_model(means)  # [N, 3] metres
    assert np.allclose(object_points.min(0) + object_points.max(0), 0.0) and abs(np.ptp(object_points[:, 2]) - 0.4) < 0.01
    for scale in (0.2, 0.35):  # 0.2 = metric for this object, 0.35 = rendered 1.75 times too large
        pose = pose_on_plane(FRAME, np.array([0.1, 1.0, 3.0]), FLOOR_NORMAL, 0.7, scale)
        rotation, translation, render_scale = metric_pose(pose, frame)
        assert np.isclose(render_scale, scale / 0.2) and np.allclose(rotation.T @ rotation, np.eye(3))
        rendered, exported = pose.apply(means), object_points @ rotation.T + translation
        assert np.allclose(rendered[:, :2] / rendered[:, 2:], exported[:, :2] / exported[:, 2:])
        assert np.allclose(rendered, render_scale * exported)
        assert np.allclose(rotation[:, 2], FLOOR_NORMAL)  # the frame's z axis is up


def test_annotations_carry_pose_camera_amodal_mask_and_depth(tmp_path):
    out = _run(tmp_path, "fields", workers=1, num_images=8, random_placement_share=0.4)
    coco = json.loads((out / "annotations.json").read_text())
    placement = {ann["image_id"]: ann["placement"] for ann in coco["annotations"]}
    assert set(placement.values()) == {"plane", "random"}
    for image in coco["images"]:
        assert np.allclose(image["K"], K)
        expected = {"input": "depth:floor", "file": "depth.npy", "median_filter_px": 5}
        assert image["depth"] == (expected if placement.get(image["id"]) == "plane" else None)
    model = coco["info"]["object_models"]["blob"]
    assert model["input"] == "object:blob" and model["file"] == "object.ply" and model["metres_per_unit"] == 0.2
    blob = make_blob(view_dependent=True)  # the object of write_floor_scene
    points = model_points(blob.means.numpy(), blob.opacities.numpy())
    bottom = metric_frame(FRAME, points, 0.4).from_model(points)[:, 2].min()  # [m] its lowest model point
    for ann in coco["annotations"]:
        visible, amodal = rle_to_mask(ann["segmentation"]), rle_to_mask(ann["amodal_segmentation"])
        assert not (visible & ~amodal).any() and amodal.sum() >= ann["area"]
        rotation, translation = np.asarray(ann["pose"]["R"]), np.asarray(ann["pose"]["t"])
        if ann["placement"] == "plane":  # metric: the object stands on the floor, 1 m below the camera, upright
            assert ann["pose"]["render_scale"] == 1.0 and np.allclose(rotation[:, 2], FLOOR_NORMAL, atol=1e-6)
            assert abs((rotation @ [0.0, 0.0, bottom] + translation)[1] - CAMERA_HEIGHT) < 1e-3


def test_photos_made_without_a_plane_are_information_and_the_others_a_warning(tmp_path, caplog):
    inputs = write_floor_scene(tmp_path / "floor")
    for name in ("closeup", "empty_floor"):  # two photos without a placement plane
        plain = write_floor_scene(tmp_path / name, with_planes=False)
        inputs.update({key.replace(":floor", f":{name}"): value for key, value in plain.items() if ":floor" in key})
    cfg = ComposeConfig(**params(expected_without_plane=["closeup"]))
    with caplog.at_level(logging.INFO, logger="stages.compose.run"):
        left_out = compose.photos_without_plane(cfg, inputs)
    assert sorted(left_out) == ["closeup", "empty_floor"]
    levels = {record.levelname: record.getMessage() for record in caplog.records}
    assert "1 of 3 photos of the sample (expected: views without a floor): closeup" in levels["INFO"]
    assert "leaves out 1 of 3 photos, which have no placement plane: empty_floor" in levels["WARNING"]


def test_a_small_object_renders_finer_so_its_mask_is_its_coverage():
    """One sample per pixel with the rasterizer's low-pass widens thin parts of a small render; rendered at 4x
    and reduced by area, the mask is the object's coverage (a 12x finer render is the reference)."""
    posed = posed_gaussians(make_blob(), pose_on_plane(FRAME, np.array([0.0, 1.0, 9.0]), FLOOR_NORMAL, 0.4, 0.15))
    window = object_window(posed, K)
    assert supersample_factor(window, 160) == 4 and supersample_factor(window, 0) == 1
    masks = {s: render_window(posed, K, window, None, supersample=s)[1] > 0.5 for s in (1, 4, 12)}
    iou = {s: (masks[s] & masks[12]).sum() / (masks[s] | masks[12]).sum() for s in (1, 4)}
    assert iou[4] > max(0.9, iou[1]) and masks[1].sum() > masks[4].sum()
    rgb, alpha, depth = render_window(posed, K, window, None, supersample=4)
    assert np.all(rgb <= alpha[..., None] + 1e-5) and np.isfinite(depth[alpha > 0.5]).all()
    near = posed_gaussians(make_blob(), pose_on_plane(FRAME, np.array([0.0, 1.0, 2.0]), FLOOR_NORMAL, 0.4, 0.15))
    masses = [render_window(near, K, object_window(near, K), None, supersample=s)[1].sum() for s in (1, 2)]
    assert abs(masses[1] - masses[0]) < 0.05 * masses[0]  # a larger render: about the same opacity either way


def floor_grid(step: float) -> PlacementPlane:
    """The factory's floor (1 m under the camera) as placement points every `step` metres, x in [-1, 1], z in [2, 6]."""
    xs, zs = np.meshgrid(np.arange(-1.0, 1.0 + 1e-9, step), np.arange(2.0, 6.0 + 1e-9, step))
    points = np.stack([xs.ravel(), np.full(xs.size, CAMERA_HEIGHT), zs.ravel()], axis=1)
    return PlacementPlane(FLOOR_NORMAL, points.mean(0), 8.0, points, (points @ K.T)[:, :2] / points[:, 2:])


def test_an_object_stood_beside_another_neither_intersects_nor_strays():
    ring = np.array([[0.7 * np.cos(a), 0.7 * np.sin(a), h] for a in np.linspace(0, 6, 20) for h in (0.5, 1.5)])
    assert np.isclose(footprint_radius(FRAME, ring), 0.7)  # leaves reaching 0.7 units from the stem
    plane, anchor, rng = floor_grid(0.05), np.array([0.0, 1.0, 4.0]), np.random.default_rng(0)
    far_plane = floor_grid(0.05)
    far_plane.points = far_plane.points + [0.0, 0.0, 10.0]
    assert plane_under([far_plane, plane], anchor + 0.01) is plane
    distances = []
    for _ in range(60):  # 0.5 model units at 0.2 m per unit (0.4 m tall) = 0.1 m, beside one of 0.1 m: 0.2-0.4 m
        pose = sample_pose_beside(FRAME, 0.4, 0.5, plane, anchor, 0.1, 1.0, True, K, HEIGHT, rng, (0.1, 0.4))
        base = pose.apply(FRAME.base_point[None])[0]
        assert np.min(np.linalg.norm(plane.points - base, axis=1)) < 1e-9  # on one of the plane's points
        assert np.allclose(pose.rotation @ FRAME.normal, FLOOR_NORMAL) and np.isclose(pose.scale, 0.2)
        distances.append(np.linalg.norm(base - anchor))
    assert 0.2 - 1e-9 <= min(distances) < 0.25 and 0.35 < max(distances) <= 0.4 + 1e-9
    assert sample_pose_beside(FRAME, 0.4, 0.5, plane, anchor + [3.0, 0, 0], 0.1, 1.0, True, K, HEIGHT, rng,
                              (0.1, 0.4)) is None  # no placement point 0.2-0.4 m away: the caller stands it anywhere
    pose = sample_pose_beside(FRAME, 0.4, 0.5, plane, anchor, 0.1, 1.0, False, K, HEIGHT, rng, (0.25, 0.25))
    depth = pose.apply(FRAME.base_point[None])[0][2]  # non-metric: a quarter of the image height where it stands
    assert np.isclose(pose.scale * FRAME.height * K[1, 1] / depth, 0.25 * HEIGHT)


def test_grouped_objects_stand_beside_one_another(tmp_path):
    """With group_share 1 every later object of an image stands beside an earlier one: each object's nearest
    neighbour is 1-2x the sum of their footprint radii away (blobs of 0.1 m: 0.2-0.4 m); placed independently they
    are not."""
    blob = make_blob(view_dependent=True)  # the object of write_floor_scene
    points = model_points(blob.means.numpy(), blob.opacities.numpy())
    base = metric_frame(FRAME, points, 0.4).from_model(FRAME.base_point[None])[0]  # [3] metres, the exported frame
    assert abs(0.2 * footprint_radius(FRAME, points) - 0.1) < 0.002

    def nearest_neighbours(out: Path) -> list[float]:
        by_image: dict[int, list[np.ndarray]] = {}
        for ann in json.loads((out / "annotations.json").read_text())["annotations"]:
            rotation, translation = np.asarray(ann["pose"]["R"]), np.asarray(ann["pose"]["t"])
            by_image.setdefault(ann["image_id"], []).append(rotation @ base + translation)
        return [min(np.linalg.norm(p - q) for q in bases if q is not p)
                for bases in by_image.values() if len(bases) > 1 for p in bases]

    settings = {"workers": 1, "num_images": 8, "min_objects": 3, "max_objects": 3}
    grouped = nearest_neighbours(_run(tmp_path, "grouped", group_share=1.0, **settings))
    alone = nearest_neighbours(_run(tmp_path, "alone", **settings))
    assert len(grouped) >= 8 and all(0.2 - 1e-3 <= d <= 0.4 + 1e-3 for d in grouped)
    assert sum(d > 0.4 + 1e-3 for d in alone) >= len(alone) // 2
