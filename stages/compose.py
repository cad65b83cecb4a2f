"""compose: the Cut-and-Splat generator (paper: "Scene Composition").

Per image (seeded by its index): a background, 1..max objects, each stood on a placement plane
(normal on the plane normal, random turn about up, size from its real height and the metric depth)
or, with `placement: random` (the no_placement variant) and for the random share, posed at random. With
`placement: plane` only photos with a placement plane are drawn while there is one (stats.json lists the
others, `photos_without_plane`); when no photo has one, every object is posed at random. Objects are
rendered in their image windows, occluded by the median-filtered background depth and by each other,
augmented (random SH view direction, pixel augmentations) and alpha-blended. Output: a COCO dataset (see docs/stage_contracts.md). The objects and photos the engine left
out (their upstream stages failed) are listed in stats.json (`left_out`); the categories stay those of the
data config, so a left-out object has no instances.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from stages.composition.augment import PixelAugStrengths, augment_object
from stages.composition.backgrounds import Background, load_backgrounds, plane_issues
from stages.composition.dataset import DATASET_IMAGES, ComposedImage, Instance, generate, image_rng, write_dataset, write_jpeg
from stages.composition.occlusion import composite_layers, occlude_by_background
from stages.composition.placement import ObjectFrame, sample_plane_pose, sample_random_pose
from stages.composition.render_object import ObjectLayer, render_object_layer
from stages.errors import StageError
from stages.fan_in import InputKinds, fanned, left_out_items, per_object
from stages.gaussians.model import Gaussians
from stages.gaussians.ply import read_ply
from stages.records.extract import ExtractRecord

if TYPE_CHECKING:  # the engine's object; not part of the stage's cache key
    from stages.context import Context

log = logging.getLogger(__name__)

PLACEMENTS = ("plane", "random")
INPUTS = InputKinds(per_object=("object",), per_photo=("background", "depth", "planes"))


@dataclass
class ComposeConfig:
    """Settings of the compose stage (defaults sized for a 2-core CPU)."""

    augment: bool = True  # random SH view direction and pixel augmentations (variant no_aug: false)
    placement: str = "plane"  # "plane": on placement planes | "random": random poses (variant no_placement)
    objects: list[dict] = field(default_factory=list)  # [{"name", "height_m"}], category ids 1..n in this order
    num_images: int = DATASET_IMAGES
    min_objects: int = 1
    max_objects: int = 3
    random_placement_share: float = 0.0  # share of images posed at random with placement "plane" (paper: none)
    min_visible_fraction: float = 0.25  # drop objects with less of their alpha visible
    min_area: int = 64  # drop objects whose visible mask has fewer pixels
    mask_threshold: float = 0.5  # visible alpha above this is in the mask
    placement_attempts: int = 5  # poses tried per object before it is dropped
    apparent_height: list[float] = field(default_factory=lambda: [0.12, 0.4])  # random / non-metric size,
    #                                                                          fraction of image height
    random_depth: list[float] = field(default_factory=lambda: [2.0, 4.0])  # random poses: depth range
    depth_median_size: int = 5  # median filter of the background depth (pixels)
    depth_tolerance_rel: float = 0.03  # object pixel occluded when behind the surface by more than this
    depth_tolerance_abs: float = 0.02  # ... plus this (metres / depth units)
    max_window_fraction: float = 4.0  # reject poses whose render window exceeds this many images
    image_size: list[int] | None = None  # [width, height]; None = each background's own size
    aug_blur_prob: float = 0.3
    aug_blur_sigma: float = 1.5
    aug_brightness: float = 0.15
    aug_contrast: float = 0.2
    aug_saturation: float = 0.3
    aug_hue: float = 0.03
    aug_noise_std: float = 0.03
    aug_tone_curve: float = 0.1
    render_backend: str = "auto"
    workers: int = 0  # image processes, 0 = one per core (the files are the same for any count)
    preview_count: int = 16

    def __post_init__(self) -> None:
        if self.placement not in PLACEMENTS:
            raise StageError(f"compose: unknown placement {self.placement!r}; choose one of {PLACEMENTS}")
        if not 1 <= self.min_objects <= self.max_objects:
            raise StageError(f"compose: need 1 <= min_objects <= max_objects, got {self.min_objects}, "
                             f"{self.max_objects}")

    def pixel_aug(self) -> PixelAugStrengths:
        """The pixel augmentation strengths."""
        return PixelAugStrengths(self.aug_blur_prob, self.aug_blur_sigma, self.aug_brightness, self.aug_contrast,
                                 self.aug_saturation, self.aug_hue, self.aug_noise_std, self.aug_tone_curve)


@dataclass
class SceneObject:
    """An extracted object model with its ground frame and real height."""

    name: str
    category_id: int
    gaussians: Gaussians
    frame: ObjectFrame
    height_m: float


@dataclass
class ComposeAssets:
    """Everything one process needs to compose images."""

    cfg: ComposeConfig
    seed: int
    objects: list[SceneObject]
    backgrounds: list[Background]


def load_object(name: str, category_id: int, folder: Path, height_m: float) -> SceneObject:
    """Read an extract folder (object.ply + extract.json)."""
    ply_path = folder / "object.ply"
    if not ply_path.is_file():
        raise StageError(f"compose: object {name!r}: {folder} lacks object.ply (run extract)")
    meta = ExtractRecord.read(folder)
    frame = ObjectFrame(meta.normal, meta.base_point, meta.height)
    return SceneObject(name, category_id, read_ply(ply_path), frame, float(height_m))


def load_assets(cfg_params: dict, seed: int, inputs: dict[str, Path]) -> ComposeAssets:
    """Load objects and backgrounds (called once per worker process)."""
    cfg = ComposeConfig(**cfg_params)
    if not cfg.objects or any("name" not in o or "height_m" not in o for o in cfg.objects):
        raise StageError("compose: `objects` must list {name, height_m} for every object (data config)")
    found = per_object(inputs, [o["name"] for o in cfg.objects], INPUTS.per_object, "compose")
    objects = [load_object(spec["name"], k + 1, found[spec["name"]]["object"], float(spec["height_m"]))
               for k, spec in enumerate(cfg.objects) if spec["name"] in found]
    backgrounds = load_backgrounds(inputs, "compose", cfg.depth_median_size, cfg.image_size)
    return ComposeAssets(cfg, seed, objects, backgrounds)


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
                 rng: np.random.Generator) -> ObjectLayer | None:
    """Pose and render one object (with background occlusion for plane poses); None if every try fails."""
    cfg = assets.cfg
    width, height = background.size
    apparent = (cfg.apparent_height[0], cfg.apparent_height[1])
    for _ in range(cfg.placement_attempts):
        if mode == "plane":
            pose = sample_plane_pose(obj.frame, obj.height_m, background.planes, background.metric, background.K,
                                     height, rng, apparent)
        else:
            pose = sample_random_pose(obj.frame, background.K, width, height, rng, apparent,
                                      (cfg.random_depth[0], cfg.random_depth[1]))
        view_dir = None
        if cfg.augment:
            view_dir = rng.normal(size=3)
            view_dir /= np.linalg.norm(view_dir)
        layer = render_object_layer(obj.gaussians, pose, background.K, width, height, view_dir,
                                    int(cfg.max_window_fraction * width * height), cfg.render_backend)
        if layer is None or layer.full_alpha_sum <= 0:
            continue
        if mode == "plane":
            layer = occlude_by_background(layer, background.depth, cfg.depth_tolerance_rel, cfg.depth_tolerance_abs)
        if (layer.alpha.sum() >= cfg.min_visible_fraction * layer.full_alpha_sum
                and int((layer.alpha > cfg.mask_threshold).sum()) >= cfg.min_area):
            return layer
    return None


def compose_image(assets: ComposeAssets, index: int, images_dir: Path) -> ComposedImage:
    """Compose image `index`, write images_dir/%06d.jpg and return its annotations."""
    cfg, rng = assets.cfg, image_rng(assets.seed, index)
    background = pick_background(cfg, assets.backgrounds, rng)
    mode, fallback = placement_mode(cfg, background, rng)
    count = int(rng.integers(cfg.min_objects, cfg.max_objects + 1))
    layers, chosen, dropped = [], [], {"unplaceable": 0, "hidden_by_objects": 0}
    for _ in range(count):
        obj = assets.objects[int(rng.integers(len(assets.objects)))]
        layer = place_object(assets, obj, background, mode, rng)
        if layer is None:
            dropped["unplaceable"] += 1
            continue
        if cfg.augment:
            layer.rgb = augment_object(layer.rgb, layer.alpha, rng, cfg.pixel_aug())
        layers.append(layer)
        chosen.append(obj)
    image, visible = composite_layers(background.image, layers)
    fractions = [float(visible[k].sum()) / layer.full_alpha_sum for k, layer in enumerate(layers)]
    keep = [k for k in range(len(layers)) if fractions[k] >= cfg.min_visible_fraction
            and int((visible[k] > cfg.mask_threshold).sum()) >= cfg.min_area]
    if len(keep) < len(layers):  # an object hidden by others is removed from the image, not left unlabelled
        dropped["hidden_by_objects"] += len(layers) - len(keep)
        layers, chosen = [layers[k] for k in keep], [chosen[k] for k in keep]
        image, visible = composite_layers(background.image, layers)
        fractions = [float(visible[k].sum()) / layer.full_alpha_sum for k, layer in enumerate(layers)]
    file_name = f"{index:06d}.jpg"  # COCO file_name, relative to the dataset's images/ folder
    write_jpeg(images_dir / file_name, image)
    instances = [Instance(obj.category_id, visible[k] > cfg.mask_threshold,
                          {"visible_fraction": round(min(fractions[k], 1.0), 4), "placement": mode,
                           "background": background.bg_id})
                 for k, obj in enumerate(chosen) if (visible[k] > cfg.mask_threshold).any()]
    width, height = background.size
    return ComposedImage(file_name, width, height, instances,
                         {"placement": mode, "fallback": fallback, "dropped": dropped})


def photos_without_plane(cfg: ComposeConfig, inputs: dict[str, Path]) -> dict[str, str]:
    """{photo id: why} of the photos `placement: plane` leaves out (none when no photo has a plane: then every
    photo is used, with random poses); a warning says so."""
    if cfg.placement != "plane":
        return {}
    issues, photos = plane_issues(inputs), fanned(inputs, "background")
    if len(issues) == len(photos):
        log.warning("no photo has a placement plane (%s): every object is posed at random",
                    ", ".join(sorted(set(issues.values()))))
        return {}
    if issues:
        log.warning("placement 'plane' leaves out %d of %d photos, which have no placement plane: %s",
                    len(issues), len(photos), ", ".join(f"{bg_id} ({why})" for bg_id, why in issues.items()))
    return issues


def run(ctx: Context) -> dict:
    """Compose cfg.num_images images into ctx.out as a COCO dataset; returns the stats."""
    cfg = ComposeConfig(**ctx.params)
    inputs = {k: Path(v) for k, v in ctx.inputs.items()}
    names = [o["name"] for o in cfg.objects]
    present = per_object(inputs, names, INPUTS.per_object, "compose")
    unused_photos = photos_without_plane(cfg, inputs)
    images = generate(load_assets, (ctx.params, ctx.seed, inputs), compose_image, cfg.num_images,
                      ctx.out / "images", cfg.workers)
    return write_dataset(ctx.out, names, images, cfg.num_images, ctx.progress, cfg.preview_count,
                         info={"stage": "compose", "augment": cfg.augment, "placement": cfg.placement,
                               "item": ctx.item},
                         extra_stats={"left_out": left_out_items(ctx.left_out, names, present),
                                      "photos_without_plane": unused_photos})
