"""Is a cut-out object whole? Its alpha box at the capture cameras against boxes drawn by hand on the photos.

For each boxed photo: the frame that `frames` made of it, that frame's camera in the splat's cameras.json,
object.ply rendered there (alpha > 0.5 gives the predicted box), and the drawn box mapped into the undistorted
SfM image (photo pixels x the frame scale, then through the distorted camera SfM refined, `source_camera` in
sfm.json, into the PINHOLE camera of the undistorted images). Boxes are [x0, y0, x1, y1] in continuous pixel
coordinates (the top-left pixel spans 0..1).
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import pycolmap
import torch

from stages.lib.gaussians.model import Gaussians
from stages.lib.gaussians.ply import read_ply
from stages.lib.gaussians.rasterize import render
from stages.records.cameras import CameraFrame, CamerasRecord
from stages.records.frames import FramesRecord
from stages.records.sfm import SfmRecord

EDGE_SAMPLES = 64  # points per box edge mapped through the lens model
ALPHA_THRESHOLD = 0.5


@dataclass
class BoxScore:
    """One boxed photo: the drawn and predicted boxes in the undistorted frame and how they compare."""

    photo: str
    frame: str
    drawn: list[float]  # [4] mapped into the undistorted SfM image
    predicted: list[float] | None  # [4] alpha > 0.5 box; None when the object is not in view
    iou: float
    bottom_error: float  # |bottom edge difference| / drawn box height
    outside_fraction: float  # alpha > 0.5 pixels outside the drawn box grown by `margin`, of all alpha pixels


def load_boxes(path: Path) -> dict[str, list[float]]:
    """{photo file name: [x0, y0, x1, y1]} of a boxes.json ({"boxes": {...}})."""
    return {name: [float(v) for v in box] for name, box in json.loads(Path(path).read_text())["boxes"].items()}


def box_edge_points(box: list[float]) -> np.ndarray:
    """EDGE_SAMPLES points on each edge of `box` [4]: [4 * EDGE_SAMPLES, 2]."""
    x0, y0, x1, y1 = box
    t = np.linspace(0.0, 1.0, EDGE_SAMPLES)
    xs, ys = x0 + t * (x1 - x0), y0 + t * (y1 - y0)
    return np.concatenate([np.stack([xs, np.full_like(t, y0)], 1), np.stack([xs, np.full_like(t, y1)], 1),
                           np.stack([np.full_like(t, x0), ys], 1), np.stack([np.full_like(t, x1), ys], 1)])


def undistorted_box(box: list[float], scale: float, source_camera: dict, K: np.ndarray) -> list[float]:
    """A box drawn on a photo mapped into the undistorted SfM image: photo px x `scale` = frame px, through
    `source_camera` (sfm.json: model, width, height, params) to normalised coordinates, then K [3, 3]."""
    camera = pycolmap.Camera(model=source_camera["model"], width=source_camera["width"],
                             height=source_camera["height"], params=source_camera["params"])
    normalised = camera.cam_from_img(box_edge_points(box) * scale)  # [M, 2]
    pixels = normalised @ K[:2, :2].T + K[:2, 2]  # [M, 2]
    return [float(pixels[:, 0].min()), float(pixels[:, 1].min()), float(pixels[:, 0].max()), float(pixels[:, 1].max())]


def alpha_mask(gaussians: Gaussians, frame: CameraFrame) -> np.ndarray:
    """Mask [H, W] bool of alpha > ALPHA_THRESHOLD of the model rendered at one camera."""
    with torch.no_grad():
        out = render(gaussians, torch.as_tensor(frame.viewmat, dtype=torch.float32),
                     torch.as_tensor(frame.K, dtype=torch.float32), frame.width, frame.height)
    return out.alpha.numpy() > ALPHA_THRESHOLD


def mask_box(mask: np.ndarray) -> list[float] | None:
    """Bounding box [4] of a mask [H, W] (pixel edges), None when it is empty."""
    ys, xs = np.nonzero(mask)
    return None if len(xs) == 0 else [float(xs.min()), float(ys.min()), float(xs.max() + 1), float(ys.max() + 1)]


def box_iou(a: list[float], b: list[float]) -> float:
    """Intersection over union of two boxes [4]."""
    width = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    height = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = width * height
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0


def outside_fraction(mask: np.ndarray, box: list[float], margin: float) -> float:
    """Share of the mask [H, W] outside `box` [4] grown by `margin` pixels (what frames the object)."""
    total = int(mask.sum())
    if total == 0:
        return 0.0
    inside = np.zeros_like(mask)
    x0, y0 = max(0, int(np.floor(box[0] - margin))), max(0, int(np.floor(box[1] - margin)))
    inside[y0:int(np.ceil(box[3] + margin)), x0:int(np.ceil(box[2] + margin))] = True
    return float((mask & ~inside).sum() / total)


def score_cutout(boxes: dict[str, list[float]], frames_dir: Path, sfm_dir: Path, splat_dir: Path,
                 object_ply: Path, margin: float = 8.0) -> list[BoxScore]:
    """Scores of object.ply against the drawn boxes of the photos the capture's frames came from (frames,
    sfm, splat_train output folders). `margin`: the drawn boxes' error in pixels (outside_fraction)."""
    frame_of = {Path(entry.source).name: entry for entry in FramesRecord.read(frames_dir).frames}
    source_camera = SfmRecord.read(sfm_dir).source_camera
    cameras = {frame.file: frame for frame in CamerasRecord.read(splat_dir).frames}
    gaussians = read_ply(object_ply)
    scores = []
    for photo, box in boxes.items():
        entry = frame_of[photo]
        frame = cameras[Path(entry.file).name]
        drawn = undistorted_box(box, entry.scale, source_camera, frame.K)
        mask = alpha_mask(gaussians, frame)
        predicted = mask_box(mask)
        iou = box_iou(predicted, drawn) if predicted is not None else 0.0
        bottom = abs(predicted[3] - drawn[3]) / (drawn[3] - drawn[1]) if predicted is not None else 1.0
        scores.append(BoxScore(photo, frame.file, drawn, predicted, iou, bottom, outside_fraction(mask, drawn, margin)))
    return scores


def scores_json(scores: list[BoxScore]) -> list[dict]:
    """The scores as JSON-ready dicts."""
    return [asdict(score) for score in scores]
