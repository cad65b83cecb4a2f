"""Issue 55, item 4: the frames of a walk through the in-domain rooms against in-domain photos and generic
backgrounds, and box mAP against the number of walk frames, from the summaries of two sweeps (never typed-in numbers).

    python dag.py +experiment=backgrounds                  # full, full_indomain, full_walk, cut_and_paste and
    python -m benchmarks.walk_backgrounds compare SWEEP    #   cut_and_paste_indomain, three seeds each
    python dag.py +experiment=walk_frames                  # full_walk with bg_frames.count 5, 10, 20, 40, seed 0
    python -m benchmarks.walk_backgrounds curve SWEEP

SWEEP is the sweep's folder, outputs/multiruns/<time>. compare: box mAP (mean ± std over seeds) of full, full_indomain
and full_walk per test set, and the difference of the means of walk frames against photos and of each against the
generic backgrounds, beside the seed spread (beyond it when larger than both standard deviations); writes
walk_backgrounds.md into SWEEP. curve: box mAP per test set against bg_frames.count and the slots the walk filled;
writes walk_frames.md and walk_frames.png into SWEEP. Both print the markdown.
"""
from __future__ import annotations

import argparse
import statistics
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from stages.app.report import (box_ap, by_variant, config_value, load_summaries, mean_std, seed_values,  # noqa: E402
                               test_names)
from stages.app.summary import stage_metrics  # noqa: E402

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


def compare(sweep: Path) -> str:
    """The markdown of the walk frames against photos and generic backgrounds (Cut-and-Splat, box mAP)."""
    summaries = load_summaries(sweep)
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


def curve(sweep: Path) -> str:
    """The markdown (and walk_frames.png in `sweep`) of box mAP against the number of walk frames."""
    summaries = sorted(load_summaries(sweep), key=lambda s: config_value(s, "bg_frames.count") or 0)
    tests = test_names(summaries)
    rows = [(config_value(s, "bg_frames.count"), filled_slots(s), [box_ap(s, t) for t in tests]) for s in summaries]
    fig, ax = plt.subplots(figsize=(5.5, 3.5))
    for k, test in enumerate(tests):
        points = [(count, aps[k]) for count, _, aps in rows if aps[k] is not None]
        ax.plot([p[0] for p in points], [p[1] for p in points], marker="o", label=test)
    ax.set_xscale("log", base=2)
    ax.set_xlabel("walk frames (bg_frames.count)")
    ax.set_ylabel("box mAP")
    ax.legend()
    fig.tight_layout()
    fig.savefig(sweep / "walk_frames.png", dpi=120)
    plt.close(fig)
    lines = ["| bg_frames.count | slots filled | " + " | ".join(f"box mAP {t}" for t in tests) + " |",
             "|---|---|" + "---|" * len(tests)]
    lines += [f"| {count} | {filled if filled is not None else '—'} | "
              + " | ".join("—" if ap is None else f"{ap:.1f}" for ap in aps) + " |" for count, filled, aps in rows]
    return "\n".join(lines + ["", "![box mAP against walk frames](walk_frames.png)"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("what", choices=("compare", "curve"))
    parser.add_argument("sweep", type=Path, help="the sweep's folder, outputs/multiruns/<time>")
    args = parser.parse_args()
    text = compare(args.sweep) if args.what == "compare" else curve(args.sweep)
    (args.sweep / f"{'walk_backgrounds' if args.what == 'compare' else 'walk_frames'}.md").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
