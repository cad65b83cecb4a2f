"""Benchmark: Gaussian budget vs held-out PSNR and training time of the splat_train stage.

A synthetic scene (random coloured Gaussians in a unit ball, rendered by the reference rasterizer from
an orbit of cameras, written as a COLMAP model) is trained once per budget and seed (--seed, one or more) with the
stage's defaults except `iterations`, `max_gaussians` and the settings of `--set KEY=VALUE` (repeatable). Prints one
JSON object per run and a summary list.

    OMP_NUM_THREADS=1 python -m benchmarks.splat_train --budgets 1000 3000 10000 --iterations 600

With `--sfm SFM_DIR` (an sfm stage output, e.g. a sample object's) the budgets are trained on that scene
instead, at the stage's own train_long_side unless --long-side is given; CPU minutes are reported too.
With `--masks DIR` (GT object masks named like the frames, e.g. the sample's objects/<name>/masks/) the
held-out error is also split into object and background pixels (where the PSNR is lost):

    OMP_NUM_THREADS=1 python -m benchmarks.splat_train --sfm outputs/cache/sfm/<key> --budgets 20000 \
        --iterations 2000 --masks outputs/cache/sample/<key>/objects/<name>/masks --seed <stage seed>

A setting against the defaults over seeds, on the plush dog (issue 59's lever, benchmarks/results/opensplat.md):

    python -m benchmarks.splat_train --sfm <the dog's sfm> --budgets 30000 --iterations 2000 --seed 0 1 2 \
        --set prune_opacity=0.05

With `--gpu` (on a CUDA GPU with gsplat, `pip install -e ".[gpu,dev]"`; "no CUDA device: skipped" elsewhere)
it measures the stage on the real plush dog (../shared/real; its frames and sfm through the engine and the
cache of --cache, or the sfm folder of --sfm), each run in a fresh folder with the engine's seed:
today's budget with the PyTorch path on the GPU and with gsplat (wall seconds, their ratio, held-out PSNR),
then the GPU budget (`splat_train.cuda`) with gsplat at each of --gpu-iterations (densification stopping at
the same share of the run): wall seconds, the held-out PSNR against seconds from the start of training
(the curve the budget is chosen from), and the held-out PSNR at its own resolution and at today's 256 px,
on the same held-out views as today's; for the budget's own iteration count, the cut-out's IoU against the
hand-drawn boxes (extract, benchmarks/lib/cutout_boxes.py; needs the frames, so not with --sfm). Targets
(H100): today's budget <= 20 s wall with gsplat; the GPU budget <= 180 s and >= 2 dB above today's
held-out PSNR at 256 px, cut-out IoU >= 0.9 on every boxed photo.

    python -m benchmarks.splat_train --gpu --out benchmarks/results/splat_train_gpu.json
"""
from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from dataclasses import asdict
from importlib.metadata import version
from pathlib import Path

import cv2
import numpy as np
import torch
from omegaconf import OmegaConf

from benchmarks.lib.cutout_boxes import load_boxes, score_cutout
from benchmarks.lib.gpu_checks import gsplat_gpu_ready
from benchmarks.lib.settings import add_set_option, changed_settings
from benchmarks.lib.splat_runs import run_held_out_psnr, train_timed
from stages.engine.context import Context
from stages.extract import run as extract
from stages.lib.gaussians.model import Gaussians
from stages.lib.gaussians.ply import read_ply
from stages.lib.gaussians.rasterize import render
from stages.records.cameras import CamerasRecord
from stages.records.sfm import SfmRecord
from stages.splat_train import run as splat_train
from stages.splat_train.spec import CUDA_BUDGET, for_device
from tests.factories.configs import REAL
from tests.factories.runs import DOG, real_config, real_seed, run_real_chain
from tests.factories.splats import orbit_viewmats, random_blob_scene, write_synthetic_sfm

GPU_TARGETS = {"today_gsplat_wall_s": 20.0, "gpu_budget_wall_s": 180.0, "gain_db_at_today_resolution": 2.0,
               "min_cutout_iou": 0.9}  # on an H100 (issue 35)


def object_background_psnr(out: Path, sfm: Path, masks: Path, long_side: int) -> dict:
    """PSNR of a trained scene (out/scene.ply) over the held-out views, pooled over GT-object pixels and
    over background pixels, plus the share of the squared error that lies on the object."""
    record = SfmRecord.read(sfm)
    held_out = set(CamerasRecord.read(out).held_out)
    gaussians = read_ply(out / "scene.ply")
    object_sse = background_sse = object_pixels = background_pixels = 0.0
    for frame in (f for f in record.scene().frames if f.name in held_out):
        view = splat_train.load_view(record.images_dir, frame, long_side, "cpu")
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


def cutout_ious(frames: Path, sfm: Path, splat: Path, out: Path) -> list[float]:
    """IoU of the object extract cuts out of a splat_train folder with the default settings (the engine's
    seed), against each hand-drawn box of the dog."""
    cfg = real_config("extract")
    out.mkdir(parents=True)
    extract.run(Context(stage="extract", item=DOG, params=OmegaConf.to_container(cfg.extract, resolve=True),
                        inputs={"splat": splat}, out=out, seed=real_seed("extract")))
    scores = score_cutout(load_boxes(REAL / DOG / "boxes.json"), frames, sfm, splat, out / "object.ply")
    return [round(score.iou, 3) for score in scores]


def warm_up_gsplat() -> float:
    """Seconds of a first tiny gsplat render and backward: gsplat's CUDA build at its first use on a machine
    (1-2 minutes), else loading the built code."""
    started = time.perf_counter()
    g = random_blob_scene(50, seed=0).to("cuda")
    g = Gaussians(g.means.requires_grad_(), g.log_scales, g.quats, g.opacity_logits, g.sh)
    K = torch.tensor([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]], device="cuda")
    viewmat = orbit_viewmats(1, radius=3.2, height=1.2)[0].cuda()
    render(g, viewmat, K, 32, 32, backend="gsplat").rgb.sum().backward()
    torch.cuda.synchronize()
    return round(time.perf_counter() - started, 1)


def gpu_main(args: argparse.Namespace, changes: dict) -> None:
    """The --gpu measurements (module docstring); `changes`: the settings --set changes in the GPU budget."""
    if not gsplat_gpu_ready():
        return
    first_call_s = warm_up_gsplat()
    frames, sfm = None, args.sfm
    if sfm is None:
        if not REAL.is_dir():
            raise SystemExit(f"{REAL} not present: give --sfm, or put the real captures beside the repository")
        engine, graph, _ = run_real_chain(args.cache, "sfm")
        frames, sfm = (engine.output_dir(graph.nodes[stage][0]) for stage in ("frames", "sfm"))
    seed = real_seed("splat_train")
    defaults = asdict(splat_train.SplatTrainConfig())
    today = for_device(defaults, "cpu")
    budget = {**for_device(defaults, "cuda"), **changes}
    today_side = today["train_long_side"]
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, backend in (("today_torch_cuda", "cuda"), ("today_gsplat", "gsplat")):
            if name == "today_torch_cuda" and args.skip_torch:
                continue
            rows[name] = train_timed(sfm, Path(tmp) / name, {**today, "backend": backend}, seed, "cuda")
            rows[name]["held_out_psnr_at_today_resolution"] = run_held_out_psnr(Path(tmp) / name, sfm, today_side,
                                                                                "cuda")
            print(json.dumps({name: {k: v for k, v in rows[name].items() if k != "curve"}}), flush=True)
        reference = rows.get("today_torch_cuda", rows["today_gsplat"])["held_out_psnr_at_today_resolution"]
        for iterations in args.gpu_iterations:
            name = f"gpu_budget_{iterations}"
            share = budget["densify_until"] / budget["iterations"]
            params = {**budget, "backend": "gsplat", "iterations": iterations,
                      "densify_until": round(share * iterations)}
            row = rows[name] = train_timed(sfm, Path(tmp) / name, params, seed, "cuda")
            row["held_out_psnr_at_today_resolution"] = run_held_out_psnr(Path(tmp) / name, sfm, today_side, "cuda")
            row["gain_db_at_today_resolution"] = round(row["held_out_psnr_at_today_resolution"] - reference, 3)
            if frames is not None and iterations == budget["iterations"]:
                row["cutout_ious"] = cutout_ious(frames, sfm, Path(tmp) / name, Path(tmp) / f"{name}_extract")
            print(json.dumps({name: {k: v for k, v in row.items() if k != "curve"}}), flush=True)
    own = rows[f"gpu_budget_{budget['iterations']}"] if budget["iterations"] in args.gpu_iterations else None
    checks = {"today_gsplat_wall_s": rows["today_gsplat"]["wall_s"] <= GPU_TARGETS["today_gsplat_wall_s"]}
    if own is not None:
        checks |= {"gpu_budget_wall_s": own["wall_s"] <= GPU_TARGETS["gpu_budget_wall_s"],
                   "gain_db_at_today_resolution": own["gain_db_at_today_resolution"]
                   >= GPU_TARGETS["gain_db_at_today_resolution"]}
        if "cutout_ious" in own:
            checks["min_cutout_iou"] = min(own["cutout_ious"]) >= GPU_TARGETS["min_cutout_iou"]
    if "today_torch_cuda" in rows:
        rows["today_gsplat"]["speedup_vs_torch_cuda"] = round(rows["today_torch_cuda"]["wall_s"]
                                                              / rows["today_gsplat"]["wall_s"], 1)
    result = {"device": torch.cuda.get_device_name(), "torch": torch.__version__, "gsplat": version("gsplat"),
              "gsplat_first_call_s": first_call_s, "sfm": str(sfm), "seed": seed, "gpu_budget": budget,
              "targets": GPU_TARGETS, "met": checks, "runs": rows}
    if args.out:
        args.out.write_text(json.dumps(result, indent=1))
    print(json.dumps({"met": checks, **{name: {k: row[k] for k in ("wall_s", "num_gaussians", "held_out_psnr",
                                                                   "held_out_psnr_at_today_resolution")}
                                        for name, row in rows.items()}}, indent=1))


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
    parser.add_argument("--seed", type=int, nargs="+", default=[0],
                        help="the stage's seeds (e.g. from a cache manifest): each budget trained at each")
    parser.add_argument("--out", type=Path, default=None, help="also write the results JSON here")
    parser.add_argument("--gpu", action="store_true", help="the CUDA measurements on the real plush dog")
    parser.add_argument("--cache", type=Path, default=Path("/tmp/real16/cache"), help="--gpu: the engine's cache")
    parser.add_argument("--gpu-iterations", type=int, nargs="+", default=[
        CUDA_BUDGET["iterations"] // 2, CUDA_BUDGET["iterations"],
        CUDA_BUDGET["iterations"] * 3 // 2], help="--gpu: iteration counts of the GPU budget to train")
    add_set_option(parser, "the stage's settings (with --gpu: the GPU budget's), e.g. --set max_gaussians=300000")
    parser.add_argument("--skip-torch", action="store_true", help="--gpu: skip today's budget on the PyTorch path")
    args = parser.parse_args()
    changes = changed_settings(args.set, asdict(splat_train.SplatTrainConfig()))
    if args.gpu:
        logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
        gpu_main(args, changes)
        return
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
        for seed in args.seed:
            for budget in args.budgets:
                out = Path(tmp) / f"out_{budget}_{seed}"
                out.mkdir()
                params = {"iterations": args.iterations, "max_gaussians": budget, **changes}
                if long_side:
                    params["train_long_side"] = long_side
                ctx = Context(stage="splat_train", item=f"budget{budget}", out=out, inputs={"sfm": sfm}, seed=seed,
                              params=params)
                started, cpu_started = time.perf_counter(), time.process_time()
                metrics = splat_train.run(ctx)
                stats = json.loads((out / "train_stats.json").read_text())
                row = {"max_gaussians": budget, "seed": seed, "num_gaussians": metrics["num_gaussians"],
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
    print(json.dumps([{k: r[k] for k in ("max_gaussians", "seed", "num_gaussians", "minutes", "cpu_minutes",
                                         "held_out_psnr")} for r in results]))


if __name__ == "__main__":
    main()
