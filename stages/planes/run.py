"""Stage planes: horizontal surfaces of a background photo where an object can stand (the paper's "Object
Placement"; the search on the depth map: stages/lib/planes/search.py).

Reads `depth` (a bg_depth folder) and `image` (the photo); writes planes.json (stages/records/planes.py: the
planes' normals, centres, areas and placement points in the camera frame) and placement.png (the photo with a
dot per placement point, a colour per plane).
"""
from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from stages.lib.imageio import load_photo
from stages.lib.planes.search import CAMERA_UP, find_placement_planes
from stages.planes.spec import PlanesConfig
from stages.records.depth import DepthRecord
from stages.records.planes import PlacementPlane, PlanesRecord

if TYPE_CHECKING:  # the engine's object; not part of the stage's cache key
    from stages.engine.context import Context

log = logging.getLogger(__name__)

PALETTE = [(230, 25, 75), (60, 180, 75), (255, 225, 25), (0, 130, 200), (245, 130, 48),
           (145, 30, 180), (70, 240, 240), (240, 50, 230), (210, 245, 60), (250, 190, 212),
           (0, 128, 128), (220, 190, 255), (170, 110, 40), (255, 250, 200), (128, 0, 0)]


def draw_placement(photo: np.ndarray, planes: list[dict], radius: int) -> np.ndarray:
    """The paper's placement figure: photo uint8 [H, W, 3] with a dot per point, colour per plane."""
    canvas = cv2.cvtColor(photo, cv2.COLOR_RGB2BGR)
    for index, plane in enumerate(planes):
        red, green, blue = PALETTE[index % len(PALETTE)]
        for u, v in np.asarray(plane["pixels"]).reshape(-1, 2):
            cv2.circle(canvas, (int(u), int(v)), radius, (blue, green, red), -1, cv2.LINE_AA)
    return cv2.cvtColor(canvas, cv2.COLOR_BGR2RGB)


def run(ctx: Context) -> dict:
    """Write planes.json and placement.png for ctx.inputs["image"] with depth ctx.inputs["depth"]."""
    cfg = ctx.typed(PlanesConfig)
    started = time.perf_counter()
    image_path = Path(ctx.inputs["image"])
    photo = load_photo(image_path)                                      # [H, W, 3] uint8
    height, width = photo.shape[:2]
    depth_dir = Path(ctx.inputs["depth"])
    record = DepthRecord.read(depth_dir)
    record.check_size(depth_dir, width, height)
    rng = np.random.default_rng(ctx.seed)
    if record.depth is None:
        result = {"up": CAMERA_UP, "planes": [], "up_source": "none", "up_scores": {}, "patches": 0}
    else:
        result = find_placement_planes(record.depth, record.K, cfg, rng, photo)
    PlanesRecord(record.K, width, height, result["up"], record.metric,
                 [PlacementPlane(p["normal"], p["center"], p["area"], p["points"], p["pixels"])
                  for p in result["planes"]]).write(ctx.out)
    figure = draw_placement(photo, result["planes"], cfg.dot_radius_px)
    cv2.imwrite(str(ctx.out / "placement.png"), cv2.cvtColor(figure, cv2.COLOR_RGB2BGR))
    seconds = time.perf_counter() - started
    log.info("planes %s: %d planes (%d patches), up from %s, %.2f s", image_path.name,
             len(result["planes"]), result["patches"], result["up_source"], seconds)
    return {
        "planes": len(result["planes"]),
        "patches": result["patches"],
        "points": int(sum(len(p["points"]) for p in result["planes"])),
        "area": float(sum(p["area"] for p in result["planes"])),
        "up_source": result["up_source"],
        "up_scores": result["up_scores"],
        "seconds": seconds,
    }
