"""compose beyond the paper (issue 32): cast shadows on the support plane, relighting by the photo's light, the
settings and variants that switch them, and the report's rows and figure."""
from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from stages.app.report import write_report
from stages.compose import run as compose
from stages.compose.spec import ComposeConfig
from stages.contract.errors import StageError
from stages.contract.fan_in import input_name
from stages.engine.context import Context
from stages.lib.composition.light import (SceneLight, exposure_gain, gaussian_normals, photo_light, relit,
                                          sample_scene_light, shading_factors)
from stages.lib.composition.occlusion import filtered_background_depth
from stages.lib.composition.placement import ObjectFrame, pose_on_plane
from stages.lib.composition.shadow import Shadow, ShadowLook, apply_shadows, cast_shadow, shadow_caster
from stages.lib.gaussians.model import SH_C0
from stages.lib.gaussians.rasterize import gaussian_colors
from tests.factories.backgrounds import FLOOR_NORMAL, HEIGHT, K, WIDTH, floor_depth, write_floor_scene
from tests.factories.configs import CONF, compose_cfg, composition_error
from tests.factories.splats import make_blob

FRAME = ObjectFrame(np.array([0.0, 0.0, 1.0]), np.zeros(3), 2.0)  # make_blob: base at 0, up +z, 2 units tall
SCALE = 2  # the floor scene's camera at twice its resolution
K2 = np.diag([SCALE, SCALE, 1.0]) @ K
CONTACT = np.array([0.1, 1.0, 3.0])  # on the floor, 3 m ahead
LOOK = {"strength": 0.6, "contact": 0.5, "softness": 0.04}


def unit(vector) -> np.ndarray:
    return np.asarray(vector, dtype=np.float64) / np.linalg.norm(vector)


def floor_shadow(light: np.ndarray, depth: np.ndarray | None = None):
    """The blob's shadow standing 0.4 m tall at CONTACT on the floor scene (2x), and its contact pixel (u, v)."""
    g = make_blob()
    pose = pose_on_plane(FRAME, CONTACT, FLOOR_NORMAL, 0.3, 0.2)
    depth = cv2.resize(floor_depth(), (WIDTH * SCALE, HEIGHT * SCALE), interpolation=cv2.INTER_NEAREST) \
        if depth is None else depth
    shadow = cast_shadow(shadow_caster(g), pose, FRAME, K2, filtered_background_depth(depth, 5),
                         ShadowLook(light, **LOOK), 0.05, 0.02)
    contact = K2 @ CONTACT
    return shadow, contact[:2] / contact[2]


def dark_pixels(shadow, threshold: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Image (x, y) of the shadow's pixels darker than `threshold`."""
    rows, cols = np.nonzero(shadow.darkness > threshold)
    return cols + shadow.x0, rows + shadow.y0


def test_shadow_falls_on_the_floor_away_from_the_light():
    from_right_beyond = unit([1.0, -1.0, 0.6])  # light to the right, above, beyond the object
    shadow, (u, v) = floor_shadow(from_right_beyond)
    xs, ys = dark_pixels(shadow)
    assert len(xs) > 100 and shadow.darkness.max() <= 1.0
    assert (ys + 0.5 > K2[1, 2]).all()  # below the horizon: on the floor
    assert xs.mean() < u - 5 and ys.mean() > v  # to the left and towards the camera: away from the light
    from_left_near = unit([-1.0, -1.2, -0.5])  # light to the left, above, on the camera's side
    shadow, _ = floor_shadow(from_left_near)
    xs, ys = dark_pixels(shadow)
    assert xs.mean() > u + 5 and ys.mean() < v + 2  # to the right and away from the camera
    overhead = floor_shadow(unit(FLOOR_NORMAL + [0.0, 0.0, 1e-3]))[0]
    xs, ys = dark_pixels(overhead)
    assert abs(xs.mean() - u) < 3  # straight down: around the base


def test_shadow_is_darkest_at_the_contact_and_softer_towards_the_tip():
    shadow, (u, v) = floor_shadow(unit([1.0, -1.0, 0.6]))
    xs, _ = dark_pixels(shadow, 0.02)
    near = shadow.darkness[int(v) - shadow.y0, int(u) - shadow.x0 - 6]  # just beside the base
    tip = xs.min()  # the far end of the shadow, on the left
    far = shadow.darkness[:, tip - shadow.x0: tip - shadow.x0 + 4].max()
    assert near > 0.5 and far < near


def test_a_surface_nearer_than_the_plane_takes_no_shadow_and_neither_does_the_space_past_it():
    light = unit([1.0, -1.0, 0.6])
    free, (u, v) = floor_shadow(light)
    depth = cv2.resize(floor_depth(), (WIDTH * SCALE, HEIGHT * SCALE), interpolation=cv2.INTER_NEAREST)
    box = int(u) - 10  # a box 2 m away over the image left of the object, where the shadow falls
    depth[:, :box] = np.minimum(depth[:, :box], 2.0)
    blocked, _ = floor_shadow(light, depth)
    xs, _ = dark_pixels(free)
    assert (xs < box - 3).sum() > 20  # on the free floor the shadow reaches there ...
    xs, _ = dark_pixels(blocked, 0.01)
    assert not (xs < box - 3).any()  # ... not on the box in front of it
    behind = cv2.resize(floor_depth(), (WIDTH * SCALE, HEIGHT * SCALE), interpolation=cv2.INTER_NEAREST)
    behind[:, :box] = 8.0  # past the floor's edge (a drop): the shadow stops there too
    cut, _ = floor_shadow(light, behind)
    xs, _ = dark_pixels(cut, 0.01)
    assert not (xs < box - 3).any()


def test_apply_shadows_darkens_only_and_takes_the_darkest_where_they_overlap():
    image = np.full((4, 5, 3), 0.8, np.float32)
    first = Shadow(0, 0, np.full((2, 3), 0.5, np.float32))
    second = Shadow(1, 1, np.full((2, 2), 0.25, np.float32))
    out = apply_shadows(image, [first, second])
    assert np.allclose(out[0, 0], 0.4) and np.allclose(out[1, 1], 0.4)  # overlap: the darker one, not both
    assert np.allclose(out[2, 2], 0.6) and np.allclose(out[3, 4], 0.8) and (out <= image).all()


def floor_assets(tmp_path: Path, name: str, photo: np.ndarray | None = None, **settings) -> compose.ComposeAssets:
    """compose's assets of the floor scene (optionally another photo, BGR uint8) with `settings`."""
    inputs = write_floor_scene(tmp_path / name)
    if photo is not None:
        cv2.imwrite(str(inputs[input_name("background", "floor")]), photo)
    params = {"objects": [{"name": "blob", "height_m": 0.4}], "num_images": 6, "preview_count": 2, **settings}
    return compose.load_assets(ComposeConfig(**params), 7, inputs)


def test_effects_change_pixels_only_never_a_mask(tmp_path):
    """Shadows and relighting come from their own random stream and change no draw of the image: with and
    without them the same objects lie in the same places with the same masks; a shadow only darkens the
    background, and the opaque inside of an object does not take it."""
    grey = np.full((HEIGHT, WIDTH, 3), 170, np.uint8)
    plain = floor_assets(tmp_path, "plain", grey, shadow=False, relight="none")
    shadowed = floor_assets(tmp_path, "shadowed", grey, shadow=True, relight="none")
    relit_only = floor_assets(tmp_path, "relit", grey, shadow=False, relight="shading")
    darker = 0
    for index in range(4):
        items = {}
        for name, assets in (("plain", plain), ("shadowed", shadowed), ("relit", relit_only)):
            (tmp_path / f"{name}_{index}").mkdir()
            item = compose.compose_image(assets, index, tmp_path / f"{name}_{index}")
            image = cv2.imread(str(tmp_path / f"{name}_{index}" / item.file_name)).astype(np.int32)
            items[name] = (item, image)
        (item, image), shadowed_image = items["plain"], items["shadowed"][1]
        for other, _ in items.values():
            assert [i.category_id for i in other.instances] == [i.category_id for i in item.instances]
            assert all(np.array_equal(a.mask, b.mask) for a, b in zip(other.instances, item.instances))
        masks = np.zeros((HEIGHT, WIDTH), bool)
        for instance in item.instances:
            masks |= cv2.erode(instance.mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        assert (shadowed_image <= image + 12).all()  # darker or the same, never brighter (but for JPEG ringing)
        assert np.abs(shadowed_image - image)[masks].max(initial=0) <= 12  # the object's inside: unchanged (JPEG)
        darker += int(((shadowed_image < image - 10).any(axis=2) & ~masks).sum())
    assert darker > 50


def test_effects_are_the_same_for_any_number_of_processes(tmp_path):
    outs = []
    for workers in (1, 2):
        out = tmp_path / f"workers{workers}"
        out.mkdir()
        params = {"objects": [{"name": "blob", "height_m": 0.4}], "num_images": 4, "workers": workers,
                  "shadow": True, "relight": "shading", "light_direction": "photo"}
        compose.run(Context(stage="compose", item="x", out=out, seed=5, params=params,
                            inputs=write_floor_scene(tmp_path / f"in{workers}")))
        outs.append(out)
    assert (outs[0] / "annotations.json").read_bytes() == (outs[1] / "annotations.json").read_bytes()
    for path in sorted((outs[0] / "images").glob("*.jpg")):
        assert path.read_bytes() == (outs[1] / "images" / path.name).read_bytes()


def test_relighting_takes_the_tint_of_the_background_within_the_clamp(tmp_path):
    """A grey object on an orange background turns orange; the gain is clamped; strength 0 changes nothing."""
    orange = np.zeros((HEIGHT, WIDTH, 3), np.uint8)
    orange[:] = (60, 140, 230)  # BGR
    image = cv2.cvtColor(orange, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0
    light = photo_light(image, K, [])
    gain = exposure_gain(light, (40, 30, 120, 90), 0.5, 1.5)
    assert gain[0] > gain[1] > gain[2]
    assert np.all(gain <= 1.5 ** (1 / 2.2) + 1e-9) and np.all(gain >= 1.5 ** (-1 / 2.2) - 1e-9)
    assert np.allclose(exposure_gain(light, (40, 30, 120, 90), 0.0, 1.5), 1.0)
    assert np.allclose(exposure_gain(light, (40, 30, 120, 90), 1.0, 1.1),
                       [1.1 ** (1 / 2.2), 1.1 ** (-1 / 2.2), 1.1 ** (-1 / 2.2)])  # a strong tint hits the clamp
    colours = {}
    for relight in ("none", "exposure"):
        assets = floor_assets(tmp_path, relight, orange, relight=relight, shadow=False, augment=False)
        obj, background = assets.objects[0], assets.backgrounds[0]
        grey = obj.gaussians.clone()
        grey.sh[:] = 0.0  # colour 0.5 from every direction
        obj.gaussians = grey
        layer = compose.place_object(assets, obj, background, "plane", np.random.default_rng(3),
                                     compose.image_light(assets, background, 0))
        opaque = layer.alpha > 0.9
        colours[relight] = (layer.rgb[opaque] / layer.alpha[opaque][:, None]).mean(0)
    assert np.allclose(colours["none"], 0.5, atol=0.02)
    red, green, blue = colours["exposure"] / colours["none"]
    assert red > green > blue and red <= 1.5 ** (1 / 2.2) + 0.01 and blue >= 1.5 ** (-1 / 2.2) - 0.01


def test_relit_multiplies_every_colour_for_every_view_direction():
    g = make_blob(view_dependent=True)
    factors = np.random.default_rng(0).uniform(0.5, 1.5, g.num)
    brighter = relit(g, factors)
    for direction in ([0.0, 0.0, 1.0], [1.0, -0.5, 0.2]):
        view = torch.tensor(direction)
        before = gaussian_colors(g, torch.eye(4), sh_view_dir=view)
        after = gaussian_colors(brighter, torch.eye(4), sh_view_dir=view)
        assert torch.allclose(after, before * torch.as_tensor(factors, dtype=torch.float32)[:, None], atol=1e-5)
    assert SH_C0 > 0 and brighter.sh.shape == g.sh.shape


def test_shading_brightens_the_side_facing_the_light_and_keeps_the_mean():
    g = make_blob()
    normals = gaussian_normals(g, FRAME.centre)
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0)
    side = g.means.numpy()[:, 0]  # make_blob: a cylinder about z; +x faces a light from +x
    light = SceneLight(unit([1.0, 0.0, 1.0]), math.radians(45), 0.6)
    factors = shading_factors(normals, g.opacities.numpy(), light.direction, light, 1.0)
    assert factors[side > 0.3].mean() > 1.1 > 0.9 > factors[side < -0.3].mean()
    weights = g.opacities.numpy()
    assert abs(float((weights * factors ** 2.2).sum() / weights.sum()) - 1.0) < 1e-6  # linear light: same mean
    assert np.allclose(shading_factors(normals, weights, light.direction, light, 0.0), 1.0)


def test_photo_light_points_to_the_brighter_side_of_the_floor(tmp_path):
    """The floor of the scene lit from its right: the estimate points to +x; a plain photo gives none."""
    assets = floor_assets(tmp_path, "flat")
    background = assets.backgrounds[0]
    u = (np.arange(WIDTH) + 0.5 - K[0, 2]) / K[0, 0]
    ramp = np.clip(0.35 + 0.5 * u, 0.05, 1.0).astype(np.float32)  # brighter to the right
    image = np.repeat(np.repeat(ramp[None, :, None], HEIGHT, axis=0), 3, axis=2)
    light = photo_light(image, background.K, background.planes)
    assert light.towards_light is not None and light.towards_light @ [1.0, 0.0, 0.0] > 0.95
    assert np.allclose(light.up, FLOOR_NORMAL)
    assert photo_light(np.full_like(image, 0.5), background.K, background.planes).towards_light is None
    lights = [sample_scene_light(light, True, (30.0, 70.0), (0.3, 0.7), np.random.default_rng(s))
              for s in range(20)]
    elevations = [math.degrees(math.asin(float(sl.direction @ light.up))) for sl in lights]
    assert all(29.9 <= e <= 70.1 for e in elevations)
    assert np.mean([sl.direction @ [1.0, 0.0, 0.0] for sl in lights]) > 0.4  # towards the bright side


def test_effect_settings_are_checked_and_the_variants_switch_one_each():
    for bad in ({"shadow_strength": [0.8, 0.2]}, {"shadow_strength": [0.2, 1.0]}, {"light_elevation": [0.0, 95.0]},
                {"shadow_contact": 1.5}, {"relight_max_gain": 0.5}, {"shadow_softness": -0.1}):
        with pytest.raises(StageError, match=next(iter(bad))):
            ComposeConfig(**bad)
    assert "expected one of [none, exposure, shading]" in composition_error(["compose.relight=bright"])
    assert "expected one of [photo, random]" in composition_error(["compose.light_direction=sun"])
    settings = {name: OmegaConf.to_container(OmegaConf.load(CONF / "variant" / f"{name}.yaml").compose)
                for name in ("full", "shadow", "relight", "effects")}
    assert settings["shadow"] == {**settings["full"], "shadow": True}
    assert settings["relight"] == {**settings["full"], "relight": "shading"}
    assert settings["effects"] == {**settings["full"], "shadow": True, "relight": "shading"}
    expected = {"full": (False, "none"), "shadow": (True, "none"), "relight": (False, "shading"),
                "effects": (True, "shading")}
    for name, switches in expected.items():
        cfg = compose_cfg([f"variant={name}"])
        assert cfg.variant.name == name and (cfg.compose.shadow, cfg.compose.relight) == switches
    defaults = ComposeConfig()
    assert not defaults.shadow and defaults.relight == "none"  # full takes the schema's defaults: the paper's compose
    sweep = OmegaConf.load(CONF / "experiment" / "ablation.yaml").hydra.sweeper.params.variant.split(",")
    assert {"full", "no_aug", "no_placement", "cut_and_paste"} == set(sweep)


def write_job(sweep: Path, num: int, variant: str, seed: int, ap: float, dataset: Path | None) -> None:
    """A job's summary.json (box AP `ap` on tests a and b) with the compose dataset folder it made."""
    job = sweep / f"{num}_{variant}"
    job.mkdir(parents=True)
    compose_settings = {"shadow": variant in ("shadow", "effects"),
                        "relight": "shading" if variant in ("relight", "effects") else "none"}
    config = {"variant": {"name": variant}, "run": {"seed": seed}, "compose": compose_settings,
              "data": {"test_sets": [{"name": "test_a"}, {"name": "test_b"}]}}
    metrics = {"bbox": {"AP": ap, "AP50": ap + 30, "per_class": {}}, "segm": {"AP": ap - 5}}
    outcomes = [{"stage": "compose", "status": "cached", "path": str(dataset)}] if dataset else []
    (job / "summary.json").write_text(json.dumps({
        "variant": {"name": variant}, "config": config,
        "eval": {f"{variant}@test_a": metrics, f"{variant}@test_b": metrics},
        "compute_seconds_by_stage": {"compose": 40}, "failed": [], "outcomes": outcomes}))


def test_report_has_the_effect_rows_and_the_figure_of_the_same_placements(tmp_path):
    datasets = {}
    for variant in ("full", "shadow", "relight"):
        out = tmp_path / "cache" / variant
        out.mkdir(parents=True)
        settings = {"shadow": variant == "shadow", "relight": "shading" if variant == "relight" else "none"}
        params = {"objects": [{"name": "blob", "height_m": 0.4}], "num_images": 4, **settings}
        compose.run(Context(stage="compose", item=variant, out=out, seed=5, params=params,
                            inputs=write_floor_scene(tmp_path / variant)))
        datasets[variant] = out
    sweep = tmp_path / "sweep"
    for num, (variant, ap) in enumerate([("full", 60.0), ("shadow", 55.0), ("relight", 58.0),
                                         ("cut_and_paste", 40.0)]):
        write_job(sweep, num, variant, 0, ap, datasets.get(variant))
    report = write_report(sweep).read_text()
    table = report.split("## Ablation")[1].split("\n\n")[2].splitlines()  # the paper's Table 1 layout
    assert [row.split(" |")[0] for row in table[2:]] == ["| Cut-and-Splat", "| with cast shadows", "| with relighting",
                                                         "| Cut-and-Paste"]
    assert "| with cast shadows | 55.0 | 55.0 |" in report and "![effects](effects.png)" in report
    assert (sweep / "effects.png").is_file()
