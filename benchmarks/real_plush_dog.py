"""Real capture end to end: plush dog photos -> frames -> sfm -> splat_train -> extract, plus figures.

Usage (single-threaded, the machine is shared):

    OMP_NUM_THREADS=1 python -m benchmarks.real_plush_dog --work /tmp/plush \
        --figures benchmarks/results/real_plush_dog

Each stage runs through its `run(ctx)` with the stage defaults (frames: num_frames=100 keeps all 84
photos; sfm: num_threads=1). A stage whose output folder already holds its metrics.json is not rerun.
Writes <work>/<stage>/ folders, <work>/summary.json, and under --figures: filtering.png (extract's panel,
downscaled) and object_heldout.png (the photo and the extracted object rendered at one held-out camera on white
and on green).
"""
from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from stages import extract, frames, sfm, splat_train
from stages.context import Context
from stages.gaussians.ply import read_ply
from stages.gaussians.rasterize import render
from stages.records.cameras import CamerasRecord

REAL = Path(__file__).resolve().parents[2] / "shared" / "real" / "plush_dog" / "images"
log = logging.getLogger("real_plush_dog")


def run_stage(module, name: str, params: dict, inputs: dict[str, Path], work: Path) -> dict:
    """Run one stage into work/<name> (skipped when work/<name>/metrics.json exists); return its metrics."""
    out = work / name
    metrics_path = out / "metrics.json"
    if metrics_path.exists():
        return json.loads(metrics_path.read_text())
    out.mkdir(parents=True, exist_ok=True)
    device = "cuda" if torch.cuda.is_available() else "cpu"
    ctx = Context(stage=name, item="plush_dog", params=params, inputs=inputs, out=out, seed=1, device=device)
    start = time.perf_counter()
    metrics = module.run(ctx)
    metrics["wall_s"] = time.perf_counter() - start
    metrics_path.write_text(json.dumps(metrics, indent=2))
    log.info("%s: %s", name, metrics)
    return metrics


def save_small_png(path: Path, bgr: np.ndarray, max_side: int) -> None:
    """Write `bgr` [H, W, 3] uint8 as PNG with its long side at most `max_side`."""
    factor = min(1.0, max_side / max(bgr.shape[:2]))
    if factor < 1.0:
        bgr = cv2.resize(bgr, None, fx=factor, fy=factor, interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(path), bgr, [cv2.IMWRITE_PNG_COMPRESSION, 9])


def render_held_out(splat_dir: Path, object_ply: Path, photos: Path) -> np.ndarray:
    """Photo | object on white | object on green at the middle held-out camera: BGR uint8 [H, 3W, 3]."""
    cameras = CamerasRecord.read(splat_dir)
    name = cameras.held_out[len(cameras.held_out) // 2]
    frame = next(f for f in cameras.frames if f.file == name)
    gaussians = read_ply(object_ply)
    panels = [cv2.resize(cv2.imread(str(photos / name), cv2.IMREAD_COLOR), (frame.width, frame.height),
                         interpolation=cv2.INTER_AREA)]
    for background in ([1.0, 1.0, 1.0], [0.0, 0.6, 0.0]):  # green shows what white hides (backdrop remnants)
        with torch.no_grad():
            output = render(gaussians, torch.tensor(frame.viewmat, dtype=torch.float32),
                            torch.tensor(frame.K, dtype=torch.float32), frame.width, frame.height,
                            background=torch.tensor(background))
        rgb = (output.rgb.clamp(0, 1).numpy() * 255).round().astype(np.uint8)  # [H, W, 3]
        panels.append(rgb[:, :, ::-1])
    log.info("held-out render at %s (%dx%d)", name, frame.width, frame.height)
    return np.concatenate(panels, axis=1)


def main() -> None:
    """Run the chain and write the summary and figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=Path, default=REAL)
    parser.add_argument("--work", type=Path, default=Path("/tmp/plush"))
    parser.add_argument("--figures", type=Path, default=Path("benchmarks/results/real_plush_dog"))
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    torch.set_num_threads(1)
    work = args.work
    summary = {
        "frames": run_stage(frames, "frames", {"num_frames": 100}, {"video": args.images}, work),
        "sfm": run_stage(sfm, "sfm", {"num_threads": 1}, {"frames": work / "frames"}, work),
        "splat_train": run_stage(splat_train, "splat_train", {}, {"sfm": work / "sfm"}, work),
        "extract": run_stage(extract, "extract", {}, {"splat": work / "splat_train"}, work),
    }
    (work / "summary.json").write_text(json.dumps(summary, indent=2))
    args.figures.mkdir(parents=True, exist_ok=True)
    save_small_png(args.figures / "filtering.png", cv2.imread(str(work / "extract" / "filtering.png")), 1200)
    save_small_png(args.figures / "object_heldout.png",
                   render_held_out(work / "splat_train", work / "extract" / "object.ply", work / "sfm" / "images"),
                   1200)
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main()
