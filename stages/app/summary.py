"""The end of a run or plan: summary.json (every node's outcome, the eval metrics, input problems, warnings and
what was left out) and the short report printed on screen (per stage, items by status and their seconds;
the eval results; the items with nothing to compute, e.g. frame slots a video could not fill, as information, never
as failures; where the summary and previews are). The full table stays in summary.json / plan.json.
"""
from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import Mapping

from omegaconf import DictConfig, OmegaConf

from stages.engine.cache_entry import MANIFEST, METRICS, Outcome, read_manifest
from stages.engine.graph import Node, Ref
from stages.lib.coco import format_ap

RUN_COLUMNS = ("ran", "cached", "empty", "failed", "blocked")
PLAN_COLUMNS = ("cached", "would-run", "empty", "bad-input", "blocked")
PREVIEWS = ("preview.png", "card.md", "predictions.png")  # a dataset's preview and card; eval's predictions
PREVIEW_STAGES = ("dataset", "eval")  # (a dataset's shards have previews of their own first images too)
KEPT_METRICS = ("bg_frames",)  # the summary keeps their first node's metrics.json (small; read from archives)
SHOWN = 10  # lines of each list the report shows; the rest is in the JSON file


def _origin(value: "Node | Ref | Path") -> str:
    """Where a raw input comes from: "sample" (an output of the sample stage) or its path."""
    return "sample" if isinstance(value, (Node, Ref)) else str(value)


def _video_origin(node: Node) -> str:
    """Where a bg_frames node's frame slots come from: "frames of the sample's walk" or "frames of <video>"."""
    video = node.inputs["video"]
    source = "the sample's walk" if isinstance(video, (Node, Ref)) else str(video)
    return f"frames of {source}"


def data_line(nodes: Mapping[str, list[Node]]) -> str:
    """One line on the data a graph ({stage: nodes}) uses: its objects, its background photos by source (the
    user's folders and videos, the sample's photos and walk) and its test sets, each with where it comes from."""
    objects = [f"{n.item} ({_origin(n.inputs['video'])})" for n in nodes.get("frames", [])]
    objects += [f"{n.item} (model {_origin(n.inputs['model'])})" for n in nodes.get("extract", [])
                if "model" in n.inputs]
    photos = {_video_origin(node): 0 for node in nodes.get("bg_frames", [])}  # a video that gives no slot shows 0
    for node in nodes.get("bg_depth", []):
        image = node.inputs["image"]
        origin = (_video_origin(image.node) if isinstance(image, Ref) and image.node.stage.name == "bg_frames" else
                  "of the sample" if isinstance(image, Ref) else f"from {Path(image).parent}")
        photos[origin] = photos.get(origin, 0) + 1
    tests = dict.fromkeys(f"{n.item.partition('@')[2]} ({_origin(n.inputs['testset'])})" for n in nodes.get("eval", []))
    count = sum(photos.values())
    return (f"data: {len(objects)} object{'s' * (len(objects) != 1)}: {', '.join(objects) or 'none'}; "
            f"{count} background photo{'s' * (count != 1)}: "
            f"{', '.join(f'{count} {origin}' for origin, count in photos.items()) or 'none'}; "
            f"test sets: {', '.join(tests) or 'none'}")


def summarise(outcomes: list[Outcome], cfg: DictConfig, problems: Mapping[Path, str], notes: list[str]) -> dict:
    """The run summary: one row per node, the eval metrics of this configuration, input problems, warnings
    (of cached nodes too, from their manifests), what each node ran without, previews and notes."""
    evals, stage_seconds, rows = {}, {}, [asdict(outcome) for outcome in outcomes]
    for outcome in outcomes:
        if outcome.stage == "eval" and outcome.status in ("ran", "cached"):
            evals[outcome.item] = json.loads((Path(outcome.path) / METRICS).read_text())
        if outcome.path and outcome.status in ("ran", "cached") and (Path(outcome.path) / MANIFEST).is_file():
            seconds = read_manifest(outcome.path).get("seconds", 0.0)
            stage_seconds[outcome.stage] = stage_seconds.get(outcome.stage, 0.0) + seconds
    return {
        "variant": OmegaConf.to_container(cfg.variant, resolve=True, enum_to_str=True),
        "config": OmegaConf.to_container(cfg, resolve=True, enum_to_str=True),
        "outcomes": rows,
        "eval": evals,
        "compute_seconds_by_stage": stage_seconds,
        "failed": [f"{r.label}: {r.error}" for r in outcomes if r.status == "failed"],
        "empty": {r.label: r.error for r in outcomes if r.status == "empty"},
        "distrusted": distrusted_lines(outcomes),
        "input_problems": {str(path): message for path, message in problems.items()},
        "warnings": [f"{r.label}: {warning}" for r in outcomes for warning in r.warnings],
        "left_out": {r.label: r.left_out for r in outcomes if r.left_out},
        "previews": [str(Path(r.path) / name) for r in outcomes
                     if r.path and r.status in ("ran", "cached") and r.stage in PREVIEW_STAGES
                     for name in PREVIEWS if (Path(r.path) / name).is_file()],
        "notes": notes,
        "depth_sources": depth_sources(outcomes),
        "photos_without_plane": photos_without_plane(outcomes),
        "stage_metrics": {stage: metrics for stage in KEPT_METRICS  # read back from archives once the cache is gone
                          if (metrics := stage_metrics({"outcomes": rows}, stage)) is not None},
    }


def summary_outcomes(summary: dict) -> list[dict]:
    """The node rows of a summary.json as `summarise` writes them ("records" in summaries before 2026-11-28)."""
    return summary.get("outcomes", summary.get("records", []))


def stage_metrics(summary: dict, stage: str) -> dict | None:
    """The metrics.json of a job's first `stage` node that ran or came from the cache: the summary's own copy (for the
    KEPT_METRICS stages), else the cache entry's (None when there is none or the entry is gone)."""
    if stage in summary.get("stage_metrics", {}):
        return summary["stage_metrics"][stage]
    for outcome in summary_outcomes(summary):
        path = Path(outcome.get("path") or "/") / METRICS
        if outcome.get("stage") == stage and outcome.get("status") in ("ran", "cached") and path.is_file():
            return json.loads(path.read_text())
    return None


def distrusted_lines(outcomes: list[Outcome]) -> list[str]:
    """One line per node whose cache entry was not trusted (a file missing or of another size than its manifest
    outcomes: stages/engine/cache_entry.py), naming the entry and the file."""
    return [f"{r.label}: {r.distrusted}" for r in outcomes if r.distrusted]


def photos_without_plane(outcomes: list[Outcome]) -> dict[str, dict]:
    """{generator of a dataset ("compose[full]"): {"photos", "without_plane": {id: why}, "expected": [ids]}} from
    compose's metrics (each shard's gives the same): the photos `placement: plane` could not use, and which of them
    were made without a horizontal surface."""
    found = {}
    for outcome in outcomes:
        path = Path(outcome.path) / METRICS
        if outcome.stage == "compose" and outcome.status in ("ran", "cached") and path.is_file():
            metrics = json.loads(path.read_text())
            if metrics.get("photos_without_plane"):  # the same for every shard of a dataset: said once
                dataset = f"{outcome.stage}[{outcome.item.partition('#')[0]}]"
                found[dataset] = {"photos": metrics.get("photos"), "without_plane": metrics["photos_without_plane"],
                                  "expected": metrics.get("expected_without_plane", [])}
    return found


def plane_lines(without_plane: Mapping[str, Mapping]) -> list[str]:
    """One line per generator: how many photos have no placement plane, the expected ones counted, the others
    named with why."""
    lines = []
    for label, found in without_plane.items():
        others = {bg_id: why for bg_id, why in found["without_plane"].items() if bg_id not in found["expected"]}
        parts = ([f"{len(found['expected'])} of the sample, views without a floor (expected)"] if found["expected"]
                 else []) + ([f"{len(others)} not: " + ", ".join(f"{k} ({v})" for k, v in others.items())]
                             if others else [])
        lines.append(f"{label}: {len(found['without_plane'])} of {found['photos']} photos have no placement plane: "
                     + "; ".join(parts))
    return lines


def depth_sources(outcomes: list[Outcome]) -> dict[str, int]:
    """{where a photo's depth came from: how many photos} over the bg_depth nodes that ran or were cached: "sidecar
    <encoding>", "model <name> (<repo>@<revision>)" or "model <path>", "none" (bg_depth's metrics)."""
    sources: dict[str, int] = {}
    for outcome in outcomes:
        path = Path(outcome.path) / METRICS
        if outcome.stage == "bg_depth" and outcome.status in ("ran", "cached") and path.is_file():
            metrics = json.loads(path.read_text())
            source = {"sidecar": f"sidecar {metrics.get('sidecar_format')}",
                      "model": f"model {metrics.get('model')}"}.get(metrics["provider"], metrics["provider"])
            sources[source] = sources.get(source, 0) + 1
    return sources


def wall_seconds(outcomes: list[Outcome]) -> float:
    """Seconds from the first of these nodes starting to the last one ending (0 when none ran here)."""
    ran = [r for r in outcomes if r.started > 0]
    return max(r.started + r.seconds for r in ran) - min(r.started for r in ran) if ran else 0.0


def stage_table(outcomes: list[Outcome], columns: tuple[str, ...], seconds: bool = True) -> str:
    """One row per stage (in graph order): how many items had each status and (run) the seconds they took:
    `work s`, summed over the nodes (nodes side by side add up), and `wall s`, from the stage's first node
    starting to its last one ending; a last row `all` gives both for the whole run."""
    by_stage: dict[str, list[Outcome]] = {}
    for outcome in outcomes:
        by_stage.setdefault(outcome.stage, []).append(outcome)
    header = ("stage", "items", *columns) + (("work s", "wall s") if seconds else ())
    groups = list(by_stage.items()) + ([("all", outcomes)] if seconds else [])
    rows = [header]
    for stage, group in groups:
        counts = [str(sum(r.status == c for r in group)) for c in columns]
        times = (f"{sum(r.seconds for r in group):.1f}", f"{wall_seconds(group):.1f}") if seconds else ()
        rows.append((stage, str(len(group)), *counts, *times))
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


def _left_out_lines(left_out: Mapping[str, Mapping[str, str]], empty: Mapping[str, str]) -> list[str]:
    """One line per group a node ran without, but those left out because a node of `empty` ({label: why}) had
    nothing to compute (empty_lines says so once)."""
    quiet = tuple(f"{label} empty" for label in empty)
    return [f"{label} without {group}: {why}" for label, groups in left_out.items() for group, why in groups.items()
            if not why.startswith(quiet)]


def empty_lines(empty: Mapping[str, str]) -> list[str]:
    """One line per reason that nodes ({label: why}) had nothing to compute (frame slots their video could not
    fill): the items, then why; information, not a failure."""
    items: dict[str, list[str]] = {}
    for label, why in empty.items():
        item = label.partition("[")[2][:-1]
        items.setdefault(why, [])
        if item not in items[why]:
            items[why].append(item)
    return [f"{', '.join(names)}: {why}" for why, names in items.items()]


def run_report(summary: dict, outcomes: list[Outcome], summary_path: Path) -> str:
    """The short report printed at the end of a run."""
    lines = [stage_table(outcomes, RUN_COLUMNS), ""]
    for item, metrics in summary["eval"].items():
        lines.append(f"{item}: box AP {metrics['bbox']['AP']:.1f} (AP50 {metrics['bbox']['AP50']:.1f})  "
                     f"mask AP {format_ap(metrics['segm']['AP'])}")
    lines += summary["notes"]
    if summary["depth_sources"]:
        sources = summary["depth_sources"].items()
        lines.append("photo depth: " + ", ".join(f"{count} from {source}" for source, count in sources))
    lines += plane_lines(summary["photos_without_plane"])
    lines += _section("empty, nothing to compute", empty_lines(summary["empty"]), summary_path)
    lines += _section("failed", summary["failed"], summary_path)  # the readers of bad input files among them
    lines += _section("cache entries not trusted, computed again", summary["distrusted"], summary_path)
    lines += _section("left out", _left_out_lines(summary["left_out"], summary["empty"]), summary_path)
    lines += _section("warnings", summary["warnings"], summary_path)
    lines += _section("previews", summary["previews"], summary_path)
    lines.append(f"summary: {summary_path}")
    return "\n".join(lines)


def plan_report(outcomes: list[Outcome], problems: Mapping[Path, str], notes: list[str], plan_path: Path,
                data: str = "") -> str:
    """The short report of run.action=plan, after the `data` line (data_line) when given."""
    lines = [data] if data else []
    empty = {r.label: r.error for r in outcomes if r.status == "empty"}  # known from the cache
    lines += [stage_table(outcomes, PLAN_COLUMNS, seconds=False), "", *notes]
    lines += _section("empty, nothing to compute", empty_lines(empty), plan_path)
    lines += _section("input problems", list(problems.values()), plan_path)
    lines += _section("cache entries not trusted, would run again", distrusted_lines(outcomes), plan_path)
    lines += _section("would run without", _left_out_lines({r.label: r.left_out for r in outcomes if r.left_out},
                                                           empty), plan_path)
    lines.append(f"plan: {plan_path}")
    return "\n".join(lines)
