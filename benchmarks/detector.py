"""Detector benchmark: cost of each training lever, and box mAP against training minutes.

  python -m benchmarks.detector steps --dataset D [--threads 1] [--steps 6] [--lever NAME ...]
      seconds per training image of each lever in STEP_LEVERS (or only the named ones), each on its own
      against the same reference in the same run (the previous default: 320 px whole images, RoIAlign
      sampling 2, contiguous memory, explicitly padded convolutions), as a ratio to that reference.
  python -m benchmarks.detector loaders --dataset D --model M [--threads 2] [--steps 60] [--repeats 2]
      training seconds per iteration with the batches built in the training process (loader_workers 0)
      and in one loader process (1), alternating, each run --steps iterations continuing from the
      trained detector M (model.pt): the step costs of late training.
  python -m benchmarks.detector runs --dataset D --testset T [--testset T2] --config NAME='{"epochs": 2}' ...
      trains one detector per named configuration (overrides of the train_maskrcnn defaults) on the
      COCO dataset D, evaluates it on every test set, and appends a row (training minutes, box / mask
      AP) to --out (JSON); configurations already there are skipped. --seed repeats with another seed.
      With --device cuda they train and evaluate on the GPU, over the stage's CUDA budget (`train_maskrcnn.cuda`).
  python -m benchmarks.detector chart --runs runs.json [--runs more.json ...] --png chart.png
      box mAP against CPU core-minutes of training (threads x wall minutes: runs with 1 thread side by
      side and runs with 2 threads on 2 cores compare), one panel per test set, Pareto front marked;
      and the table of every run of the given JSONs.
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import os
import statistics
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

import torch
import torch.nn.functional as F

from stages.app.report import pareto_front
from stages.engine.context import Context
from stages.eval.run import run as run_eval
from stages.lib.coco import format_ap
from stages.lib.detection import efficientnet_lite
from stages.lib.detection.data import CocoInstances
from stages.lib.detection.model import build_maskrcnn, load_detector, to_device
from stages.lib.detection.model_config import model_config_of
from stages.lib.masks.dice import add_mask_dice
from stages.train_maskrcnn.run import BatchSource, run as run_train, train_detector
from stages.train_maskrcnn.spec import WIDE_HEADS, TrainMaskrcnnConfig, for_device

# The training settings before the convergence work (issue 15), as overrides of today's defaults.
PREVIOUS_DEFAULT = {"image_size": 320, "train_crop": 0, "roi_sampling_ratio": 2, "batch_size": 2, "closeup_share": 0.0,
                    "mask_dice_weight": 0.0, **WIDE_HEADS}
# Today's defaults as levers on PREVIOUS_DEFAULT (the code paths are always on in the stage).
NEW_DEFAULT = {"_native_padding": True, "_channels_last": True, "_fold_frozen_norm": True,
               **{k: v for k, v in TrainMaskrcnnConfig().__dict__.items() if k in PREVIOUS_DEFAULT}}
# Each lever on its own, applied to PREVIOUS_DEFAULT (keys starting with "_" are code paths, not settings).
STEP_LEVERS = {
    "reference": {},
    "native padding for stride-1 convolutions": {"_native_padding": True},
    "channels-last": {"_channels_last": True},
    "frozen BatchNorm folded into the convolutions": {"_fold_frozen_norm": True},
    "bf16 autocast": {"bf16": True},
    "RoIAlign sampling 1": {"roi_sampling_ratio": 1},
    "128 -> 64 RoIs, 300 -> 150 proposals": {"box_batch_size_per_image": 64, "rpn_post_nms_train": 150,
                                             "rpn_pre_nms_train": 300},
    "FPN 128 -> 64 channels": {"fpn_channels": 64},
    "mask head 128 -> 64 channels": {"mask_head_channels": 64},
    "backbone: 3 -> 1 trainable groups": {"trainable_layers": 1},
    "backbone frozen": {"trainable_layers": 0},
    "batch 4": {"batch_size": 4},
    "batch 8": {"batch_size": 8},
    "512 px whole images": {"image_size": 512},
    "512 px, 320 px crops": {"image_size": 512, "train_crop": 320},
    "512 px, 256 px crops": {"image_size": 512, "train_crop": 256},
    "640 px, 320 px crops": {"image_size": 640, "train_crop": 320},
    "all kept levers (the new default)": NEW_DEFAULT,
    "new default without the mask loss's Dice term": {**NEW_DEFAULT, "mask_dice_weight": 0.0},
    "new default + bf16 autocast": {**NEW_DEFAULT, "bf16": True},
    "new default + torch.compile of the backbone": {**NEW_DEFAULT, "_compile_backbone": True},
}


def padded_convolve(self, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None = None) -> torch.Tensor:
    """The reference Conv2dSame.convolve: an explicit "SAME" padding copy before every convolution.

    x [B, C, H, W], weight [O, C / groups, k, k], bias [O] or None.
    """
    pads = []
    for size in (x.shape[-1], x.shape[-2]):
        total = max((math.ceil(size / self.stride[0]) - 1) * self.stride[0] + self.kernel_size[0] - size, 0)
        pads += [total // 2, total - total // 2]
    return F.conv2d(F.pad(x, pads), weight, bias, self.stride, 0, 1, self.groups)


def separate_conv_norm(conv, norm, x: torch.Tensor) -> torch.Tensor:
    """The reference: the convolution, then the (frozen) BatchNorm as its own pass. x [B, C, H, W]."""
    return norm(conv(x))


def seconds_per_image(dataset: Path, lever: dict, steps: int) -> dict:
    """Median training seconds per image (model step) and loading seconds per image of one lever."""
    settings = {k: v for k, v in lever.items() if not k.startswith("_")}
    cfg = TrainMaskrcnnConfig(**{**PREVIOUS_DEFAULT, **settings})
    native_convolve, folded_norm = efficientnet_lite.Conv2dSame.convolve, efficientnet_lite.conv_norm
    if not lever.get("_native_padding"):
        efficientnet_lite.Conv2dSame.convolve = padded_convolve
    if not lever.get("_fold_frozen_norm"):
        efficientnet_lite.conv_norm = separate_conv_norm
    try:
        data = CocoInstances(dataset, cfg.image_size)
        torch.manual_seed(0)
        model = add_mask_dice(build_maskrcnn(model_config_of(cfg), len(data.category_names)), cfg.mask_dice_weight)
        model = to_device(model, "cpu") if lever.get("_channels_last") else model
        if lever.get("_compile_backbone"):  # inductor; the warm-up step below pays for the compilation
            model.backbone = torch.compile(model.backbone)
        model.train()
        optimizer = torch.optim.SGD([p for p in model.parameters() if p.requires_grad], lr=0.002, momentum=0.9)
        source = BatchSource(data, cfg, seed=0)
        load, train = [], []
        for step in range(steps + 1):  # the first step warms up and is not counted
            started = time.perf_counter()
            batch = source[step]
            loaded = time.perf_counter()
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=cfg.bf16):
                loss = sum(model([b[0] for b in batch], [b[1] for b in batch]).values())
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            if step:
                load.append((loaded - started) / cfg.batch_size)
                train.append((time.perf_counter() - loaded) / cfg.batch_size)
    finally:
        efficientnet_lite.Conv2dSame.convolve, efficientnet_lite.conv_norm = native_convolve, folded_norm
    return {"train_s_per_image": statistics.median(train), "load_s_per_image": statistics.median(load)}


def loader_costs(dataset: Path, model_path: Path, threads: int, iterations: int, repeats: int) -> dict:
    """Training seconds per iteration (loading included) with `loader_workers` 0 and 1, alternating.

    Each run trains `iterations` default-config iterations on `dataset`, continuing from the trained
    detector `model_path` at a low learning rate: a trained model's heads get the RoI counts of late
    training, which a fresh model's first steps do not have.
    """
    torch.set_num_threads(threads)
    data = CocoInstances(dataset, TrainMaskrcnnConfig().image_size)
    rows = []
    for repeat in range(repeats):
        for workers in (0, 1):
            model, _, categories = load_detector(model_path)
            if categories != data.category_names:
                raise SystemExit(f"{model_path} detects {categories}, {dataset} holds {data.category_names}")
            cfg = TrainMaskrcnnConfig(loader_workers=workers, lr=0.002, warmup_iterations=0, checkpoint_every=0)
            cfg.epochs = iterations * cfg.batch_size / len(data)
            record = train_detector(model, data, cfg, seed=repeat)
            rows.append({"loader_workers": workers, "repeat": repeat, "iterations": record["iterations"],
                         "seconds_per_iteration": record["seconds_per_iteration"]})
            logging.info("%s", rows[-1])
    medians = {workers: statistics.median(r["seconds_per_iteration"] for r in rows if r["loader_workers"] == workers)
               for workers in (0, 1)}
    return {"dataset": str(dataset), "model": str(model_path), "threads": threads, "load_1min": os.getloadavg()[0],
            "runs": rows, "median_seconds_per_iteration": medians, "workers_1_over_0": medians[1] / medians[0]}


def step_costs(dataset: Path, steps: int, threads: int, names: list[str] | None = None) -> dict:
    """Seconds per training image of the STEP_LEVERS entries `names` (default: all), and each one's ratio to
    the reference (always measured, first)."""
    unknown = sorted(set(names or []) - set(STEP_LEVERS))
    if unknown:
        raise SystemExit(f"unknown levers {unknown}; known: {list(STEP_LEVERS)}")
    torch.set_num_threads(threads)
    rows = {}
    for name, lever in STEP_LEVERS.items():
        if names and name not in names and name != "reference":
            continue
        rows[name] = {"settings": lever, **seconds_per_image(dataset, lever, steps)}
        rows[name]["ratio_to_reference"] = rows[name]["train_s_per_image"] / rows["reference"]["train_s_per_image"]
        logging.info("%s: %s", name, rows[name])
    return {"dataset": str(dataset), "threads": threads, "steps": steps, "load_1min": os.getloadavg()[0],
            "levers": rows}


def train_and_evaluate(dataset: Path, testsets: list[Path], name: str, overrides: dict, seed: int, threads: int,
                       work: Path, device: str = "cpu") -> dict:
    """Train one configuration and evaluate it on every test set: one result row. On "cuda" the overrides apply
    over the stage's CUDA budget (`train_maskrcnn.cuda`), as a run on a GPU gives them."""
    out = work / f"{name}_s{seed}" / "train"
    out.mkdir(parents=True, exist_ok=True)
    params = {**for_device(asdict(TrainMaskrcnnConfig()), device), **overrides, "threads": threads,
              "checkpoint_every": 0}
    load_before = os.getloadavg()[0]
    train = run_train(Context("train_maskrcnn", name, params, {"dataset": dataset}, out, seed=seed, device=device))
    cfg = TrainMaskrcnnConfig(**params)
    row = {"name": name, "overrides": overrides, "seed": seed, "train_minutes": train["seconds"] / 60,
           "iterations": train["iterations"], "images_seen": train["iterations"] * cfg.batch_size,
           "image_size": cfg.image_size, "train_crop": cfg.train_crop, "final_loss": train["final_loss"],
           "load_1min": [load_before, os.getloadavg()[0]]}
    for testset in testsets:
        eval_out = out.parent / f"eval_{testset.name}"
        eval_out.mkdir(parents=True, exist_ok=True)
        metrics = run_eval(Context("eval", name, {"threads": threads}, {"model": out, "testset": testset}, eval_out,
                                   device=device))
        row[testset.name] = {"box_AP": metrics["bbox"]["AP"], "box_AP50": metrics["bbox"]["AP50"],
                             "mask_AP": metrics["segm"]["AP"], "per_class": metrics["bbox"]["per_class"],
                             "mask_per_class": metrics["segm"]["per_class"],
                             "inference_s": metrics["inference_seconds_per_image"]}
    logging.info("%s", row)
    return row


def runs(dataset: Path, testsets: list[Path], configs: dict[str, dict], seed: int, threads: int, work: Path,
         out: Path, device: str = "cpu") -> dict:
    """Train and evaluate every named configuration; rows already in `out` (same name and seed) are kept.

    `out` is rewritten after every finished run, so an interrupted benchmark keeps what it measured.
    """
    result = {"dataset": str(dataset), "testsets": [str(t) for t in testsets], "threads": threads, "device": device,
              "runs": []}
    if out.exists():
        recorded = json.loads(out.read_text())
        was = (recorded["dataset"], recorded["threads"], recorded.get("device", "cpu"))
        if was != (str(dataset), threads, device):
            raise SystemExit(f"{out} holds runs on {was[0]} with {was[1]} threads on the {was[2]}, not {dataset} "
                             f"with {threads} on the {device}: pass another --out")
        result["runs"] = recorded["runs"]
    done = {(row["name"], row["seed"]) for row in result["runs"]}
    for name, overrides in configs.items():
        if (name, seed) in done:
            logging.info("%s seed %d: already in %s, skipped", name, seed, out)
            continue
        result["runs"].append(train_and_evaluate(dataset, testsets, name, overrides, seed, threads, work, device))
        write_result(out, result)
    return result


def merge_runs(paths: list[Path]) -> dict:
    """The runs of several `runs` JSONs (same test sets) as one result; each row gains its dataset, its
    thread count and core_minutes = threads x training minutes."""
    merged: dict = {"testsets": None, "runs": []}
    for path in paths:
        result = json.loads(path.read_text())
        names = [Path(t).name for t in result["testsets"]]
        if merged["testsets"] not in (None, names):
            raise SystemExit(f"{path}: test sets {names}, not {merged['testsets']} as in the other files")
        merged["testsets"] = names
        annotations = Path(result["dataset"]) / "annotations.json"  # absent when the dataset was not kept
        images = len(json.loads(annotations.read_text())["images"]) if annotations.is_file() else None
        merged["runs"] += [{**row, "threads": result["threads"], "dataset_images": images,
                            "core_minutes": row["train_minutes"] * result["threads"]} for row in result["runs"]]
    merged["runs"].sort(key=lambda r: r["core_minutes"])
    return merged


def draw_chart(result: dict, png: Path) -> None:
    """Box mAP against CPU core-minutes of training, one panel per test set; points numbered as in the
    table, the Pareto front as a step line."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result["runs"]
    figure, axes = plt.subplots(1, len(result["testsets"]), figsize=(5.5 * len(result["testsets"]), 4.2), sharey=True,
                                squeeze=False)
    for axis, testset in zip(axes[0], result["testsets"]):
        points = [(row["core_minutes"], row[testset]["box_AP"]) for row in rows]
        front = pareto_front(points)
        for number, (x, y) in enumerate(points, start=1):
            axis.scatter(x, y, color="tab:red" if number - 1 in front else "tab:gray", zorder=3, s=18)
            axis.annotate(str(number), (x, y), textcoords="offset points", xytext=(3, 3), fontsize=8)
        line = [points[i] for i in front]
        axis.step([p[0] for p in line], [p[1] for p in line], "r--", where="post", lw=1, label="Pareto front")
        axis.set_title(testset)
        axis.set_xlabel("CPU core-minutes of training (threads x minutes)")
        axis.grid(alpha=0.3)
    axes[0][0].set_ylabel("box mAP (COCO AP, %)")
    axes[0][-1].legend(fontsize=8, loc="lower right")
    figure.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(png, dpi=120)
    plt.close(figure)


def runs_table(result: dict) -> str:
    """Markdown table of the runs, numbered as in the chart (sorted by core-minutes)."""
    header = ["#", "configuration", "seed", "dataset images", "windows / images seen", "threads", "train minutes",
              "core-minutes"] + [f"{t}: box AP / AP50 / mask AP" for t in result["testsets"]]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for number, row in enumerate(result["runs"], start=1):
        cells = [str(number), row["name"], str(row["seed"]), str(row.get("dataset_images") or "?"),
                 str(row["images_seen"]), str(row["threads"]), f"{row['train_minutes']:.1f}", f"{row['core_minutes']:.1f}"]
        cells += [f"{row[t]['box_AP']:.1f} / {row[t]['box_AP50']:.1f} / {format_ap(row[t]['mask_AP'])}"
                  for t in result["testsets"]]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def steps_table(result: dict) -> str:
    """Markdown table of the step costs."""
    lines = ["| lever | train s / image | load s / image | x reference |", "|---|---|---|---|"]
    for name, row in result["levers"].items():
        lines.append(f"| {name} | {row['train_s_per_image']:.3f} | {row['load_s_per_image']:.3f} | "
                     f"{row['ratio_to_reference']:.2f} |")
    return "\n".join(lines)


def write_result(path: Path, result: dict) -> None:
    """A benchmark result as indented JSON at `path` (its folder made if missing)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=1))


def parse_configs(items: list[str]) -> dict[str, dict]:
    """NAME=JSON pairs from the command line."""
    configs = {}
    for item in items:
        name, _, text = item.partition("=")
        configs[name] = json.loads(text or "{}")
    return configs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("mode", choices=["steps", "loaders", "runs", "chart"])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--steps", type=int, default=6)
    parser.add_argument("--lever", action="append", default=[], help="steps: only these levers (and the reference)")
    parser.add_argument("--dataset", type=Path)
    parser.add_argument("--testset", type=Path, action="append", default=[])
    parser.add_argument("--config", action="append", default=[], help="NAME=JSON overrides (runs)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "detector_benchmark")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--runs", type=Path, action="append", default=[], help="runs JSONs to chart (chart mode)")
    parser.add_argument("--png", type=Path, help="the chart (chart mode)")
    parser.add_argument("--model", type=Path, help="a trained model.pt (loaders mode)")
    parser.add_argument("--repeats", type=int, default=2, help="loaders: runs per setting")
    parser.add_argument("--device", choices=["cpu", "cuda"], default="cpu",
                        help="runs: train and evaluate there (cuda: over the stage's CUDA budget)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.mode == "chart":
        if not args.runs or not args.png:
            parser.error("chart needs at least one --runs (a runs JSON) and --png")
        result = merge_runs(args.runs)
        draw_chart(result, args.png)
        print(runs_table(result))
        return
    if not args.dataset:
        parser.error(f"{args.mode} needs --dataset")
    if args.mode == "loaders":
        if not args.model or not args.out:
            parser.error("loaders needs --model (a trained model.pt) and --out")
        result = loader_costs(args.dataset, args.model, args.threads, args.steps, args.repeats)
        write_result(args.out, result)
        print(json.dumps(result["median_seconds_per_iteration"]), f"1 / 0: {result['workers_1_over_0']:.3f}")
        return
    if args.mode == "steps":
        result = step_costs(args.dataset, args.steps, args.threads, args.lever)
        print(steps_table(result))
        if args.out:
            write_result(args.out, result)
        return
    if not args.testset or not args.config or not args.out:
        parser.error("runs needs at least one --testset, at least one --config and --out")
    if args.device == "cuda" and not torch.cuda.is_available():
        print("no CUDA device: skipped")
        return
    runs(args.dataset, args.testset, parse_configs(args.config), args.seed, args.threads, args.work, args.out,
         args.device)
    print(runs_table(merge_runs([args.out])))


if __name__ == "__main__":
    main()
