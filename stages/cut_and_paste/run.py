"""cut_and_paste: the Cut-and-Paste baseline (Dwibedi et al. 2017) the paper compares against.

Cut-outs: K frames per object spread over its capture, masked by rendering the extracted object
model at each frame's camera. Per image (seeded by its index): a background, 1..max cut-outs with
random scale, rotation, flip and position, pasted with one blend mode (none, Gaussian, motion,
Poisson). Later pastes cover earlier ones (their masks shrink); objects left too hidden are removed
from the image. Output: a COCO dataset like compose's; the objects and photos the engine left out, and the frame
slots their video could not fill (it reads a photo without its depth, whose node finds a slot empty), are listed in
stats.json (`left_out`).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from stages.contract.errors import StageError
from stages.contract.fan_in import group_name, left_out_items, per_object
from stages.cut_and_paste.spec import INPUTS, CutAndPasteConfig
from stages.lib.composition.backgrounds import Background, empty_slots, load_backgrounds
from stages.lib.composition.blend import paste
from stages.lib.composition.cutouts import Cutout, object_cutouts
from stages.lib.composition.dataset import ComposedImage, Instance, generate, image_rng, write_dataset, write_jpeg
from stages.lib.gaussians.ply import read_ply
from stages.records.sfm import SfmRecord

if TYPE_CHECKING:  # the engine's object; not part of the stage's cache key
    from stages.engine.context import Context


@dataclass
class PasteAssets:
    """Everything one process needs: config, seed, cut-outs per category, backgrounds."""

    cfg: CutAndPasteConfig
    seed: int
    cutouts: list[tuple[int, list[Cutout]]]  # (category id, its cut-outs) of every object present
    backgrounds: list[Background]


@dataclass
class PlacedCutout:
    """A cut-out warped into image coordinates."""

    category_id: int
    colour: np.ndarray  # [H, W, 3] float32, valid where mask
    mask: np.ndarray  # [H, W] bool, inside the image
    full_area: float  # pasted area including any part outside the image


def place_cutout(cutout: Cutout, width: int, height: int, rng: np.random.Generator,
                 cfg: CutAndPasteConfig) -> tuple[np.ndarray, np.ndarray, float]:
    """Randomly scale, rotate, flip and position a cut-out in a width x height image.

    Returns colour [H, W, 3] float32, mask [H, W] bool and the full pasted area in pixels.
    """
    rgb, mask = cutout.rgb, cutout.mask
    if rng.random() < cfg.flip_prob:
        rgb, mask = rgb[:, ::-1], mask[:, ::-1]
    h, w = mask.shape
    scale = rng.uniform(*cfg.size_range) * min(width, height) / max(h, w)
    angle = rng.uniform(-cfg.max_rotation_deg, cfg.max_rotation_deg)
    u, v = rng.uniform(0, width), rng.uniform(0, height)
    matrix = cv2.getRotationMatrix2D((w / 2, h / 2), angle, scale)
    matrix[:, 2] += (u - w / 2, v - h / 2)
    colour = cv2.warpAffine(np.ascontiguousarray(rgb).astype(np.float32) / 255.0, matrix, (width, height),
                            flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    warped = cv2.warpAffine(np.ascontiguousarray(mask).astype(np.float32), matrix, (width, height),
                            flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    return colour, warped > 0.5, float(mask.sum()) * scale * scale


def visible_masks(placed: list[PlacedCutout]) -> list[np.ndarray]:
    """Each pasted mask minus the masks pasted after it (later pastes cover earlier ones)."""
    masks = [p.mask.copy() for p in placed]
    for k in range(len(placed)):
        for later in placed[k + 1:]:
            masks[k] &= ~later.mask
    return masks


def paste_image(assets: PasteAssets, index: int, images_dir: Path) -> ComposedImage:
    """Make image `index`, write images_dir/%06d.jpg and return its annotations."""
    cfg, rng = assets.cfg, image_rng(assets.seed, index)
    background = assets.backgrounds[int(rng.integers(len(assets.backgrounds)))]
    width, height = background.size
    mode = cfg.blend_modes[int(rng.integers(len(cfg.blend_modes)))]
    placed = []
    for _ in range(int(rng.integers(cfg.min_objects, cfg.max_objects + 1))):
        category_id, cutouts = assets.cutouts[int(rng.integers(len(assets.cutouts)))]
        cutout = cutouts[int(rng.integers(len(cutouts)))]
        colour, mask, full_area = place_cutout(cutout, width, height, rng, cfg)
        placed.append(PlacedCutout(category_id, colour, mask, full_area))
    masks = visible_masks(placed)
    keep = [k for k, m in enumerate(masks) if m.sum() >= max(cfg.min_area, cfg.min_visible_fraction * placed[k].full_area)]
    dropped = len(placed) - len(keep)
    placed = [placed[k] for k in keep]  # removed objects are not pasted at all (no unlabelled objects)
    masks = visible_masks(placed)
    image = background.image.copy()
    for item in placed:
        if item.mask.any():
            image = paste(image, item.colour, item.mask, mode, rng)
    write_jpeg(images_dir / f"{index:06d}.jpg", image)
    instances = [Instance(item.category_id, mask, {"visible_fraction": round(min(float(mask.sum()) / item.full_area, 1.0), 4),
                                                   "blend": mode, "background": background.bg_id})
                 for item, mask in zip(placed, masks) if mask.any()]
    return ComposedImage(f"{index:06d}.jpg", width, height, instances,
                         {"placement": "cut_and_paste", "blend": mode, "dropped": {"hidden_or_small": dropped}})


def load_assets(cfg: CutAndPasteConfig, seed: int, cutouts: list[tuple[int, list[Cutout]]],
                inputs: dict[str, Path]) -> PasteAssets:
    """Load the backgrounds (called once per worker process; cut-outs come ready)."""
    return PasteAssets(cfg, seed, cutouts, load_backgrounds(inputs, "cut_and_paste", 1, cfg.image_size))


def collect_cutouts(cfg: CutAndPasteConfig, inputs: dict[str, Path]) -> dict[str, tuple[int, list[Cutout]]]:
    """{name: (category id, cut-outs)} of the configured objects that have inputs, in category order."""
    if not cfg.objects or any("name" not in o for o in cfg.objects):
        raise StageError("cut_and_paste: `objects` must list {name, ...} for every object (data config)")
    names = [spec["name"] for spec in cfg.objects]
    found = per_object(inputs, names, INPUTS.object_kinds, "cut_and_paste")
    all_cutouts = {}
    for category_id, name in enumerate(names, start=1):
        if name not in found:
            continue
        folders = found[name]
        ply_path = folders["object"] / "object.ply"
        if not ply_path.is_file():
            raise StageError(f"cut_and_paste: object {name!r}: {ply_path} missing (run extract)")
        all_cutouts[name] = (category_id, object_cutouts(name, read_ply(ply_path), folders["splat"], SfmRecord.read(folders["sfm"]),
                                                         cfg.frames_per_object, cfg.mask_threshold, cfg.mask_open_px,
                                                         cfg.min_cutout_pixels, cfg.render_backend))
    return all_cutouts


def run(ctx: Context) -> dict:
    """Make cfg.num_images Cut-and-Paste images from cfg.first_image on (a shard) into ctx.out as a COCO dataset;
    returns the stats."""
    cfg = ctx.typed(CutAndPasteConfig)
    inputs = {k: Path(v) for k, v in ctx.inputs.items()}
    cutouts = collect_cutouts(cfg, inputs)
    images = generate(load_assets, (cfg, ctx.seed, list(cutouts.values()), inputs), paste_image,
                      cfg.num_images, ctx.out / "images", cfg.workers, cfg.first_image)
    names = [o["name"] for o in cfg.objects]
    return write_dataset(ctx.out, names, images, cfg.num_images, ctx.progress, cfg.preview_count,
                         info={"stage": "cut_and_paste", "item": ctx.item},
                         extra_stats={"cutouts_per_object": {name: len(c) for name, (_, c) in cutouts.items()},
                                      "left_out": {**left_out_items(ctx.left_out, names, cutouts),
                                                   **{group_name("photo", bg_id): why
                                                      for bg_id, why in empty_slots(inputs).items()}}})
