"""Detector benchmark: seconds per training step per backbone, and box mAP against training minutes.

  python benchmarks/detector.py steps [--threads 1] [--steps 5]
      seconds per train step (default config: batch 2, 320 px) and per inference image, per backbone,
      on synthetic 480x480 shape images.
  python benchmarks/detector.py budgets --dataset D --testset T [--testset T2] [--budgets 100 250 500]
      trains every backbone for each iteration budget on dataset D (COCO folder) and evaluates on
      each test set: box/mask AP against training minutes.
      With --out, runs already in that JSON are skipped and it is rewritten after every run.
  python benchmarks/detector.py chart --out budgets.json --png chart.png
      draws box mAP against training minutes (one panel per test set, Pareto front marked) and
      prints the markdown table.
Results are printed and written as JSON (--out).
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import statistics
import tempfile
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stages.context import Context  # noqa: E402
from stages.detection.data import Augmentation, CocoInstances  # noqa: E402
from stages.detection.model import build_maskrcnn, count_parameters, model_config_of  # noqa: E402
from tests.factories.shapes import write_shapes_dataset  # noqa: E402
from stages.eval import run as run_eval  # noqa: E402
from stages.report import pareto_front  # noqa: E402
from stages.train_maskrcnn import TrainMaskrcnnConfig, run as run_train  # noqa: E402

BACKBONES = ["efficientnet_lite0_fpn", "resnet18_fpn", "resnet50_fpn", "mobilenet_v3_fpn"]


def backbone_params(backbone: str) -> dict:
    """Config overrides per backbone: only EfficientNet-Lite0 has offline ImageNet weights."""
    return {"backbone": backbone, "pretrained": backbone == "efficientnet_lite0_fpn"}


def step_times(backbones: list[str], steps: int, threads: int) -> dict:
    """Median seconds per training step and per inference image of each backbone at the default config."""
    torch.set_num_threads(threads)
    folder = write_shapes_dataset(Path(tempfile.mkdtemp()) / "shapes", 8, size=480, seed=0)
    results = {}
    for backbone in backbones:
        cfg = TrainMaskrcnnConfig(**backbone_params(backbone))
        dataset = CocoInstances(folder, cfg.image_size)
        torch.manual_seed(0)
        model = build_maskrcnn(model_config_of(cfg), len(dataset.category_names)).train()
        optimizer = torch.optim.SGD([p for p in model.parameters() if p.requires_grad], lr=0.002, momentum=0.9)
        rng, augmentation = np.random.default_rng(0), Augmentation()
        times = []
        for step in range(steps + 1):  # the first step warms up and is not counted
            batch = [dataset.sample(i % len(dataset), rng, augmentation) for i in (2 * step, 2 * step + 1)]
            started = time.perf_counter()
            loss = sum(model([b[0] for b in batch], [b[1] for b in batch]).values())
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            times.append(time.perf_counter() - started)
        model.eval()
        infer = []
        with torch.no_grad():
            for i in range(3):
                image = dataset.sample(i)[0]
                started = time.perf_counter()
                model([image])
                infer.append(time.perf_counter() - started)
        results[backbone] = {"train_step_s": statistics.median(times[1:]), "inference_s": statistics.median(infer),
                             "parameters": count_parameters(model), "pretrained": cfg.pretrained}
        logging.info("%s: %s", backbone, results[backbone])
    return {"threads": threads, "batch_size": 2, "image_size": 320, "steps": steps, "backbones": results}


def run_key(row: dict) -> tuple[str, int]:
    """(backbone, iterations) of one budgets run."""
    return row["backbone"], row["iterations"]


def train_and_evaluate(dataset: Path, testsets: list[Path], backbone: str, iterations: int, threads: int,
                       work: Path) -> dict:
    """Train one backbone for one iteration budget, evaluate it on every test set: one result row."""
    name = f"{backbone}_{iterations}"
    out = work / name / "train"
    out.mkdir(parents=True, exist_ok=True)
    params = {**backbone_params(backbone), "iterations": iterations, "threads": threads}
    load_before = os.getloadavg()[0]
    train = run_train(Context("train_maskrcnn", name, params, {"dataset": dataset}, out, seed=0))
    row = {"backbone": backbone, "iterations": iterations, "pretrained": params["pretrained"],
           "train_minutes": train["seconds"] / 60, "seconds_per_iteration": train["seconds_per_iteration"],
           "final_loss": train["final_loss"], "load_1min": [load_before, os.getloadavg()[0]]}
    for testset in testsets:
        eval_out = work / name / f"eval_{testset.name}"
        eval_out.mkdir(parents=True, exist_ok=True)
        metrics = run_eval(Context("eval", name, {"threads": threads}, {"model": out, "testset": testset}, eval_out))
        row[testset.name] = {"box_AP": metrics["bbox"]["AP"], "box_AP50": metrics["bbox"]["AP50"],
                             "mask_AP": metrics["segm"]["AP"],
                             "inference_s": metrics["inference_seconds_per_image"]}
    logging.info("%s", row)
    return row


def budgets(dataset: Path, testsets: list[Path], backbones: list[str], iteration_budgets: list[int],
            threads: int, work: Path, out: Path | None) -> dict:
    """Train each backbone for each budget and evaluate on every test set.

    With `out`, runs already recorded there (same dataset) are skipped and the file is rewritten
    after every finished run, so an interrupted benchmark keeps what it measured.
    """
    result = {"dataset": str(dataset), "testsets": [str(t) for t in testsets], "threads": threads, "runs": []}
    if out and out.exists():
        recorded = json.loads(out.read_text())
        if recorded["dataset"] != str(dataset) or recorded["threads"] != threads:
            raise SystemExit(f"{out} holds runs on {recorded['dataset']} with {recorded['threads']} threads, "
                             f"not {dataset} with {threads}: pass another --out")
        result["runs"] = recorded["runs"]
    done = {run_key(row) for row in result["runs"]}
    for backbone in backbones:
        for iterations in iteration_budgets:
            if (backbone, iterations) in done:
                logging.info("%s %d: already in %s, skipped", backbone, iterations, out)
                continue
            result["runs"].append(train_and_evaluate(dataset, testsets, backbone, iterations, threads, work))
            if out:
                out.parent.mkdir(parents=True, exist_ok=True)
                out.write_text(json.dumps(result, indent=1))
    return result


def draw_budgets_chart(result: dict, png: Path) -> None:
    """Box mAP against training minutes, one line per backbone, one panel per test set; Pareto front marked."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    testsets = [Path(t).name for t in result["testsets"]]
    runs = sorted(result["runs"], key=run_key)
    figure, axes = plt.subplots(1, len(testsets), figsize=(6 * len(testsets), 4.5), sharey=True, squeeze=False)
    for axis, testset in zip(axes[0], testsets):
        for backbone in dict.fromkeys(row["backbone"] for row in runs):
            rows = [row for row in runs if row["backbone"] == backbone]
            minutes = [row["train_minutes"] for row in rows]  # [B]
            box_ap = [row[testset]["box_AP"] for row in rows]  # [B]
            weights = "ImageNet" if rows[0]["pretrained"] else "scratch"
            axis.plot(minutes, box_ap, "o-", label=f"{backbone} ({weights})")
            for row, x, y in zip(rows, minutes, box_ap):
                axis.annotate(str(row["iterations"]), (x, y), textcoords="offset points", xytext=(4, 4), fontsize=7)
        points = [(row["train_minutes"], row[testset]["box_AP"]) for row in runs]
        front = [points[i] for i in pareto_front(points)]
        axis.step([p[0] for p in front], [p[1] for p in front], "k--", where="post", lw=1, label="Pareto front")
        axis.scatter([p[0] for p in front], [p[1] for p in front], s=120, facecolors="none", edgecolors="k")
        axis.set_title(f"{testset} (labels: iterations)")
        axis.set_xlabel(f"training minutes ({result['threads']} CPU thread, shared machine)")
        axis.grid(alpha=0.3)
    axes[0][0].set_ylabel("box mAP (COCO AP, %)")
    axes[0][-1].legend(fontsize=8)
    figure.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(png, dpi=120)
    plt.close(figure)


def budgets_table(result: dict) -> str:
    """Markdown table of the budgets runs: minutes, s/it, box AP / AP50 / mask AP and inference s per test set."""
    testsets = [Path(t).name for t in result["testsets"]]
    header = ["backbone", "weights", "iterations", "train minutes", "s / it", "load (1 min, start-end)"]
    header += [f"{t}: box AP / AP50 / mask AP" for t in testsets] + [f"{t}: inference s / image" for t in testsets]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for row in sorted(result["runs"], key=run_key):
        cells = [row["backbone"], "ImageNet" if row["pretrained"] else "scratch", str(row["iterations"]),
                 f"{row['train_minutes']:.1f}", f"{row['seconds_per_iteration']:.2f}",
                 "-".join(f"{load:.1f}" for load in row["load_1min"])]
        cells += [f"{row[t]['box_AP']:.1f} / {row[t]['box_AP50']:.1f} / {row[t]['mask_AP']:.1f}" for t in testsets]
        cells += [f"{row[t]['inference_s']:.2f}" for t in testsets]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("mode", choices=["steps", "budgets", "chart"])
    parser.add_argument("--backbones", nargs="+", default=BACKBONES)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--dataset", type=Path)
    parser.add_argument("--testset", type=Path, action="append", default=[])
    parser.add_argument("--budgets", type=int, nargs="+", default=[100, 250, 500])
    parser.add_argument("--work", type=Path, default=Path("outputs/benchmarks/detector"))
    parser.add_argument("--out", type=Path)
    parser.add_argument("--png", type=Path, help="chart of a budgets JSON (chart mode: --out is read)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.mode == "chart":
        if not args.out or not args.png:
            parser.error("chart needs --out (the budgets JSON to read) and --png")
        result = json.loads(args.out.read_text())
        draw_budgets_chart(result, args.png)
        print(budgets_table(result))
        return
    if args.mode == "steps":
        result = step_times(args.backbones, args.steps, args.threads)
    else:
        if not args.dataset or not args.testset:
            parser.error("budgets needs --dataset and at least one --testset")
        result = budgets(args.dataset, args.testset, args.backbones, args.budgets, args.threads, args.work,
                         args.out)
    text = json.dumps(result, indent=1)
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)


if __name__ == "__main__":
    main()
