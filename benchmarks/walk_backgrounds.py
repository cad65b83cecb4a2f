"""Issue 55, item 4: the frames of a walk through the in-domain rooms against in-domain photos and generic
backgrounds, and box mAP against the number of walk frames, from the summaries of two sweeps (never typed-in numbers).

    python dag.py +experiment=backgrounds                  # full, full_indomain, full_walk, cut_and_paste and
    python -m benchmarks.walk_backgrounds compare SWEEP    #   cut_and_paste_indomain, three seeds each
    python dag.py +experiment=walk_frames                  # full_walk with bg_frames.count 5, 10, 20, 40, seed 0
    python -m benchmarks.walk_backgrounds curve SWEEP
    python -m benchmarks.walk_backgrounds sizes NAME=FOLDER ...   # composed datasets and test sets, side by side

SWEEP is the sweep's folder, outputs/multiruns/<time>; more folders after it pool their jobs with its own (a sweep run
in parts, or the generic-background jobs of an +experiment=ablation folder), and the files go into the first. compare:
box mAP (mean ± std over seeds) of full, full_indomain and full_walk per test set, and the difference of the means of
walk frames against photos and of each against the generic backgrounds, beside the seed spread (beyond it when larger
than both standard deviations); writes walk_backgrounds.md. curve: box mAP per test set against bg_frames.count and
the slots the walk filled; writes walk_frames.md and walk_frames.png. Both print the markdown. sizes: how large and
where the instances of COCO folders (a job's dataset in the cache, a test set) are, as the dataset card measures them.
"""
from __future__ import annotations

import argparse
import statistics
from collections import defaultdict
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from stages.app.report import (by_variant, config_value, load_summaries, mean_std, seed_values,  # noqa: E402
                               test_names)
from stages.app.summary import stage_metrics  # noqa: E402
from stages.lib.cards.stats import dataset_stats  # noqa: E402
from stages.records.coco_dataset import CocoDataset  # noqa: E402

VARIANTS = (("full", "generic backgrounds"), ("full_indomain", "in-domain photos"),
            ("full_walk", "walk frames"))
PAIRS = (("full_walk", "full_indomain"), ("full_walk", "full"), ("full_indomain", "full"))


def difference(ours: list[float], theirs: list[float]) -> str:
    """'+d (std a / std b), beyond | within the spread' of two variants' box mAP over seeds ('—' without both)."""
    if not ours or not theirs:
        return "—"
    lead = statistics.mean(ours) - statistics.mean(theirs)
    if len(ours) < 2 or len(theirs) < 2:
        return f"{lead:+.1f} (one seed)"
    spreads = (statistics.stdev(ours), statistics.stdev(theirs))
    return (f"{lead:+.1f} ({spreads[0]:.1f} / {spreads[1]:.1f}), "
            f"{'beyond' if abs(lead) > max(spreads) else 'within'} the spread")


def compare(sweeps: list[Path]) -> str:
    """The markdown of the walk frames against photos and generic backgrounds (Cut-and-Splat, box mAP)."""
    summaries = load_summaries(*sweeps)
    tests, groups = test_names(summaries), by_variant(summaries)
    lines = ["| backgrounds (Cut-and-Splat) | seeds | " + " | ".join(f"box mAP {t}" for t in tests) + " |",
             "|---|---|" + "---|" * len(tests)]
    lines += [f"| {label} | {len(groups.get(name, []))} | "
              + " | ".join(mean_std(seed_values(groups.get(name, []), t)) for t in tests) + " |"
              for name, label in VARIANTS]
    lines += ["", "| difference of the means (std over seeds) | " + " | ".join(tests) + " |",
              "|---|" + "---|" * len(tests)]
    labels = dict(VARIANTS)
    lines += [f"| {labels[a]} − {labels[b]} | "
              + " | ".join(difference(seed_values(groups.get(a, []), t), seed_values(groups.get(b, []), t))
                           for t in tests) + " |" for a, b in PAIRS]
    return "\n".join(lines)


def filled_slots(summary: dict) -> int | None:
    """How many frame slots the walk's bg_frames node filled in a job (None when it did not run or was not found)."""
    metrics = stage_metrics(summary, "bg_frames")
    return None if metrics is None else metrics.get("filled")


def curve(sweeps: list[Path]) -> str:
    """The markdown (and walk_frames.png in the first sweep folder) of box mAP against the number of walk frames:
    the full_walk jobs of the sweeps by bg_frames.count, mean ± std where a count has several seeds."""
    walks = [s for s in load_summaries(*sweeps) if s["variant"]["name"] == "full_walk"]
    tests, by_count = test_names(walks), defaultdict(list)
    for summary in walks:
        by_count[config_value(summary, "bg_frames.count")].append(summary)
    counts = sorted(by_count)
    fig, ax = plt.subplots(figsize=(5.5, 3.5))
    for test in tests:
        points = [(count, statistics.mean(aps)) for count in counts if (aps := seed_values(by_count[count], test))]
        ax.plot([p[0] for p in points], [p[1] for p in points], marker="o", label=test)
    ax.set_xscale("log", base=2)
    ax.set_xticks(counts, [str(count) for count in counts])  # the counts run; no powers of 2 between them
    ax.set_xticks([], minor=True)
    ax.set_xlabel("walk frames (bg_frames.count)")
    ax.set_ylabel("box mAP")
    ax.legend()
    fig.tight_layout()
    fig.savefig(sweeps[0] / "walk_frames.png", dpi=120)
    plt.close(fig)
    lines = ["| bg_frames.count | seeds | slots filled | " + " | ".join(f"box mAP {t}" for t in tests) + " |",
             "|---|---|---|" + "---|" * len(tests)]
    for count in counts:
        filled = sorted({f for job in by_count[count] if (f := filled_slots(job)) is not None})
        lines.append(f"| {count} | {len(by_count[count])} | {', '.join(map(str, filled)) or '—'} | "
                     + " | ".join(mean_std(seed_values(by_count[count], t)) for t in tests) + " |")
    return "\n".join(lines + ["", "![box mAP against walk frames](walk_frames.png)"])


def sizes(folders: dict[str, Path]) -> str:
    """The markdown of each COCO folder's instance sizes (square root of the mask area, pixels: quartiles) and box
    centres' height in the image (fraction of its height: median), as the dataset card measures them."""
    lines = ["| folder | instances | size px: 25 % / median / 75 % | box centre y (median) |", "|---|---|---|---|"]
    for name, folder in folders.items():
        stats = dataset_stats(CocoDataset.read(folder))
        quartiles = " / ".join(f"{v:.0f}" for v in np.percentile(stats.size_px, [25, 50, 75]))
        lines.append(f"| {name} | {stats.instances} | {quartiles} | {np.median(stats.centre[:, 1]):.2f} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("what", choices=("compare", "curve", "sizes"))
    parser.add_argument("paths", nargs="+", help="sweep folders, outputs/multiruns/<time>; sizes: NAME=FOLDER of COCO "
                                                "folders")
    args = parser.parse_args()
    if args.what == "sizes":
        if not all("=" in entry for entry in args.paths):
            parser.error("sizes takes NAME=FOLDER arguments (a label, '=', a COCO folder)")
        print(sizes({name: Path(path) for name, _, path in (entry.partition("=") for entry in args.paths)}))
        return
    sweeps = [Path(path) for path in args.paths]
    text = compare(sweeps) if args.what == "compare" else curve(sweeps)
    (sweeps[0] / f"{'walk_backgrounds' if args.what == 'compare' else 'walk_frames'}.md").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
