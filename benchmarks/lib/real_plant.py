"""The real plant (../shared/real/splats/plant.splat) composed onto the real TUM office photo with its Kinect depth,
and running one stage by hand: shared by the compose, compose-effects and export benchmarks."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from stages.bg_depth import run as bg_depth
from stages.compose import run as compose
from stages.contract.fan_in import fan_in
from stages.engine.context import Context
from stages.lib.gaussians.ply import read_splat, write_ply
from stages.planes import run as planes
from stages.records.extract import ExtractRecord
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


def real_plant_on_tum(root: Path, images: int) -> dict:
    """plant.splat onto the TUM office photo with its Kinect depth (bg_depth sidecar -> planes -> compose into
    root/out, its preview root/out/preview.png); each stage's metrics."""
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
    shutil.copy(root / "planes" / "placement.png", root / "placement.png")
    return {"bg_depth": depth_metrics, "planes": {k: plane_metrics[k] for k in ("planes", "area", "up_source")},
            "compose": stats}
