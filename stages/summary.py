"""The end of a run or plan: summary.json (every node's record, the eval metrics, input problems, warnings and
what was left out) and the short report printed on screen (per stage, items by status and their seconds;
the eval results; where the summary and previews are). The full table stays in summary.json / plan.json.
"""
from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import Mapping

from omegaconf import DictConfig, OmegaConf

from stages.coco import format_ap
from stages.engine import MANIFEST, Record

RUN_COLUMNS = ("ran", "cached", "failed", "blocked")
PLAN_COLUMNS = ("cached", "would-run", "bad-input", "blocked")
PREVIEWS = ("preview.png", "predictions.png")  # a dataset's preview (compose, cut_and_paste); eval's predictions
SHOWN = 10  # lines of each list the report shows; the rest is in the JSON file


def summarise(records: list[Record], cfg: DictConfig, problems: Mapping[Path, str], notes: list[str]) -> dict:
    """The run summary: one row per node, the eval metrics of this configuration, input problems, warnings
    (of cached nodes too, from their manifests), what each node ran without, previews and notes."""
    evals, stage_seconds = {}, {}
    for record in records:
        if record.stage == "eval" and record.status in ("ran", "cached"):
            evals[record.item] = json.loads((Path(record.path) / "metrics.json").read_text())
        manifest = Path(record.path) / MANIFEST
        if record.path and record.status in ("ran", "cached") and manifest.is_file():
            seconds = json.loads(manifest.read_text()).get("seconds", 0.0)
            stage_seconds[record.stage] = stage_seconds.get(record.stage, 0.0) + seconds
    return {
        "variant": OmegaConf.to_container(cfg.variant, resolve=True),
        "config": OmegaConf.to_container(cfg, resolve=True),
        "records": [asdict(record) for record in records],
        "eval": evals,
        "compute_seconds_by_stage": stage_seconds,
        "failed": [f"{r.label}: {r.error}" for r in records if r.status == "failed"],
        "input_problems": {str(path): message for path, message in problems.items()},
        "warnings": [f"{r.label}: {warning}" for r in records for warning in r.warnings],
        "left_out": {r.label: r.left_out for r in records if r.left_out},
        "previews": [str(Path(r.path) / name) for r in records if r.path and r.status in ("ran", "cached")
                     for name in PREVIEWS if (Path(r.path) / name).is_file()],
        "notes": notes,
    }


def stage_table(records: list[Record], columns: tuple[str, ...], seconds: bool = True) -> str:
    """One row per stage (in graph order): how many items had each status and (run) the seconds they ran."""
    stages: dict[str, dict[str, float]] = {}
    for record in records:
        row = stages.setdefault(record.stage, {"items": 0, "seconds": 0.0, **{c: 0 for c in columns}})
        row["items"] += 1
        row["seconds"] += record.seconds
        if record.status in row:
            row[record.status] += 1
    header = ("stage", "items", *columns) + (("seconds",) if seconds else ())
    rows = [header] + [(stage, str(row["items"]), *(str(row[c]) for c in columns))
                       + ((f"{row['seconds']:.1f}",) if seconds else ()) for stage, row in stages.items()]
    widths = [max(len(row[i]) for row in rows) for i in range(len(header))]
    aligned = [[row[0].ljust(widths[0])] + [cell.rjust(w) for cell, w in zip(row[1:], widths[1:])] for row in rows]
    return "\n".join("  ".join(row) for row in aligned)


def _section(title: str, lines: list[str], more_in: Path) -> list[str]:
    """A titled list, cut to SHOWN lines (the rest is in `more_in`)."""
    if not lines:
        return []
    shown = [f"  {line}" for line in lines[:SHOWN]]
    if len(lines) > SHOWN:
        shown.append(f"  ... {len(lines) - SHOWN} more in {more_in}")
    return [f"{title} ({len(lines)}):", *shown]


def _left_out_lines(left_out: Mapping[str, Mapping[str, str]]) -> list[str]:
    return [f"{label} without {group}: {why}" for label, groups in left_out.items() for group, why in groups.items()]


def run_report(summary: dict, records: list[Record], summary_path: Path) -> str:
    """The short report printed at the end of a run."""
    lines = [stage_table(records, RUN_COLUMNS), ""]
    for item, metrics in summary["eval"].items():
        lines.append(f"{item}: box AP {metrics['bbox']['AP']:.1f} (AP50 {metrics['bbox']['AP50']:.1f})  "
                     f"mask AP {format_ap(metrics['segm']['AP'])}")
    lines += summary["notes"]
    lines += _section("failed", summary["failed"], summary_path)  # the readers of bad input files among them
    lines += _section("left out", _left_out_lines(summary["left_out"]), summary_path)
    lines += _section("warnings", summary["warnings"], summary_path)
    lines += _section("previews", summary["previews"], summary_path)
    lines.append(f"summary: {summary_path}")
    return "\n".join(lines)


def plan_report(records: list[Record], problems: Mapping[Path, str], notes: list[str], plan_path: Path) -> str:
    """The short report of run.action=plan."""
    lines = [stage_table(records, PLAN_COLUMNS, seconds=False), "", *notes]
    lines += _section("input problems", list(problems.values()), plan_path)
    lines += _section("would run without", _left_out_lines({r.label: r.left_out for r in records if r.left_out}),
                      plan_path)
    lines.append(f"plan: {plan_path}")
    return "\n".join(lines)
