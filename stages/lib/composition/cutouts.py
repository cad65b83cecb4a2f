"""Object cut-outs for Cut-and-Paste: K capture frames spread over the video, masked by rendering
the extracted object model at each frame's camera (the paper used manual Segment Anything)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from scipy.ndimage import binary_fill_holes

from stages.contract.errors import StageError
from stages.lib.gaussians.model import Gaussians
from stages.lib.gaussians.rasterize import render
from stages.lib.imageio import read_rgb
from stages.records.cameras import CamerasRecord
from stages.records.sfm import SfmRecord


@dataclass
class Cutout:
    """An object crop: colour [h, w, 3] uint8 and mask [h, w] bool, cropped to the mask's box."""

    rgb: np.ndarray
    mask: np.ndarray
    source: str  # frame file it came from


def spread_indices(count: int, k: int) -> list[int]:
    """k indices spread evenly over 0..count-1 (all of them when count <= k)."""
    if count <= k:
        return list(range(count))
    return [int(round(x)) for x in np.linspace(0, count - 1, k)]


def clean_mask(mask: np.ndarray, open_px: int) -> np.ndarray:
    """Morphological opening with an open_px x open_px square, then hole filling. mask: [H, W] bool."""
    if open_px > 1:
        kernel = np.ones((open_px, open_px), np.uint8)
        mask = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_OPEN, kernel).astype(bool)
    return binary_fill_holes(mask)


def object_mask(g: Gaussians, viewmat: np.ndarray, K: np.ndarray, width: int, height: int, threshold: float,
                open_px: int, backend: str = "auto") -> np.ndarray:
    """The object's mask [H, W] bool in a frame: rendered opacity > threshold, cleaned."""
    with torch.no_grad():
        out = render(g, torch.as_tensor(viewmat, dtype=torch.float32), torch.as_tensor(K, dtype=torch.float32),
                     width, height, backend=backend)
    return clean_mask(out.alpha.numpy() > threshold, open_px)


def crop_to_mask(rgb: np.ndarray, mask: np.ndarray, source: str) -> Cutout | None:
    """The cut-out of rgb [H, W, 3] inside mask [H, W]; None for an empty mask."""
    if not mask.any():
        return None
    ys, xs = np.nonzero(mask)
    box = (slice(ys.min(), ys.max() + 1), slice(xs.min(), xs.max() + 1))
    return Cutout(np.ascontiguousarray(rgb[box]), np.ascontiguousarray(mask[box]), source)


def object_cutouts(name: str, g: Gaussians, splat_dir: Path, sfm: SfmRecord, k: int, threshold: float,
                   open_px: int, min_pixels: int, backend: str = "auto") -> list[Cutout]:
    """Cut-outs of one object from k capture frames spread over its capture (cameras.json order)."""
    if not CamerasRecord.exists(splat_dir):
        raise StageError(f"cut_and_paste: object {name!r}: {splat_dir / CamerasRecord.JSON} missing (run splat_train)")
    cameras = CamerasRecord.read(splat_dir)
    if not cameras.frames:
        raise StageError(f"cut_and_paste: object {name!r}: {splat_dir / CamerasRecord.JSON} lists no frames")
    width, height = cameras.width, cameras.height
    cutouts = []
    for index in spread_indices(len(cameras.frames), k):
        frame = cameras.frames[index]
        rgb = read_rgb(sfm.image(frame.file))
        if rgb.shape[:2] != (height, width):
            rgb = cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)
        mask = object_mask(g, frame.viewmat, frame.K, width, height, threshold, open_px, backend)
        cutout = crop_to_mask(rgb, mask, frame.file)
        if cutout is not None and int(cutout.mask.sum()) >= min_pixels:
            cutouts.append(cutout)
    if not cutouts:
        raise StageError(f"cut_and_paste: object {name!r}: the object model covers no frame of {splat_dir}; "
                         "check the extract output")
    return cutouts
