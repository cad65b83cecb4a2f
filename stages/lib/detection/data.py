"""COCO instance datasets for Mask R-CNN: reading (RLE or polygon masks) and basic augmentation."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

from stages.lib.coco import load_coco
from stages.records.coco_dataset import CocoDataset

CLOSEUP_MAX_ZOOM = 3.0  # close-ups enlarge an object at most this much: more only shows a blur of its pixels


@dataclass
class Augmentation:
    """Training augmentation: horizontal flip, scale jitter (zoom in by cropping, out by padding), colour."""

    hflip: bool = True
    scale_min: float = 0.75  # content scale factor range; 1 = unchanged
    scale_max: float = 1.25
    colour: float = 0.2  # max relative change of brightness, contrast and saturation
    crop: int = 0  # after resizing, a crop x crop window around a random instance (0 = the whole image)
    closeup_share: float = 0.0  # share of samples that are close-ups: one instance zoomed to fill the window
    closeup_fill: tuple[float, float] = (0.5, 1.0)  # close-ups: the instance's longer side / the window side


class CocoInstances:
    """A COCO folder (`images/` + `annotations.json`) as Mask R-CNN samples.

    Labels are 1..K in the order of `category_names` (categories sorted by id); crowd annotations
    are skipped. Images are resized so the longer side is `image_size` (the model's size).
    """

    def __init__(self, folder: str | Path, image_size: int):
        self.folder = Path(folder)
        self.coco = load_coco(self.folder)  # checked: categories present and distinct, every image file exists
        categories = sorted(self.coco.loadCats(self.coco.getCatIds()), key=lambda c: c["id"])
        self.category_names = [c["name"] for c in categories]
        self.label_of_category = {c["id"]: i + 1 for i, c in enumerate(categories)}
        self.image_ids = sorted(self.coco.getImgIds())
        if not self.image_ids:
            raise ValueError(f"{self.folder / CocoDataset.JSON}: no images")
        self.image_size = image_size

    def __len__(self) -> int:
        return len(self.image_ids)

    def image_path(self, index: int) -> Path:
        """Path of the index-th image file."""
        return CocoDataset.image_file(self.folder, self.coco.imgs[self.image_ids[index]])

    def raw(self, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Image [H, W, 3] uint8, masks [N, H, W] bool, labels [N] int64 at the file's resolution."""
        image = np.asarray(Image.open(self.image_path(index)).convert("RGB"))
        anns = [a for a in self.coco.imgToAnns[self.image_ids[index]] if not a.get("iscrowd", 0)]
        h, w = image.shape[:2]
        masks = np.zeros((len(anns), h, w), bool)
        for k, ann in enumerate(anns):
            mask = self.coco.annToMask(ann)
            if mask.shape != (h, w):
                raise ValueError(f"{self.image_path(index)}: annotation {ann['id']} mask is {mask.shape}, image {(h, w)}")
            masks[k] = mask > 0
        labels = np.array([self.label_of_category[a["category_id"]] for a in anns], np.int64)
        return image, masks, labels

    def sample(self, index: int, rng: np.random.Generator | None = None,
               augmentation: Augmentation | None = None) -> tuple[torch.Tensor, dict]:
        """One training sample: image [3, h, w] float in [0, 1] and a Mask R-CNN target dict.

        target: boxes [N, 4] float x0 y0 x1 y1, labels [N] int64, masks [N, h, w] uint8.
        """
        image, masks, labels = self.raw(index)
        image_t = torch.from_numpy(image.copy()).permute(2, 0, 1).float() / 255.0  # [3, H, W]
        masks_t = torch.from_numpy(masks)  # [N, H, W] bool
        if augmentation is not None:
            image_t, masks_t = augment(image_t, masks_t, rng, augmentation)
        image_t, masks_t = resize_longer_side(image_t, masks_t, self.image_size)
        if augmentation is not None and augmentation.closeup_share > 0 and rng.random() < augmentation.closeup_share:
            fill = rng.uniform(*augmentation.closeup_fill)
            image_t, masks_t = closeup_of_instance(image_t, masks_t, augmentation.crop or self.image_size, fill, rng)
        elif augmentation is not None and augmentation.crop > 0:
            image_t, masks_t = crop_around_instance(image_t, masks_t, augmentation.crop, rng)
        return image_t, masks_to_target(masks_t, torch.from_numpy(labels))


def resize_longer_side(image: torch.Tensor, masks: torch.Tensor, size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Resize image [3, H, W] (bilinear) and masks [N, H, W] bool (nearest) to longer side `size`."""
    h, w = image.shape[-2:]
    scale = size / max(h, w)
    new_hw = (max(1, round(h * scale)), max(1, round(w * scale)))
    if new_hw == (h, w):
        return image, masks
    image = F.interpolate(image[None], size=new_hw, mode="bilinear", align_corners=False, antialias=scale < 1)[0]
    if masks.shape[0]:
        masks = F.interpolate(masks[None].float(), size=new_hw, mode="nearest")[0] > 0.5
    else:
        masks = masks.new_zeros((0, *new_hw))
    return image.clamp(0, 1), masks


def augment(image: torch.Tensor, masks: torch.Tensor, rng: np.random.Generator,
            aug: Augmentation) -> tuple[torch.Tensor, torch.Tensor]:
    """Flip, scale-jitter and colour-jitter image [3, H, W] in [0, 1] with masks [N, H, W] bool."""
    if aug.hflip and rng.random() < 0.5:
        image, masks = image.flip(-1), masks.flip(-1)
    scale = rng.uniform(aug.scale_min, aug.scale_max)
    if scale != 1.0:
        image, masks = zoom(image, masks, scale, rng)
    if aug.colour > 0:
        image = colour_jitter(image, rng.uniform(1 - aug.colour, 1 + aug.colour, size=3))
    return image, masks


def zoom(image: torch.Tensor, masks: torch.Tensor, scale: float,
         rng: np.random.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Show the content `scale` times larger on a canvas of the same aspect: crop (>1) or pad (<1).

    The window of size (H, W) / scale is placed at a random offset; padding is mid-grey.
    Output sizes are the window's; the caller resizes to the model size afterwards.
    """
    h, w = image.shape[-2:]
    win_h, win_w = max(1, round(h / scale)), max(1, round(w / scale))
    y0 = int(rng.integers(min(0, h - win_h), max(0, h - win_h) + 1))
    x0 = int(rng.integers(min(0, w - win_w), max(0, w - win_w) + 1))
    return padded_window(image, masks, y0, x0, win_h, win_w)


def padded_window(image: torch.Tensor, masks: torch.Tensor, y0: int, x0: int, win_h: int,
                  win_w: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The win_h x win_w window at (y0, x0) of image [3, H, W] and masks [N, H, W] bool; the part of the
    window outside the image is mid-grey (image) and empty (masks)."""
    h, w = image.shape[-2:]
    out_image = torch.full((3, win_h, win_w), 0.5)
    out_masks = torch.zeros((masks.shape[0], win_h, win_w), dtype=torch.bool)
    sy0, sx0 = max(y0, 0), max(x0, 0)  # source window clipped to the image
    sy1, sx1 = min(y0 + win_h, h), min(x0 + win_w, w)
    out_image[:, sy0 - y0: sy1 - y0, sx0 - x0: sx1 - x0] = image[:, sy0:sy1, sx0:sx1]
    out_masks[:, sy0 - y0: sy1 - y0, sx0 - x0: sx1 - x0] = masks[:, sy0:sy1, sx0:sx1]
    return out_image, out_masks


def random_instance_pixels(masks: torch.Tensor, rng: np.random.Generator) -> tuple[torch.Tensor, torch.Tensor] | None:
    """Row and column indices ([P], [P]) of the pixels of one instance of masks [N, H, W] bool, chosen
    at random among the non-empty ones; None (and no draw from rng) when every mask is empty."""
    present = [k for k in range(masks.shape[0]) if masks[k].any()]
    if not present:
        return None
    return torch.nonzero(masks[present[int(rng.integers(len(present)))]], as_tuple=True)


def crop_around_instance(image: torch.Tensor, masks: torch.Tensor, size: int,
                         rng: np.random.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """A window of at most size x size of image [3, H, W] and masks [N, H, W] bool.

    The window holds the mask centre of one instance chosen at random (anywhere if there is none),
    at a random position; objects keep the scale of the full image, so training on windows costs
    less per step than training on whole images without shrinking the objects.
    """
    h, w = image.shape[-2:]
    if h <= size and w <= size:
        return image, masks
    pixels = random_instance_pixels(masks, rng)
    if pixels is not None:
        centre = (int(pixels[0].float().mean()), int(pixels[1].float().mean()))
    else:
        centre = (int(rng.integers(h)), int(rng.integers(w)))
    starts = []
    for c, extent in zip(centre, (h, w)):
        window = min(size, extent)
        low, high = max(0, c - window + 1), min(c, extent - window)
        starts.append(int(rng.integers(low, high + 1)))
    (y0, x0), (wh, ww) = starts, (min(size, h), min(size, w))
    return image[:, y0:y0 + wh, x0:x0 + ww], masks[:, y0:y0 + wh, x0:x0 + ww]


def closeup_of_instance(image: torch.Tensor, masks: torch.Tensor, size: int, fill: float,
                        rng: np.random.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """A size x size close-up of one instance of image [3, H, W] with masks [N, H, W] bool.

    A random instance is zoomed so that the longer side of its box is `fill` (<= 1) of the window (or
    CLOSEUP_MAX_ZOOM times its size, if smaller) and lies whole inside it at a random position; the window stays inside
    the image where the image is large enough, and is padded mid-grey where not. Without instances, a plain window
    (crop_around_instance). Objects larger than the training window are otherwise seen only in pieces, and the detector
    then finds parts of large objects instead of the whole (real close-up photos).
    """
    pixels = random_instance_pixels(masks, rng)
    if pixels is None:
        return crop_around_instance(image, masks, size, rng)
    ys, xs = pixels
    box = (int(ys.min()), int(xs.min()), int(ys.max()) + 1, int(xs.max()) + 1)  # y0 x0 y1 x1
    extent = max(box[2] - box[0], box[3] - box[1])
    side = max(extent, round(extent / fill), round(size / CLOSEUP_MAX_ZOOM))
    starts = []
    for low_edge, high_edge, image_length in ((box[0], box[2], image.shape[-2]), (box[1], box[3], image.shape[-1])):
        low, high = high_edge - side, low_edge  # the box inside the window
        if side <= image_length:
            low, high = max(low, 0), min(high, image_length - side)  # and the window inside the image
        starts.append(int(rng.integers(low, high + 1)))
    window_image, window_masks = padded_window(image, masks, starts[0], starts[1], side, side)
    return resize_longer_side(window_image, window_masks, size)


def colour_jitter(image: torch.Tensor, factors: np.ndarray) -> torch.Tensor:
    """Scale brightness, contrast and saturation of image [3, H, W] by factors [3]."""
    brightness, contrast, saturation = (float(f) for f in factors)
    image = image * brightness
    image = (image - image.mean()) * contrast + image.mean()
    grey = (0.299 * image[0] + 0.587 * image[1] + 0.114 * image[2])[None]  # [1, H, W]
    image = (image - grey) * saturation + grey
    return image.clamp(0, 1)


def masks_to_target(masks: torch.Tensor, labels: torch.Tensor, min_pixels: int = 4) -> dict:
    """Mask R-CNN target from masks [N, H, W] bool and labels [N]; drops masks under `min_pixels`."""
    keep = masks.flatten(1).sum(1) >= min_pixels if masks.shape[0] else torch.zeros(0, dtype=torch.bool)
    masks, labels = masks[keep], labels[keep]
    boxes = torch.zeros((masks.shape[0], 4))
    for k, mask in enumerate(masks):
        ys, xs = torch.nonzero(mask, as_tuple=True)
        boxes[k] = torch.stack([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1]).float()
    return {"boxes": boxes, "labels": labels, "masks": masks.to(torch.uint8)}
