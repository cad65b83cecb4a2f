"""Benchmark of the compose stage (issue 7).

1. Speed: 640x480 images with 1-3 small objects (a synthetic 2.4k-Gaussian object) on a
   synthetic metric floor, variant full, one worker: images/s from stats.json.
2. Real: ../shared/real/splats/plant.splat composed onto ../shared/real/rgbd/TUM_color.png with its
   Kinect depth (bg_depth sidecar provider -> planes stage -> compose), writes a preview PNG and the
   same speed figure for a 113k-Gaussian real object.

Usage: OMP_NUM_THREADS=1 python -m benchmarks.compose [--images 40] [--out /tmp/compose_bench]
Prints one JSON object; the real preview is copied to benchmarks/results/compose/compose_tum_plant.jpg.
"""
from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import cv2
import torch

from benchmarks.lib.real_plant import real_plant_on_tum, run_stage
from stages.compose import run as compose
from tests.factories.backgrounds import write_floor_scene
from tests.factories.configs import REAL


def synthetic_speed(root: Path, images: int) -> dict:
    """compose at 640x480 with the test scene's small object, scaled up from its 160x120 camera."""
    shutil.rmtree(root, ignore_errors=True)
    inputs = write_floor_scene(root / "scene")
    params = {"objects": [{"name": "blob", "height_m": 0.4}], "num_images": images, "image_size": [640, 480]}
    return run_stage(compose, "compose", params, inputs, root / "out")


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
        preview = cv2.imread(str(args.out / "real" / "out" / "preview.png"))
        cv2.imwrite(str(Path(__file__).resolve().parent / "results" / "compose" / "compose_tum_plant.jpg"), preview,
                    [cv2.IMWRITE_JPEG_QUALITY, 85])
    result["total_seconds"] = round(time.perf_counter() - started, 1)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
