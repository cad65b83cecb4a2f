"""The benchmark report: tables and plots from the run summaries of a sweep (never typed-in numbers).

Runs as a Hydra callback at the end of a sweep (`+experiment=...`), or alone, pooling the jobs of several sweep
folders (a sweep run in parts) into the first one's report:

    python -m stages.app.report outputs/multiruns/<time> [more sweep folders]
"""
from __future__ import annotations

import argparse
import json
import logging
import statistics
from collections import defaultdict
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from hydra.experimental.callback import Callback  # noqa: E402

from stages.app.summary import summary_outcomes  # noqa: E402
from stages.records.coco_dataset import CocoDataset  # noqa: E402

log = logging.getLogger(__name__)

# The paper's published numbers (box mAP, IBSYD), shown beside ours for reference only.
PAPER_ABLATION = {"full": (81.21, 79.68), "no_aug": (71.17, 73.71), "no_placement": (52.05, 53.51)}
PAPER_PER_CLASS = {"bottle": 88.44, "eyedrops": 79.39, "plant": 69.89, "sprite": 93.07, "vase": 75.29}
VARIANT_KEYS = ("variant.", "compose.augment", "compose.placement", "compose.shadow", "compose.relight",
                "run.seed")  # axes of the ablation table (seeds are averaged)
ABLATION_ROWS = [("full", "Cut-and-Splat"), ("no_aug", "no augmentation"), ("no_placement", "no smart placement"),
                 ("shadow", "with cast shadows"), ("relight", "with relighting"),
                 ("effects", "with shadows and relighting"), ("cut_and_paste", "Cut-and-Paste")]
EFFECT_VARIANTS = ("shadow", "relight", "effects")  # full with issue 32's effects on: the same placements
EFFECT_IMAGES = 3  # images of the effects figure


def load_summaries(*sweep_dirs: Path) -> list[dict]:
    """Every job's summary.json under the sweep folders, pooled (jobs that crashed have none and are listed)."""
    summaries = []
    for path in (path for sweep_dir in sweep_dirs for path in sorted(sweep_dir.glob("*/summary.json"))):
        summary = json.loads(path.read_text())
        summary["job_dir"] = str(path.parent)
        summaries.append(summary)
    return summaries


def box_ap(summary: dict, test: str, iou_type: str = "bbox", stat: str = "AP") -> float | None:
    """Box AP (percent; iou_type "segm": mask AP; stat "AP50": at IoU 0.5) of a job's model on one test
    set; None when that eval did not finish or the test set cannot measure it (boxes only)."""
    metrics = summary["eval"].get(f"{summary['variant']['name']}@{test}")
    ap = None if metrics is None else metrics[iou_type][stat]
    return None if ap is None else float(ap)


def seed_values(jobs: list[dict], test: str, iou_type: str = "bbox", stat: str = "AP") -> list[float]:
    """box_ap of each job (one per seed of a variant) on one test set, leaving out the jobs without it."""
    return [v for job in jobs if (v := box_ap(job, test, iou_type, stat)) is not None]


def test_names(summaries: list[dict]) -> list[str]:
    """The test sets' names of the jobs' configs, in the order first met."""
    names: list[str] = []
    for summary in summaries:
        for test in summary["config"]["data"]["test_sets"]:
            if test["name"] not in names:
                names.append(test["name"])
    return names


def mean_std(values: list[float]) -> str:
    """'m' for one value, 'm ± s' for several, '—' for none."""
    if len(values) < 2:
        return f"{values[0]:.1f}" if values else "—"
    return f"{statistics.mean(values):.1f} ± {statistics.stdev(values):.1f}"


def mean_std_of(point: dict) -> str:
    """'m' or 'm ± s' of a compute point."""
    return f"{point['mAP']:.1f}" + (f" ± {point['std']:.1f}" if point["seeds"] > 1 else "")


def by_variant(summaries: list[dict]) -> dict[str, list[dict]]:
    """Jobs grouped by variant name (several jobs per variant = several seeds)."""
    groups: dict[str, list[dict]] = defaultdict(list)
    for summary in summaries:
        groups[summary["variant"]["name"]].append(summary)
    return groups


def variant_rows(groups: dict[str, list[dict]]) -> list[tuple[str, str]]:
    """(variant name, row label) of the variants in `groups`: the paper's rows first, in its order, then the rest."""
    labels = dict(ABLATION_ROWS)
    return [(n, label) for n, label in ABLATION_ROWS if n in groups] + [(n, n) for n in groups if n not in labels]


def ablation_table(summaries: list[dict]) -> str:
    """The paper's Table 1 layout: one row per variant, box mAP per test set (ours, then the paper's),
    then our box AP50 and mask mAP per test set (the paper gives neither)."""
    tests = test_names(summaries)
    groups = by_variant(summaries)
    header = ("| Dataset | " + " | ".join(f"box mAP {t}" for t in tests) + " | paper mAP iPhone | paper mAP Canon | "
              + " | ".join(f"box AP50 {t}" for t in tests) + " | " + " | ".join(f"mask mAP {t}" for t in tests) + " |")
    lines = [header, "|" + "---|" * (3 * len(tests) + 3)]
    for name, label in variant_rows(groups):
        cells = {metric: [mean_std(seed_values(groups[name], t, *metric))
                          for t in tests] for metric in (("bbox", "AP"), ("bbox", "AP50"), ("segm", "AP"))}
        paper = PAPER_ABLATION.get(name, ("—", "—"))
        lines.append(f"| {label} | " + " | ".join(cells["bbox", "AP"]) + f" | {paper[0]} | {paper[1]} | "
                     + " | ".join(cells["bbox", "AP50"]) + " | " + " | ".join(cells["segm", "AP"]) + " |")
    return "\n".join(lines)


def lead_table(summaries: list[dict], reference: str = "full") -> str:
    """How far the reference variant's mean box mAP lies above each other variant's, per test set, against the
    seed spread: 'yes' when the lead exceeds both variants' standard deviations over seeds ('—' with one seed)."""
    tests = test_names(summaries)
    groups = by_variant(summaries)
    if reference not in groups:
        return ""
    lines = ["| " + dict(variant_rows(groups))[reference] + " against | " + " | ".join(
        f"lead {t} (std {reference} / other) | beyond spread {t}" for t in tests) + " |",
             "|---|" + "---|" * (2 * len(tests))]
    for name, label in variant_rows(groups):
        if name == reference:
            continue
        cells = []
        for test in tests:
            ours, theirs = seed_values(groups[reference], test), seed_values(groups[name], test)
            if not ours or not theirs:
                cells += ["—", "—"]
                continue
            lead = statistics.mean(ours) - statistics.mean(theirs)
            if len(ours) < 2 or len(theirs) < 2:
                cells += [f"{lead:+.1f}", "— (one seed)"]
                continue
            spreads = (statistics.stdev(ours), statistics.stdev(theirs))
            cells += [f"{lead:+.1f} ({spreads[0]:.1f} / {spreads[1]:.1f})", "yes" if lead > max(spreads) else "no"]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def per_class_table(summaries: list[dict], variant: str = "full") -> str:
    """The paper's Table 2 layout: per-class box AP of one variant on each test set."""
    jobs = by_variant(summaries).get(variant, [])
    if not jobs:
        return f"(no `{variant}` job in this sweep)"
    tests = test_names(summaries)
    classes: list[str] = []
    for job in jobs:
        for metrics in job["eval"].values():
            classes += [c for c in metrics["bbox"].get("per_class", {}) if c not in classes]
    lines = ["| Class | " + " | ".join(tests) + " |", "|" + "---|" * (len(tests) + 1)]
    for cls in classes:
        cells = []
        for test in tests:
            values = [m["bbox"]["per_class"][cls] for j in jobs
                      if (m := j["eval"].get(f"{variant}@{test}")) and cls in m["bbox"].get("per_class", {})]
            cells.append(mean_std([float(v) for v in values]))
        lines.append(f"| {cls} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def total_seconds(summary: dict) -> float:
    """Compute time of everything the job's configuration needs (cached stages count their recorded time)."""
    return float(sum(summary.get("compute_seconds_by_stage", {}).values()))


def pareto_front(points: list[tuple[float, float]]) -> list[int]:
    """Indices of points not dominated (less time and at least as much mAP), sorted by time."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], -points[i][1]))
    front, best = [], float("-inf")
    for i in order:
        if points[i][1] > best:
            front.append(i)
            best = points[i][1]
    return front


def plot_background_study(summaries: list[dict], test: str, path: Path) -> bool:
    """The paper's Figure 9: Cut-and-Splat vs Cut-and-Paste, generic vs in-domain backgrounds (mean box mAP over
    seeds, std as error bars); False (nothing drawn) unless at least two of those variants are in the sweep."""
    groups = by_variant(summaries)
    bars = [("full", "Cut-and-Splat\ngeneric", "tab:blue"), ("full_indomain", "Cut-and-Splat\nin-domain", "tab:cyan"),
            ("cut_and_paste", "Cut-and-Paste\ngeneric", "tab:orange"),
            ("cut_and_paste_indomain", "Cut-and-Paste\nin-domain", "tab:red")]
    present = [(label, seed_values(groups[name], test), colour)
               for name, label, colour in bars if name in groups]
    present = [bar for bar in present if bar[1]]
    if len(present) < 2:
        return False
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.bar([p[0] for p in present], [statistics.mean(p[1]) for p in present], capsize=4,
           yerr=[statistics.stdev(p[1]) if len(p[1]) > 1 else 0.0 for p in present],
           color=[p[2] for p in present])
    ax.set_ylabel(f"box mAP on {test}")
    ax.set_title("Cut-and-Splat vs Cut-and-Paste")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True


def compose_folder(summary: dict) -> Path | None:
    """The folder of the compose dataset a job made or found cached (None when it has none)."""
    for outcome in summary_outcomes(summary):
        if outcome.get("stage") == "compose" and outcome.get("status") in ("ran", "cached") and outcome.get("path"):
            folder = Path(outcome["path"])
            return folder if (folder / CocoDataset.JSON).is_file() else None
    return None


def plot_effects(summaries: list[dict], path: Path) -> bool:
    """The same placements with and without issue 32's effects: the first EFFECT_IMAGES plane-placed images of
    the full variant's dataset and of each effect variant's, of one seed they share (an image's placements do not
    depend on the effects); False (nothing drawn) unless full and an effect variant have a dataset folder."""
    groups = by_variant(summaries)
    folders = {name: found for name in ("full", *EFFECT_VARIANTS)  # {variant: {seed: its dataset folder}}
               if (found := {int(job["config"]["run"]["seed"]): folder for job in groups.get(name, [])
                             if (folder := compose_folder(job)) is not None})}
    shared = sorted(set(folders.get("full", {})).intersection(*[set(f) for n, f in folders.items() if n != "full"]))
    if "full" not in folders or len(folders) < 2 or not shared:
        return False
    seed, columns = shared[0], list(folders)
    coco = CocoDataset.read(folders["full"][seed])
    planar = {ann["image_id"] for ann in coco.annotations if ann.get("placement") == "plane"}
    if not (images := [image for image in coco.images if image["id"] in planar][:EFFECT_IMAGES]):
        return False
    fig, axes = plt.subplots(len(images), len(columns), figsize=(3.2 * len(columns), 2.5 * len(images)), squeeze=False)
    for row, image in enumerate(images):
        for column, name in enumerate(columns):
            axes[row][column].imshow(plt.imread(CocoDataset.image_file(folders[name][seed], image)))
            axes[row][column].set_axis_off()
            if row == 0:
                axes[row][column].set_title(f"{dict(ABLATION_ROWS)[name]} (seed {seed})", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True


def plot_stage_times(summaries: list[dict], path: Path) -> bool:
    """Compute minutes per stage of each variant's jobs (mean over its seeds; stacked bars, legend beside)."""
    groups = by_variant(summaries)
    names = list(groups)
    stages = sorted({stage for s in summaries for stage in s.get("compute_seconds_by_stage", {})})
    if not stages:
        return False
    fig, ax = plt.subplots(figsize=(8, 3.8))
    bottom = [0.0] * len(names)
    colours = plt.get_cmap("tab20").colors  # one colour per stage (tab10 repeats after ten)
    for number, stage in enumerate(stages):
        values = [statistics.mean(s.get("compute_seconds_by_stage", {}).get(stage, 0.0) for s in groups[name]) / 60
                  for name in names]
        ax.bar(range(len(names)), values, bottom=bottom, label=stage, color=colours[number % len(colours)])
        bottom = [b + v for b, v in zip(bottom, values)]
    ax.set_xticks(range(len(names)), names, rotation=30, ha="right")
    ax.set_ylabel("compute minutes per job")
    ax.set_title("every stage a job needs, cached ones at their recorded time", fontsize=9)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True


def config_value(summary: dict, key: str) -> Any:
    """The value of a dotted config key in a job's summary (None when absent)."""
    value: Any = summary["config"]
    for part in key.split("."):
        value = value.get(part) if isinstance(value, dict) else None
    return value


def job_label(summary: dict, keys: list[str]) -> str:
    """A short label from the overrides that vary across the sweep, e.g. "epochs=2, splat_train.iterations=1000"."""
    short = {k: k.split(".")[-1] for k in keys}
    clashing = {name for name in short.values() if list(short.values()).count(name) > 1}
    return ", ".join(f"{k if short[k] in clashing else short[k]}={config_value(summary, k)}" for k in keys)


def varying_keys(summaries: list[dict]) -> list[str]:
    """Dotted config keys whose values differ between jobs (ignoring run bookkeeping)."""
    def flatten(d: dict, prefix: str = "") -> dict[str, Any]:
        out = {}
        for k, v in d.items():
            key = f"{prefix}{k}"
            out.update(flatten(v, key + ".") if isinstance(v, dict) else {key: json.dumps(v, sort_keys=True)})
        return out

    flats = [flatten(s["config"]) for s in summaries]
    keys = sorted(set().union(*flats)) if flats else []
    return [k for k in keys if len({f.get(k) for f in flats}) > 1 and not k.startswith("run.cache")]


def compute_points(summaries: list[dict], test: str) -> list[dict]:
    """One point per configuration (seeds pooled): label, compute minutes (mean), box mAP mean and std,
    number of seeds; sorted by minutes and numbered from 1 in that order."""
    keys = [k for k in varying_keys(summaries) if k != "run.seed"]
    groups: dict[str, list[dict]] = defaultdict(list)
    for summary in summaries:
        if box_ap(summary, test) is not None:
            groups[job_label(summary, keys)].append(summary)
    points = [{"label": label, "minutes": statistics.mean(total_seconds(s) / 60 for s in jobs),
               "mAP": statistics.mean(box_ap(s, test) for s in jobs),
               "std": statistics.stdev([box_ap(s, test) for s in jobs]) if len(jobs) > 1 else 0.0,
               "seeds": len(jobs)} for label, jobs in groups.items()]
    points.sort(key=lambda p: p["minutes"])
    front = set(pareto_front([(p["minutes"], p["mAP"]) for p in points]))
    for number, point in enumerate(points, start=1):
        point.update(number=number, pareto=number - 1 in front)
    return points


def plot_speed_accuracy(points: list[dict], test: str, path: Path) -> None:
    """Box mAP (mean, std bars over seeds) against compute minutes per configuration; points carry
    their number in the report's table (long labels stay off the canvas); the Pareto front is a step line."""
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for point in points:
        colour = "tab:red" if point["pareto"] else "tab:gray"
        ax.errorbar(point["minutes"], point["mAP"], yerr=point["std"] or None, fmt="o", color=colour, ms=5,
                    capsize=3, zorder=3)
        ax.annotate(str(point["number"]), (point["minutes"], point["mAP"]), fontsize=9, xytext=(4, 4),
                    textcoords="offset points")
    line = [p for p in points if p["pareto"]]
    ax.step([p["minutes"] for p in line], [p["mAP"] for p in line], "r--", where="post", lw=1, label="Pareto front")
    ax.set_xlabel("compute minutes of the configuration (every stage it needs)")
    ax.set_ylabel(f"box mAP on {test}")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write_report(sweep_dir: Path, more: tuple[Path, ...] = ()) -> Path:
    """Write report.md (+ PNG plots) into the sweep folder from its jobs' summaries and those of `more` folders."""
    summaries = load_summaries(sweep_dir, *more)
    out, folders = sweep_dir / "report.md", ", ".join(f"`{folder}`" for folder in (sweep_dir, *more))
    if not summaries:
        out.write_text(f"# Report\n\nNo job summaries under {folders}: every job failed before the end.\n")
        return out
    tests = test_names(summaries)
    lines = ["# Cut-and-Splat report", "", f"Sweep folders: {folders}; {len(summaries)} jobs.", ""]
    other_axes = [k for k in varying_keys(summaries) if not k.startswith(VARIANT_KEYS)]
    if not other_axes:
        lines += ["## Ablation (paper Table 1 layout; box mAP over IoU 0.50:0.95, percent)", "",
                  "Ours on this sweep's data (mean ± std over seeds when several); the paper's figures are on "
                  "its real IBSYD data (iPhone / Canon) and are shown for reference only.", "",
                  ablation_table(summaries), ""]
        leads = lead_table(summaries)
        if leads:
            lines += ["Lead of Cut-and-Splat over the other variants (difference of mean box mAP; 'beyond spread' when "
                      "it exceeds both variants' standard deviations over seeds):", "", leads, ""]
    if not other_axes and plot_background_study(summaries, tests[0], sweep_dir / "backgrounds.png"):
        lines += ["## Cut-and-Splat vs Cut-and-Paste, generic vs in-domain backgrounds (paper Figure 9)", "",
                  "![backgrounds](backgrounds.png)", ""]
    if not other_axes and plot_effects(summaries, sweep_dir / "effects.png"):
        lines += ["## Cast shadows and relighting (issue 32): the same placements with and without them", "",
                  "![effects](effects.png)", ""]
    if not other_axes:
        lines += ["## Per-class box AP of the full variant (paper Table 2 layout)", "", per_class_table(summaries),
                  "", "Paper (IBSYD, iPhone): " + ", ".join(f"{k} {v}" for k, v in PAPER_PER_CLASS.items()), ""]
    points = compute_points(summaries, tests[0]) if other_axes else []
    if len(points) > 1:  # a sweep over budgets (an ablation compares methods at equal compute: no chart)
        plot_speed_accuracy(points, tests[0], sweep_dir / "speed_accuracy.png")
        lines += ["## Speed against accuracy", "", "![speed vs accuracy](speed_accuracy.png)", "",
                  "| # | configuration | compute minutes | box mAP | seeds | Pareto |", "|---|---|---|---|---|---|"]
        lines += [f"| {p['number']} | {p['label']} | {p['minutes']:.1f} | {mean_std_of(p)} | {p['seeds']} | "
                  f"{'yes' if p['pareto'] else ''} |" for p in points]
        lines.append("")
    if plot_stage_times(summaries, sweep_dir / "stage_times.png"):
        lines += ["## Time per stage", "", "![stage times](stage_times.png)", ""]
    failures = [f for s in summaries for f in s.get("failed", [])]
    if failures:
        lines += ["## Failures", ""] + [f"- {f}" for f in failures] + [""]
    out.write_text("\n".join(lines))
    log.info("report written to %s", out)
    return out


class ReportCallback(Callback):
    """Hydra callback: writes report.md into the sweep folder when a multirun ends."""

    def on_multirun_end(self, config, **kwargs) -> None:  # noqa: ANN001 - Hydra's signature
        write_report(Path(config.hydra.sweep.dir))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sweep_dir", type=Path, help="the sweep folder the report is written into")
    parser.add_argument("more", type=Path, nargs="*", help="sweep folders whose jobs join the report")
    print(write_report((args := parser.parse_args()).sweep_dir, tuple(args.more)))


if __name__ == "__main__":
    main()
