"""Issue 56, item 5: box mAP against the composed dataset's size, at the detector's default epochs and at its default
iterations, from the summaries of a sweep (never typed-in numbers).

    python dag.py +experiment=dataset_size          # 1000, 2000, 5000 images; default epochs and equal steps; seed 0
    python -m benchmarks.dataset_size SWEEP [SWEEP ...]

SWEEP is a sweep's folder, outputs/multiruns/<time>; jobs of several sweeps (the seeds of one size, say) are pooled by
(images, epochs). Per point: the detector's iterations, seeds, box and mask mAP per test set (mean ± std over seeds),
and the minutes compose and train_maskrcnn took (their recorded compute; a grown dataset's reused shards count as
cached, so compose's minutes are those of the new shards). Writes dataset_size.md and dataset_size.png (box mAP
against images, one line per budget and test set) into the first SWEEP and prints the markdown.
"""
from __future__ import annotations

import argparse
import statistics
from collections import defaultdict
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from stages.app.report import (config_value, load_summaries, mean_std, seed_values,  # noqa: E402
                               test_names)
from stages.compose.spec import ComposeConfig  # noqa: E402
from stages.train_maskrcnn.spec import TrainMaskrcnnConfig  # noqa: E402

DEFAULT_IMAGES = ComposeConfig().num_images  # the default dataset: its iterations are the "equal steps" budget
DEFAULT_EPOCHS = TrainMaskrcnnConfig().epochs


def points(summaries: list[dict]) -> dict[tuple[int, float], list[dict]]:
    """The jobs grouped by (compose.num_images, train_maskrcnn.epochs), sorted by images then epochs."""
    groups: dict[tuple[int, float], list[dict]] = defaultdict(list)
    for summary in summaries:
        groups[(int(config_value(summary, "compose.num_images")),
                float(config_value(summary, "train_maskrcnn.epochs")))].append(summary)
    return dict(sorted(groups.items()))


def iterations(jobs: list[dict]) -> int:
    """The detector's iterations of the jobs' budget on their dataset (from their config: archived summaries too)."""
    budget = TrainMaskrcnnConfig(epochs=float(config_value(jobs[0], "train_maskrcnn.epochs")),
                                 batch_size=int(config_value(jobs[0], "train_maskrcnn.batch_size")))
    return budget.iterations(int(config_value(jobs[0], "compose.num_images")))


def stage_minutes(jobs: list[dict], stage: str) -> str:
    """Mean compute minutes of `stage` over the jobs ('—' when none recorded it)."""
    values = [job["compute_seconds_by_stage"][stage] / 60 for job in jobs if stage in job["compute_seconds_by_stage"]]
    return f"{statistics.mean(values):.1f}" if values else "—"


def budget_label(images: int, epochs: float, steps: int, default_steps: int | None) -> str:
    """'default epochs', 'equal steps' (the default dataset's iterations) or the epochs."""
    if steps == default_steps and images != DEFAULT_IMAGES:
        return "equal steps"
    return "default epochs" if epochs == DEFAULT_EPOCHS else f"{epochs:g} epochs"


def plot(rows: list[tuple[int, str, list[list[float]]]], tests: list[str], path: Path) -> None:
    """Box mAP (mean, std bars) against images: one line per budget and test set."""
    fig, ax = plt.subplots(figsize=(6.0, 3.8))
    for budget, marker in (("default epochs", "o"), ("equal steps", "s")):
        for k, test in enumerate(tests):
            line = [(images, values[k]) for images, label, values in rows
                    if values[k] and (label == budget or (images == DEFAULT_IMAGES and label == "default epochs"))]
            if len(line) < 2:
                continue
            ax.errorbar([p[0] for p in line], [statistics.mean(p[1]) for p in line],
                        yerr=[statistics.stdev(p[1]) if len(p[1]) > 1 else 0.0 for p in line], marker=marker,
                        capsize=3, label=f"{test}, {budget}")
    ax.set_xscale("log")
    ax.set_xticks([1000, 2000, 5000], ["1000", "2000", "5000"])
    ax.set_xticks([], minor=True)  # no log-axis labels between the sizes
    ax.set_xlabel("composed images")
    ax.set_ylabel("box mAP")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def report(sweeps: list[Path]) -> str:
    """The markdown table of every (images, epochs) point of the sweeps' jobs; dataset_size.png beside it."""
    summaries = load_summaries(*sweeps)
    tests, groups = test_names(summaries), points(summaries)
    default_steps = next((iterations(jobs) for (images, epochs), jobs in groups.items()
                          if images == DEFAULT_IMAGES and epochs == DEFAULT_EPOCHS), None)
    lines = ["| images | budget | detector iterations | seeds | " + " | ".join(f"box mAP {t}" for t in tests) + " | "
             + " | ".join(f"mask mAP {t}" for t in tests) + " | compose min | train_maskrcnn min |",
             "|---|---|---|---|" + "---|" * (2 * len(tests) + 2)]
    rows = []
    for (images, epochs), jobs in groups.items():
        steps = iterations(jobs)
        label = budget_label(images, epochs, steps, default_steps)
        boxes = [seed_values(jobs, t) for t in tests]
        rows.append((images, label, boxes))
        lines.append(f"| {images} | {label} | {steps} | {len(jobs)} | "
                     + " | ".join(mean_std(values) for values in boxes) + " | "
                     + " | ".join(mean_std(seed_values(jobs, t, "segm")) for t in tests)
                     + f" | {stage_minutes(jobs, 'compose')} | {stage_minutes(jobs, 'train_maskrcnn')} |")
    plot(rows, tests, sweeps[0] / "dataset_size.png")
    return "\n".join(lines + ["", "![box mAP against the dataset's size](dataset_size.png)"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sweeps", type=Path, nargs="+", help="sweep folders, outputs/multiruns/<time>")
    args = parser.parse_args()
    text = report(args.sweeps)
    (args.sweeps[0] / "dataset_size.md").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
