"""compose: the Cut-and-Splat generator (paper: "Scene Composition").

Per image (seeded by its index): a background, 1..max objects, each stood on a placement plane
(normal on the plane normal, random turn about up, size from its real height and the metric depth)
or, with `placement: random` (the no_placement variant) and for the random share, posed at random. With
`placement: plane` only photos with a placement plane are drawn while there is one (stats.json lists the
others, `photos_without_plane`); when no photo has one, every object is posed at random. Objects are
rendered in their image windows, occluded by the median-filtered background depth and by each other,
augmented (random SH view direction, pixel augmentations) and alpha-blended. Beyond the paper (issue 32), each
image gets a light (its direction from the photo's planes or at random, drawn from a stream of its own, so the
placements do not depend on the effects): plane-posed objects cast shadows on their support plane (`shadow`) and
objects take the light of the background around them (`relight`). Output: a COCO dataset (see docs/stage_contracts.md).
The objects and photos the engine left out (their upstream stages failed) are listed in stats.json (`left_out`); the
categories stay those of the data config, so a left-out object has no instances.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from stages.compose.spec import INPUTS, ComposeConfig
from stages.contract.errors import StageError
from stages.contract.fan_in import fanned, input_name, left_out_items, per_object
from stages.lib.coco import mask_to_rle
from stages.lib.composition.augment import PixelAugStrengths, augment_object
from stages.lib.composition.backgrounds import Background, load_backgrounds, plane_issues
from stages.lib.composition.dataset import ComposedImage, Instance, generate, image_rng, write_dataset, write_jpeg
from stages.lib.composition.light import (PhotoLight, SceneLight, exposure_gain, gaussian_normals, photo_light, relit,
                                          sample_scene_light, shading_factors)
from stages.lib.composition.occlusion import composite_layers, occlude_by_background
from stages.lib.composition.placement import (MODEL_OPACITY, MetricFrame, ObjectFrame, footprint_radius, metric_frame,
                                              metric_pose, model_points, plane_under, sample_plane_pose,
                                              sample_pose_beside, sample_random_pose)
from stages.lib.composition.render_object import ObjectLayer, render_object_layer
from stages.lib.composition.shadow import Shadow, ShadowCaster, ShadowLook, apply_shadows, cast_shadow, shadow_caster
from stages.lib.gaussians.model import Gaussians
from stages.lib.gaussians.ply import read_ply
from stages.records.depth import DepthRecord
from stages.records.extract import ExtractRecord

if TYPE_CHECKING:  # the engine's object; not part of the stage's cache key
    from stages.engine.context import Context

log = logging.getLogger(__name__)

OBJECT_PLY = "object.ply"  # the object model in an extract folder
LIGHT_STREAM = 1  # an image's light is drawn from the generator seeded (seed, index, LIGHT_STREAM)


def pixel_aug(cfg: ComposeConfig) -> PixelAugStrengths:
    """The pixel augmentation strengths of the settings."""
    return PixelAugStrengths(cfg.aug_blur_prob, cfg.aug_blur_sigma, cfg.aug_brightness, cfg.aug_contrast,
                             cfg.aug_saturation, cfg.aug_hue, cfg.aug_noise_std, cfg.aug_tone_curve)


@dataclass
class SceneObject:
    """An extracted object model with its ground frame and real height."""

    name: str
    category_id: int
    gaussians: Gaussians
    frame: ObjectFrame
    height_m: float
    metric: MetricFrame  # the frame of its exported poses
    radius: float  # how far its opaque Gaussians reach from its up axis, model units (footprint_radius)
    caster: ShadowCaster | None = None  # what its shadow is made of (with `shadow`)
    normals: np.ndarray | None = None  # [N, 3] model frame, its Gaussians' outward normals (with relight "shading")
    opacities: np.ndarray | None = None  # [N] its Gaussians' opacities, the shading's weights (with "shading")


@dataclass
class ComposeAssets:
    """Everything one process needs to compose images."""

    cfg: ComposeConfig
    seed: int
    objects: list[SceneObject]
    backgrounds: list[Background]
    lights: dict[str, PhotoLight] = field(default_factory=dict)  # per photo id, with a shadow or relight setting


def load_object(name: str, category_id: int, folder: Path, height_m: float) -> SceneObject:
    """Read an extract folder (object.ply + extract.json)."""
    ply_path = folder / OBJECT_PLY
    if not ply_path.is_file():
        raise StageError(f"compose: object {name!r}: {folder} lacks {OBJECT_PLY} (run extract)")
    meta = ExtractRecord.read(folder)
    frame = ObjectFrame(meta.normal, meta.base_point, meta.height)
    gaussians = read_ply(ply_path)
    points = model_points(gaussians.means.numpy(), gaussians.opacities.numpy())
    return SceneObject(name, category_id, gaussians, frame, float(height_m), metric_frame(frame, points, float(height_m)),
                       footprint_radius(frame, points))


def load_assets(cfg: ComposeConfig, seed: int, inputs: dict[str, Path]) -> ComposeAssets:
    """Load objects and backgrounds (called once per worker process)."""
    if not cfg.objects or any("name" not in o or "height_m" not in o for o in cfg.objects):
        raise StageError("compose: `objects` must list {name, height_m} for every object (data config)")
    found = per_object(inputs, [o["name"] for o in cfg.objects], INPUTS.object_kinds, "compose")
    objects = [load_object(spec["name"], k + 1, found[spec["name"]]["object"], float(spec["height_m"]))
               for k, spec in enumerate(cfg.objects) if spec["name"] in found]
    backgrounds = load_backgrounds(inputs, "compose", cfg.depth_median_size, cfg.image_size)
    lights = {}
    if lit(cfg):
        for obj in objects:
            if cfg.shadow:
                obj.caster = shadow_caster(obj.gaussians)
            if cfg.relight == "shading":
                obj.normals = gaussian_normals(obj.gaussians, obj.frame.centre)
                obj.opacities = obj.gaussians.opacities.numpy()
        lights = {bg.bg_id: photo_light(bg.image, bg.K, bg.planes if cfg.placement == "plane" else [])
                  for bg in backgrounds}  # random placement knows no planes
    return ComposeAssets(cfg, seed, objects, backgrounds, lights)


def lit(cfg: ComposeConfig) -> bool:
    """Whether images get a light (a shadow or relight setting is on)."""
    return cfg.shadow or cfg.relight != "none"


def image_light(assets: ComposeAssets, background: Background, index: int) -> SceneLight | None:
    """The light of image `index` (None when no effect uses one), from its own random stream."""
    cfg = assets.cfg
    if not lit(cfg):
        return None
    rng = image_rng(assets.seed, index, LIGHT_STREAM)
    return sample_scene_light(assets.lights[background.bg_id], cfg.light_direction == "photo",
                              (cfg.light_elevation[0], cfg.light_elevation[1]),
                              (cfg.shadow_strength[0], cfg.shadow_strength[1]), rng)


def pick_background(cfg: ComposeConfig, backgrounds: list[Background], rng: np.random.Generator) -> Background:
    """A random background; with smart placement only among those that have a placement plane
    (all of them when none has one: every image then falls back to random poses)."""
    if cfg.placement == "plane":
        placeable = [background for background in backgrounds if background.plane_issue is None]
        backgrounds = placeable or backgrounds
    return backgrounds[int(rng.integers(len(backgrounds)))]


def placement_mode(cfg: ComposeConfig, background: Background, rng: np.random.Generator) -> tuple[str, str | None]:
    """("plane" | "random", why random) for one image."""
    if cfg.placement == "random":
        return "random", None
    if background.plane_issue is not None:
        return "random", background.plane_issue
    if rng.random() < cfg.random_placement_share:
        return "random", "random share"
    return "plane", None


def place_object(assets: ComposeAssets, obj: SceneObject, background: Background, mode: str,
                 rng: np.random.Generator, light: SceneLight | None = None,
                 beside: tuple[np.ndarray, float] | None = None) -> ObjectLayer | None:
    """Pose and render one object (with background occlusion for plane poses); None if every try fails.
    Under a `light` (and a relight setting) it takes the light of the photo (relight_layer), else it keeps the
    light of its capture. `beside` (plane poses): (base point [3], footprint radius) of an object standing in the
    image, next to which this one is stood (sample_pose_beside; a try that finds no spot there stands it anywhere)."""
    cfg = assets.cfg
    width, height = background.size
    apparent = (cfg.apparent_height[0], cfg.apparent_height[1])
    plane = None if beside is None else plane_under(background.planes, beside[0])
    for _ in range(cfg.placement_attempts):
        if mode == "plane":
            pose = None if plane is None else sample_pose_beside(
                obj.frame, obj.height_m, obj.radius, plane, beside[0], beside[1], cfg.group_spread, background.metric,
                background.K, height, rng, apparent)
            if pose is None:
                pose = sample_plane_pose(obj.frame, obj.height_m, background.planes, background.metric,
                                         background.K, height, rng, apparent)
        else:
            pose = sample_random_pose(obj.frame, background.K, width, height, rng, apparent,
                                      (cfg.random_depth[0], cfg.random_depth[1]))
        view_dir = None
        if cfg.augment:
            view_dir = rng.normal(size=3)
            view_dir /= np.linalg.norm(view_dir)
        gaussians = obj.gaussians
        if light is not None and cfg.relight == "shading":
            gaussians = relit(gaussians, shading_factors(obj.normals, obj.opacities,
                                                         pose.rotation.T @ light.direction, light, cfg.relight_shading))
        layer = render_object_layer(gaussians, pose, background.K, width, height, view_dir,
                                    int(cfg.max_window_fraction * width * height), cfg.render_backend,
                                    cfg.supersample_min_side)
        if layer is None or layer.full_alpha_sum <= 0:
            continue
        if mode == "plane":
            layer = occlude_by_background(layer, background.depth, cfg.depth_tolerance_rel, cfg.depth_tolerance_abs)
        if (layer.alpha.sum() >= cfg.min_visible_fraction * layer.full_alpha_sum
                and int((layer.alpha > cfg.mask_threshold).sum()) >= cfg.min_area):
            return layer if light is None or cfg.relight == "none" else relight_layer(assets, background, layer)
    return None


def beside_whom(cfg: ComposeConfig, mode: str, layers: list[ObjectLayer], chosen: list[SceneObject],
                rng: np.random.Generator) -> tuple[np.ndarray, float] | None:
    """With probability cfg.group_share (plane poses, once an object stands in the image): (base point [3] in the
    camera frame, footprint radius in the plane's units) of one of the objects standing, for the next to stand
    beside; else None. Draws nothing from `rng` when group_share is 0."""
    if mode != "plane" or not layers or cfg.group_share <= 0 or rng.random() >= cfg.group_share:
        return None
    k = int(rng.integers(len(layers)))
    pose, obj = layers[k].pose, chosen[k]
    return pose.apply(obj.frame.base_point[None])[0], pose.scale * obj.radius


def relight_layer(assets: ComposeAssets, background: Background, layer: ObjectLayer) -> ObjectLayer:
    """The layer with the exposure and white balance of the background around it (its window grown by its own
    size on every side)."""
    cfg, (rows, columns) = assets.cfg, layer.shape
    box = (layer.x0 - columns, layer.y0 - rows, layer.x0 + 2 * columns, layer.y0 + 2 * rows)
    gain = exposure_gain(assets.lights[background.bg_id], box, cfg.relight_strength, cfg.relight_max_gain)
    layer.rgb = np.minimum(layer.rgb * gain.astype(np.float32), layer.alpha[..., None])
    return layer


def object_shadow(assets: ComposeAssets, obj: SceneObject, background: Background, layer: ObjectLayer,
                  light: SceneLight) -> Shadow | None:
    """The shadow a plane-posed object casts on its support plane under the image's light."""
    cfg = assets.cfg
    look = ShadowLook(light.direction, light.strength, cfg.shadow_contact, cfg.shadow_softness)
    return cast_shadow(obj.caster, layer.pose, obj.frame, background.K, background.depth, look,
                       cfg.shadow_depth_tolerance, cfg.depth_tolerance_abs)


def compose_image(assets: ComposeAssets, index: int, images_dir: Path) -> ComposedImage:
    """Compose image `index`, write images_dir/%06d.jpg and return its annotations."""
    cfg, rng = assets.cfg, image_rng(assets.seed, index)
    background = pick_background(cfg, assets.backgrounds, rng)
    mode, fallback = placement_mode(cfg, background, rng)
    light = image_light(assets, background, index)
    count = int(rng.integers(cfg.min_objects, cfg.max_objects + 1))
    layers, chosen, shadows, dropped = [], [], [], {"unplaceable": 0, "hidden_by_objects": 0}
    record = []  # what was placed, kept and why not (placements.json)
    for _ in range(count):
        obj = assets.objects[int(rng.integers(len(assets.objects)))]
        layer = place_object(assets, obj, background, mode, rng, light, beside_whom(cfg, mode, layers, chosen, rng))
        if layer is None:
            dropped["unplaceable"] += 1
            record.append({"object": obj.name, "kept": False, "why": "unplaceable"})
            continue
        if cfg.augment:
            layer.rgb = augment_object(layer.rgb, layer.alpha, rng, pixel_aug(cfg))
        layers.append(layer)
        chosen.append(obj)
        shadows.append(object_shadow(assets, obj, background, layer, light)
                       if light is not None and cfg.shadow and mode == "plane" else None)
    image, visible = composite_layers(apply_shadows(background.image, [s for s in shadows if s]), layers)
    fractions = [float(visible[k].sum()) / layer.full_alpha_sum for k, layer in enumerate(layers)]
    keep = [k for k in range(len(layers)) if fractions[k] >= cfg.min_visible_fraction
            and int((visible[k] > cfg.mask_threshold).sum()) >= cfg.min_area]
    record += [{"object": obj.name, "kept": k in keep, "why": "" if k in keep else "hidden_by_objects"}
               for k, obj in enumerate(chosen)]
    if len(keep) < len(layers):  # an object hidden by others is removed from the image, not left unlabelled
        dropped["hidden_by_objects"] += len(layers) - len(keep)
        layers, chosen, shadows = [layers[k] for k in keep], [chosen[k] for k in keep], [shadows[k] for k in keep]
        image, visible = composite_layers(apply_shadows(background.image, [s for s in shadows if s]), layers)
        fractions = [float(visible[k].sum()) / layer.full_alpha_sum for k, layer in enumerate(layers)]
    file_name = f"{index:06d}.jpg"  # COCO file_name, relative to the dataset's images/ folder
    write_jpeg(images_dir / file_name, image)
    width, height = background.size
    instances = [Instance(obj.category_id, visible[k] > cfg.mask_threshold,
                          {"visible_fraction": round(min(fractions[k], 1.0), 4), "placement": mode,
                           "background": background.bg_id,
                           **instance_geometry(layers[k], obj.metric, cfg.mask_threshold, width, height)})
                 for k, obj in enumerate(chosen) if (visible[k] > cfg.mask_threshold).any()]
    return ComposedImage(file_name, width, height, instances,
                         {"placement": mode, "fallback": fallback, "dropped": dropped, "objects": record},
                         camera_fields(background, mode, cfg.depth_median_size))


def instance_geometry(layer: ObjectLayer, metric: MetricFrame, threshold: float, width: int, height: int) -> dict:
    """An instance's annotation fields beyond COCO's: "pose" {"R" [3x3], "t" [3] metres, "render_scale"} of
    the object's metric frame in the camera frame (placement.metric_pose) and "amodal_segmentation", the RLE
    of its own opacity above `threshold` before any occlusion, inside the width x height image."""
    rotation, translation, render_scale = metric_pose(layer.pose, metric)
    amodal = np.zeros((height, width), bool)
    rows, columns = layer.shape
    amodal[layer.y0:layer.y0 + rows, layer.x0:layer.x0 + columns] = layer.unoccluded_alpha > threshold
    return {"pose": {"R": (np.round(rotation, 6) + 0.0).tolist(), "t": (np.round(translation, 6) + 0.0).tolist(),
                     "render_scale": round(render_scale, 6)},
            "amodal_segmentation": mask_to_rle(amodal)}


def camera_fields(background: Background, mode: str, median_size: int) -> dict:
    """An image's COCO entry fields beyond COCO's: the camera "K" [3x3] and the "depth" that occluded its
    objects (plane placement; None for random poses, which no depth occludes): bg_depth's depth.npy of the
    background, named by compose's input for it (the dataset's manifest.json maps it to its cache key)."""
    depth = None
    if mode == "plane":
        depth = {"input": input_name("depth", background.bg_id), "file": DepthRecord.ARRAY,
                 "median_filter_px": median_size}
    return {"K": np.asarray(background.K, dtype=np.float64).tolist(), "depth": depth}


def object_models(cfg: ComposeConfig, inputs: dict[str, Path]) -> dict[str, dict]:
    """{name: its model file and the map of its points into the poses' metric frame} of the objects with inputs:
    the file is the extract folder's object.ply named by compose's input for it; its model points are the means
    of its Gaussians at least `min_opacity` opaque (placement.model_points), and a model point x is at
    metres_per_unit * axes^T (x - origin) (placement.MetricFrame)."""
    found = per_object(inputs, [o["name"] for o in cfg.objects], INPUTS.object_kinds, "compose")
    models = {}
    for k, spec in enumerate(cfg.objects):
        if spec["name"] in found:
            metric = load_object(spec["name"], k + 1, found[spec["name"]]["object"], float(spec["height_m"])).metric
            models[spec["name"]] = {"input": input_name("object", spec["name"]), "file": OBJECT_PLY,
                                    "min_opacity": MODEL_OPACITY, **metric.as_dict()}
    return models


def photos_without_plane(cfg: ComposeConfig, inputs: dict[str, Path]) -> dict[str, str]:
    """{photo id: why} of the photos `placement: plane` leaves out (none when no photo has a plane: then every
    photo is used, with random poses). A warning names them, except those cfg.expected_without_plane lists (the
    sample's own photos, some made without a floor), which an information line counts."""
    if cfg.placement != "plane":
        return {}
    issues, photos = plane_issues(inputs), fanned(inputs, "background")
    if len(issues) == len(photos):
        log.warning("no photo has a placement plane (%s): every object is posed at random",
                    ", ".join(sorted(set(issues.values()))))
        return {}
    expected = {bg_id for bg_id in issues if bg_id in set(cfg.expected_without_plane)}
    if expected:
        log.info("placement 'plane' leaves out %d of %d photos of the sample (expected: views without a floor): %s",
                 len(expected), len(photos), ", ".join(sorted(expected)))
    unexpected = {bg_id: why for bg_id, why in issues.items() if bg_id not in expected}
    if unexpected:
        log.warning("placement 'plane' leaves out %d of %d photos, which have no placement plane: %s",
                    len(unexpected), len(photos), ", ".join(f"{bg_id} ({why})" for bg_id, why in unexpected.items()))
    return issues


def run(ctx: Context) -> dict:
    """Compose cfg.num_images images from cfg.first_image on (a shard) into ctx.out as a COCO dataset; returns
    the stats."""
    cfg = ctx.typed(ComposeConfig)
    inputs = {k: Path(v) for k, v in ctx.inputs.items()}
    names = [o["name"] for o in cfg.objects]
    present = per_object(inputs, names, INPUTS.object_kinds, "compose")
    unused_photos = photos_without_plane(cfg, inputs)
    images = generate(load_assets, (cfg, ctx.seed, inputs), compose_image, cfg.num_images,
                      ctx.out / "images", cfg.workers, cfg.first_image)
    return write_dataset(ctx.out, names, images, cfg.num_images, ctx.progress, cfg.preview_count,
                         info={"stage": "compose", "augment": cfg.augment, "placement": cfg.placement,
                               "shadow": cfg.shadow, "relight": cfg.relight,
                               "item": ctx.item, "object_models": object_models(cfg, inputs)},
                         extra_stats={"left_out": left_out_items(ctx.left_out, names, present),
                                      "photos": len(fanned(inputs, "background")),
                                      "photos_without_plane": unused_photos,
                                      "expected_without_plane": sorted(set(unused_photos)
                                                                       & set(cfg.expected_without_plane))})
