"""Benchmark of the compose stage (issue 7).

1. Speed: 640x480 images with 1-3 small objects (a synthetic 2.4k-Gaussian object) on a
   synthetic metric floor, variant full, one worker: images/s from stats.json.
2. Real: ../shared/real/splats/plant.splat composed onto ../shared/real/rgbd/TUM_color.png with its
   Kinect depth (bg_depth sidecar provider -> planes stage -> compose), writes a preview PNG and the
   same speed figure for a 113k-Gaussian real object.

Usage: OMP_NUM_THREADS=1 python -m benchmarks.compose [--images 40] [--out /tmp/compose_bench]
Prints one JSON object; the real preview is copied to benchmarks/results/compose_tum_plant.jpg.
"""
from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from stages.bg_depth import run as bg_depth
from stages.compose import run as compose
from stages.contract.fan_in import fan_in
from stages.engine.context import Context
from stages.lib.gaussians.ply import read_splat, write_ply
from stages.planes import run as planes
from stages.records.extract import ExtractRecord
from tests.factories.backgrounds import write_floor_scene
from tests.factories.configs import REAL

TUM_K = [[525.0, 0.0, 320.0], [0.0, 525.0, 240.0], [0.0, 0.0, 1.0]]  # TUM RGB-D default intrinsics
PLANT_HEIGHT_M = 0.45


def plant_extract(folder: Path) -> Path:
    """An extract folder for plant.splat: up axis -y (README), base and height from percentiles."""
    g = read_splat(REAL / "splats" / "plant.splat")
    up = np.array([0.0, -1.0, 0.0])
    heights = g.means.numpy().astype(np.float64) @ up
    low, high = np.percentile(heights, [0.5, 99.5])
    centre = np.median(g.means.numpy().astype(np.float64), axis=0)
    base = centre + (low - centre @ up) * up
    folder.mkdir(parents=True, exist_ok=True)
    write_ply(folder / "object.ply", g)
    ExtractRecord(up, base, float(high - low)).write(folder)
    return folder


def run_stage(module, name: str, params: dict, inputs: dict, out: Path, seed: int = 0) -> dict:
    """Run a stage's run() into a fresh folder."""
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    return module.run(Context(stage=name, item="bench", params=params, inputs=inputs, out=out, seed=seed))


def synthetic_speed(root: Path, images: int) -> dict:
    """compose at 640x480 with the test scene's small object, scaled up from its 160x120 camera."""
    shutil.rmtree(root, ignore_errors=True)
    inputs = write_floor_scene(root / "scene")
    params = {"objects": [{"name": "blob", "height_m": 0.4}], "num_images": images, "image_size": [640, 480]}
    return run_stage(compose, "compose", params, inputs, root / "out")


def real_plant_on_tum(root: Path, images: int) -> dict:
    """plant.splat onto the TUM office photo with its Kinect depth."""
    shutil.rmtree(root, ignore_errors=True)
    photo = REAL / "rgbd" / "TUM_color.png"
    depth_metrics = run_stage(bg_depth, "bg_depth", {"provider": "sidecar", "sidecar_format": "tum", "K": TUM_K},
                              {"image": photo, "depth": REAL / "rgbd" / "TUM_depth.png"}, root / "depth")
    plane_metrics = run_stage(planes, "planes", {}, {"image": photo, "depth": root / "depth"}, root / "planes")
    inputs = {**fan_in({"plant": {"object": plant_extract(root / "extract")}}, compose.INPUTS.object_kinds),
              **fan_in({"tum": {"background": photo, "planes": root / "planes", "depth": root / "depth"}},
                       compose.INPUTS.photo_kinds)}
    params = {"objects": [{"name": "plant", "height_m": PLANT_HEIGHT_M}], "num_images": images,
              "random_placement_share": 0.0, "preview_count": 9}
    stats = run_stage(compose, "compose", params, inputs, root / "out", seed=1)
    preview = cv2.imread(str(root / "out" / "preview.png"))
    cv2.imwrite(str(Path(__file__).resolve().parent / "results" / "compose_tum_plant.jpg"), preview, [cv2.IMWRITE_JPEG_QUALITY, 85])
    shutil.copy(root / "planes" / "placement.png", root / "placement.png")
    return {"bg_depth": depth_metrics, "planes": {k: plane_metrics[k] for k in ("planes", "area", "up_source")},
            "compose": stats}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=40)
    parser.add_argument("--out", type=Path, default=Path("/tmp/compose_bench"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    started = time.perf_counter()
    result = {"synthetic_640x480": synthetic_speed(args.out / "synthetic", args.images)}
    if (REAL / "splats" / "plant.splat").is_file():
        result["real_plant_on_tum"] = real_plant_on_tum(args.out / "real", args.images)
    result["total_seconds"] = round(time.perf_counter() - started, 1)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
