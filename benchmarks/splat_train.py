"""Benchmark: Gaussian budget vs held-out PSNR and training time of the splat_train stage.

A synthetic scene (random coloured Gaussians in a unit ball, rendered by the reference rasterizer from
an orbit of cameras, written as a COLMAP model) is trained once per budget with the stage's defaults
except `iterations` and `max_gaussians`. Prints one JSON object per budget and a summary list.

    OMP_NUM_THREADS=1 python -m benchmarks.splat_train --budgets 1000 3000 10000 --iterations 600

With `--sfm SFM_DIR` (an sfm stage output, e.g. a sample object's) the budgets are trained on that scene
instead, at the stage's own train_long_side unless --long-side is given; CPU minutes are reported too.
With `--masks DIR` (GT object masks named like the frames, e.g. the sample's objects/<name>/masks/) the
held-out error is also split into object and background pixels (where the PSNR is lost):

    OMP_NUM_THREADS=1 python -m benchmarks.splat_train --sfm outputs/cache/sfm/<key> --budgets 20000 \
        --iterations 2000 --masks outputs/cache/sample/<key>/objects/<name>/masks --seed <stage seed>
"""
from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from stages import splat_train
from stages.context import Context
from stages.gaussians.colmap import read_colmap_scene
from stages.gaussians.ply import read_ply
from stages.gaussians.rasterize import render
from stages.records.cameras import CamerasRecord
from tests.factories.splats import orbit_viewmats, random_blob_scene, write_synthetic_sfm


def object_background_psnr(out: Path, sfm: Path, masks: Path, long_side: int) -> dict:
    """PSNR of a trained scene (out/scene.ply) over the held-out views, pooled over GT-object pixels and
    over background pixels, plus the share of the squared error that lies on the object."""
    scene = read_colmap_scene(sfm / "sparse")
    held_out = set(CamerasRecord.read(out).held_out)
    gaussians = read_ply(out / "scene.ply")
    object_sse = background_sse = object_pixels = background_pixels = 0.0
    for frame in (f for f in scene.frames if f.name in held_out):
        view = splat_train.load_view(sfm / "images", frame, long_side, "cpu")
        mask_path = masks / f"{Path(frame.name).stem}.png"
        mask = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE)
        if mask is None:
            raise SystemExit(f"{mask_path}: GT mask of held-out frame {frame.name} is missing")
        mask = cv2.resize((mask > 127).astype(np.float32), (view.width, view.height), interpolation=cv2.INTER_AREA)
        on_object = torch.from_numpy(mask > 0.5)  # [H, W]
        with torch.no_grad():
            rgb = render(gaussians, view.viewmat, view.K, view.width, view.height).rgb.clamp(0, 1)
        error = ((rgb - view.image) ** 2).mean(-1)  # [H, W]
        object_sse += float(error[on_object].sum())
        background_sse += float(error[~on_object].sum())
        object_pixels += int(on_object.sum())
        background_pixels += int((~on_object).sum())
    return {"object_psnr": 10 * np.log10(object_pixels / max(object_sse, 1e-10)),
            "background_psnr": 10 * np.log10(background_pixels / max(background_sse, 1e-10)),
            "object_pixel_share": object_pixels / (object_pixels + background_pixels),
            "object_error_share": object_sse / max(object_sse + background_sse, 1e-10)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--budgets", type=int, nargs="+", default=[1000, 3000, 10000])
    parser.add_argument("--iterations", type=int, default=600)
    parser.add_argument("--truth-gaussians", type=int, default=3000)
    parser.add_argument("--views", type=int, default=24)
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--sfm-points", type=int, default=500)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--sfm", type=Path, default=None, help="train on this sfm output instead")
    parser.add_argument("--long-side", type=int, default=None, help="train_long_side (default: stage default)")
    parser.add_argument("--masks", type=Path, default=None, help="GT object masks of the --sfm frames")
    parser.add_argument("--seed", type=int, default=0, help="the stage's seed (e.g. from a cache manifest)")
    parser.add_argument("--out", type=Path, default=None, help="also write the results JSON here")
    args = parser.parse_args()
    if args.masks and not args.sfm:
        parser.error("--masks needs --sfm (the masks of that capture's frames)")
    torch.set_num_threads(args.threads)
    logging.basicConfig(level=logging.WARNING)

    results = []
    with tempfile.TemporaryDirectory() as tmp:
        sfm = args.sfm or Path(tmp) / "sfm"
        long_side = args.long_side or (None if args.sfm else max(args.width, args.height))
        if args.sfm is None:
            focal = 0.9 * args.width
            K = torch.tensor([[focal, 0, args.width / 2], [0, focal, args.height / 2], [0, 0, 1]])
            write_synthetic_sfm(sfm, random_blob_scene(args.truth_gaussians, seed=0),
                                orbit_viewmats(args.views, radius=3.2, height=1.2), K, args.width, args.height,
                                num_points=args.sfm_points, point_noise=0.03, seed=1)
        for budget in args.budgets:
            out = Path(tmp) / f"out_{budget}"
            out.mkdir()
            params = {"iterations": args.iterations, "max_gaussians": budget}
            if long_side:
                params["train_long_side"] = long_side
            ctx = Context(stage="splat_train", item=f"budget{budget}", out=out, inputs={"sfm": sfm}, seed=args.seed,
                          params=params)
            started, cpu_started = time.perf_counter(), time.process_time()
            metrics = splat_train.run(ctx)
            stats = json.loads((out / "train_stats.json").read_text())
            row = {"max_gaussians": budget, "num_gaussians": metrics["num_gaussians"],
                   "iterations_run": metrics["iterations_run"], "minutes": (time.perf_counter() - started) / 60,
                   "cpu_minutes": (time.process_time() - cpu_started) / 60,
                   "seconds_per_iteration": metrics["seconds_per_iteration"],
                   "held_out_psnr": metrics["final_psnr"], "best_psnr": metrics["best_psnr"],
                   "psnr_curve": stats["psnr_curve"]}
            if args.masks:
                row |= object_background_psnr(out, sfm, args.masks, max(stats["train_resolution"]))
            print(json.dumps(row), flush=True)
            results.append(row)
    setup = {name: str(value) if isinstance(value, Path) else value for name, value in vars(args).items()}
    summary = {"setup": setup, "results": results}
    if args.out:
        args.out.write_text(json.dumps(summary, indent=1))
    print(json.dumps([{k: r[k] for k in ("max_gaussians", "num_gaussians", "minutes", "cpu_minutes", "held_out_psnr")}
                      for r in results]))


if __name__ == "__main__":
    main()
