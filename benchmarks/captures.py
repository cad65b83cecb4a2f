"""Capture benchmark: the capture stages (frames -> sfm -> splat_train -> extract) with their defaults on other
renders of the embedded sample, scored against the sample's ground truth.

    python -m benchmarks.captures --seeds 2 3 4 5 6 [--cache outputs/cache] [--workers 2] [--until sfm] [--recut]
    python -m benchmarks.captures --rescore benchmarks/results/captures/captures.json --cache CACHE

Each seed is a `sample` render of the five objects (and one background photo, no test photos), run through the engine
up to extract with the defaults (cached nodes are reused, so a rerun after an extract change only reruns extract;
--recut scores this checkout's extract on the splats the cache already holds for each seed's SfM, whichever checkout
trained them, and trains none; --rescore does the same for the splats an earlier captures.json names, found by their
entries' manifests, with no engine: a change to a stage before extract re-keys the seeds' entries, and their splats
still serve). Per capture: SfM frames registered at the first attempt and in the end, whether the
robust retry ran, SfM seconds, its points in all and in splat_train's seed ball (the JSON; their range in the
report with --until sfm); the splat's held-out PSNR; extract against the ground truth (precision and recall of
the kept Gaussians, mask IoU with the visible masks at the held-out capture cameras, where clutter hides no part of
the object, in the views that show at least 10 % of it, as BOP scores; and the same IoU of the ground truth's own
cut of the splat: the Gaussians within 1 cm of the object's surface, inside it or in its cavity, above what it
stands on, a rug included: benchmarks/lib/truth_views.py and cut_scoring.object_membership), support-plane source)
or the reason it refused. The report counts apart the misses handed on that their splats limit, and those short of
precision only inside the object's visual hull (`meets`).
Writes benchmarks/results/captures.md (table, targets) and captures/captures.json (with --until sfm:
captures/captures_sfm.md and .json), and copies each capture's filtering panel into benchmarks/results/captures/ (of a
refusal: the cut with its checks off); the earlier runs are told in captures/history.md.
"""
from __future__ import annotations

import argparse
import json
import logging
import shutil
import time
from pathlib import Path

import numpy as np

from benchmarks.lib.cut_scoring import CUT_TARGETS, bench_trained, draw_cut_panel, splat_chain
from stages.app.pipeline import build_graph
from stages.contract.errors import StageError
from stages.engine.cache_keys import derive_seed
from stages.engine.scheduler import Engine
from stages.extract.spec import ExtractConfig
from stages.records import sample_layout
from stages.records.sfm import SfmRecord
from stages.splat_train.run import object_ball, points_in_ball
from stages.splat_train.spec import SplatTrainConfig
from tests.factories.configs import ROOT, compose_cfg

log = logging.getLogger("benchmarks.captures")
RESULTS = Path(__file__).resolve().parent / "results"
OBJECTS_ONLY = ["sample.num_backgrounds=1", "sample.num_indomain=0", "sample.num_test=0", "data.test_sets=[]",
                "run.until=extract"]
TARGETS = {**CUT_TARGETS, "first_attempt_ratio": 0.95}
WRONG_CUT = {"precision": 0.80, "mask_iou_min": 0.5}  # a cut handed on below either is a silent wrong cut
SPLAT_LIMIT = 0.01  # a miss with its worst IoU within this of the ground truth's own cut of the splat: the splat's
HULL_SHARE = 0.9  # a precision miss with this share of its false positives in every view's mask: the visual hull's
SELF_CHECK = ("view_share", "look_at_gap", "footprint", "wall_share", "kept_share",
              "candidate")  # extract.json's figures


def sfm_figures(folder: Path) -> dict:
    """Frames registered at the first attempt and in the end, the retry, the seconds, and the points of an sfm folder
    (all of them, and those in splat_train's seed ball: seed_ball_points)."""
    record = SfmRecord.read(folder)
    summary = record.summary
    return {"frames": summary["total"], "registered": summary["registered"],
            "first_attempt": summary["attempts"][0]["registered"], "retried": len(summary["attempts"]) > 1,
            "sfm_seconds": round(sum(summary["seconds"].values()), 1), **seed_ball_points(record)}


def seed_ball_points(record: SfmRecord) -> dict[str, int]:
    """The SfM model's points, and those within splat_train's seed ball: `seed_radius` x the cameras' mean distance
    around the point they look at, where the stage adds its grey seed points for what SfM leaves empty
    (stages/splat_train/run.py; a capture whose SfM already fills the ball gains nothing from them:
    benchmarks/results/opensplat.md)."""
    scene = record.scene()
    viewmats = np.stack([frame.viewmat for frame in scene.frames])  # [V, 4, 4]
    centre, distance = object_ball(viewmats)
    in_ball = 0 if centre is None else points_in_ball(scene.points, centre, SplatTrainConfig.seed_radius * distance)
    return {"sfm_points": int(scene.points.shape[0]), "seed_ball_points": in_ball}


def score_cut(splat: Path, frames: Path, gt_dir: Path, seed: int, panel: Path, extract_panel: Path | None) -> dict:
    """The splat's PSNR and the figures of extract's cut of it (see the module doc), scored with the checks off (a
    refused cut's figures say whether the refusal was right); `seed`: the extract node's own (its RANSAC draws).
    The cut's filtering panel goes to `panel`: a copy of extract's (extract_panel), or drawn here when None."""
    stats = json.loads((splat / "train_stats.json").read_text())
    row: dict = {"psnr": round(float(stats["final_psnr"]), 2)}
    try:
        scores = bench_trained(splat, gt_dir, frames, 0.01, ExtractConfig(), seed, enforce_checks=False)
    except StageError as error:  # an earlier step's refusal: no cut to score
        return {**row, "failed_stage": "extract", "reason": str(error)}
    row.update({key: round(scores[key], 4)
                for key in ("precision", "recall", "mask_iou_mean", "mask_iou_min", "mask_iou_min_true_cut",
                            "support_above_gt_plane_m", "worst_view_missed_under_support", "false_in_visual_hull",
                            "kept_in_cavity", "seconds", "self_check_seconds")},
               plane_source=scores["plane_source"], refused="refused" in scores["checks"],
               held_out_views_hidden=scores["held_out_views_hidden"],
               **{key: scores["checks"][key] if isinstance(scores["checks"][key], str) else
                  round(scores["checks"][key], 4) for key in SELF_CHECK if key in scores["checks"]})
    if row["refused"]:
        row["reason"] = scores["checks"]["refused"]
    if extract_panel is None or row["refused"]:
        draw_cut_panel(splat, panel, ExtractConfig(), seed)
    else:
        shutil.copy(extract_panel, panel)
    return row


def score_capture(nodes: dict, engine: Engine, outcomes: dict, gt_dir: Path, gallery: Path, label: str) -> dict:
    """The figures of one capture (see the module doc); `nodes`: its frames, sfm, splat_train, extract nodes."""
    row: dict = {}
    for stage in ("sfm", "splat_train", "extract"):
        outcome = outcomes[id(nodes[stage])]
        if outcome.status not in ("ran", "cached"):
            row.update(failed_stage=stage, reason=outcome.error)
            break
    else:
        row["extract_ran"] = True
    if outcomes[id(nodes["sfm"])].status in ("ran", "cached"):
        row.update(sfm_figures(engine.output_dir(nodes["sfm"])))
    if outcomes[id(nodes["splat_train"])].status not in ("ran", "cached"):
        return row
    extract = engine.output_dir(nodes["extract"]) / "filtering.png" if row.get("extract_ran") else None
    scores = score_cut(engine.output_dir(nodes["splat_train"]), engine.output_dir(nodes["frames"]), gt_dir,
                       engine.seed(nodes["extract"]), gallery / f"{label}.png", extract)
    return {**scores, **row}  # the engine's failure, where there is one, over the cut's own


def trained_splat(cache: Path, sfm: Path, item: str) -> Path | None:
    """The newest splat_train entry in `cache` trained on the SfM entry `sfm` for `item`, by any checkout (None when
    there is none): --recut scores this checkout's extract on splats an earlier checkout trained."""
    entries = []
    for manifest in (cache / "splat_train").glob("*/manifest.json"):
        recorded = json.loads(manifest.read_text())
        if recorded["item"] == item and recorded["inputs"].get("sfm") == sfm.name:
            entries.append((recorded["finished"], manifest.parent))
    return max(entries)[1] if entries else None


def recut_capture(nodes: dict, engine: Engine, outcomes: dict, gt_dir: Path, gallery: Path, label: str,
                  item: str) -> dict:
    """The figures of one capture (see the module doc) with this checkout's extract on the splat the cache holds for
    its SfM (trained_splat), without training one; `nodes`: its frames, sfm and extract nodes."""
    if outcomes[id(nodes["sfm"])].status not in ("ran", "cached"):
        return {"failed_stage": "sfm", "reason": outcomes[id(nodes["sfm"])].error}
    sfm = engine.output_dir(nodes["sfm"])
    row = sfm_figures(sfm)
    splat = trained_splat(engine.cache_dir, sfm, item)
    if splat is None:
        return {**row, "failed_stage": "splat_train", "reason": f"no splat in {engine.cache_dir} trained on {sfm}: "
                "run the seed without --recut first"}
    return cached_splat_row(splat, sfm, engine.output_dir(nodes["frames"]), gt_dir, engine.seed(nodes["extract"]),
                            gallery / f"{label}.png")


def cached_splat_row(splat: Path, sfm: Path, frames: Path, gt_dir: Path, seed: int, panel: Path) -> dict:
    """A capture's row from its cached sfm and splat entries: SfM's figures, then this checkout's cut of the splat
    scored (score_cut, the panel drawn to `panel`)."""
    scores = score_cut(splat, frames, gt_dir, seed, panel, None)
    return {**sfm_figures(sfm), "splat": splat.name,
            "extract_ran": "failed_stage" not in scores and not scores["refused"], **scores}


def rescore_row(row: dict, cache: Path, gallery: Path) -> dict:
    """The figures of the capture of a row of an earlier captures.json, with this checkout's extract and scoring on
    the splat the row names; a row without a splat (SfM or training failed) as it was."""
    if "splat" not in row:
        return row
    splat, sfm, frames, gt_dir = splat_chain(cache, row["splat"])
    return {"seed": row["seed"], "object": row["object"],
            **cached_splat_row(splat, sfm, frames, gt_dir, derive_seed(0, "extract", row["object"]),
                               gallery / f"seed{row['seed']}_{row['object']}.png")}


def run_seed(seed: int, cache: Path, workers: int, gallery: Path, overrides: list[str],
             until: str = "extract", recut: bool = False) -> list[dict]:
    """Every object of one sample render through the capture stages up to `until` (extract, or sfm alone);
    one row per object. recut: up to sfm, then extract's cut of the cached splats (recut_capture)."""
    cfg = compose_cfg([f"sample.seed={seed}", *OBJECTS_ONLY, *overrides])
    graph = build_graph(cfg, ROOT)
    engine = Engine(cache, global_seed=int(cfg.run.seed), workers=workers)
    started = time.perf_counter()
    targets = graph.targets("sfm" if recut else until)
    outcomes = {id(node): outcome for node, outcome in zip(engine.closure(targets), engine.run(targets))}
    log.info("seed %d: capture stages in %.0f s", seed, time.perf_counter() - started)
    sample_dir = engine.output_dir(graph.nodes["sample"][0])
    rows = []
    for index, spec in enumerate(cfg.data.objects):
        if until == "sfm":
            sfm_node = graph.nodes["sfm"][index]
            outcome = outcomes[id(sfm_node)]
            rows.append({"seed": seed, "object": spec.name, **(sfm_figures(engine.output_dir(sfm_node))
                         if outcome.status in ("ran", "cached") else {"failed_stage": "sfm", "reason": outcome.error})})
            continue
        nodes = {stage: graph.nodes[stage][index] for stage in ("frames", "sfm", "splat_train", "extract")}
        gt_dir = sample_dir / sample_layout.object_folder(spec.name)
        label = f"seed{seed}_{spec.name}"
        rows.append({"seed": seed, "object": spec.name,
                     **(recut_capture(nodes, engine, outcomes, gt_dir, gallery, label, spec.name) if recut else
                        score_capture(nodes, engine, outcomes, gt_dir, gallery, label))})
    return rows


def meets(row: dict) -> dict[str, bool]:
    """Which targets a capture meets: it extracts, its cut is handed on (extract ran and the checks did not refuse
    it), P / R / IoU of a cut handed on, SfM's first attempt registers >= 95 %; whether it is a silent wrong cut
    (handed on below WRONG_CUT) or a refusal of a cut that meets the targets; and of a cut handed on short of the
    targets, whether its splat limits it (its worst IoU within SPLAT_LIMIT of the ground truth's own cut of the
    splat, which misses the target too; P and R met) or only its precision misses, lost to Gaussians inside the
    object's visual hull (HULL_SHARE of its false positives in every view's mask: no image tells them apart)."""
    first = row.get("first_attempt", 0) / max(row.get("frames", 1), 1)
    handed_on = bool(row.get("extract_ran")) and not row.get("refused")
    met = {key: row.get(key, 0.0) >= TARGETS[key] for key in ("precision", "recall", "mask_iou_min")}
    good = all(met.values())
    wrong = any(row.get(key, 0.0) < limit for key, limit in WRONG_CUT.items())
    own_cut = row.get("mask_iou_min_true_cut", 1.0)
    splat_limited = (not met["mask_iou_min"] and own_cut < TARGETS["mask_iou_min"]
                     and row.get("mask_iou_min", 0.0) >= own_cut - SPLAT_LIMIT and met["precision"] and met["recall"])
    hull_only = not met["precision"] and met["recall"] and met["mask_iou_min"] and \
        row.get("false_in_visual_hull", 0.0) >= HULL_SHARE
    return {"extracts": bool(row.get("extract_ran")), "cut": handed_on and good, "refused": not handed_on,
            "silent_wrong_cut": handed_on and wrong, "good_cut_refused": not handed_on and good,
            "splat_limited": handed_on and splat_limited, "hull_precision": handed_on and hull_only,
            "sfm_first_attempt": first >= TARGETS["first_attempt_ratio"]}


def report(rows: list[dict], command: str, until: str = "extract") -> str:
    """captures.md (captures_sfm.md with `until` sfm: the SfM target alone): the table, the targets met and the
    refusals."""
    lines = ["# Capture benchmark: the capture stages with their defaults on other renders of the sample", "",
             f"`{command}`", "",
             "| seed | object | SfM first / final / frames | retry | SfM s | PSNR dB | P | R | IoU mean / min | true cut's "
             "IoU min | plane | on a rug | self-check: views / look-at gap / footprint / wall / cluster | refused |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        lines.append(f"| {row['seed']} | {row['object']} | {row.get('first_attempt', '-')} / {row.get('registered', '-')} "
                     f"/ {row.get('frames', '-')} | {'yes' if row.get('retried') else 'no'} | {row.get('sfm_seconds', '-')} "
                     f"| {row.get('psnr', '-')} | {row.get('precision', '-')} | {row.get('recall', '-')} | "
                     f"{row.get('mask_iou_mean', '-')} / {row.get('mask_iou_min', '-')} | "
                     f"{row.get('mask_iou_min_true_cut', '-')} | {row.get('plane_source', '-')} "
                     f"| {'yes' if row.get('support_above_gt_plane_m', 0.0) > 0.001 else ''} "
                     f"| {' / '.join(str(row.get(key, '-')) for key in SELF_CHECK[:4])} / "
                     f"{row.get('candidate', 0) + 1} | {row.get('reason', '')[:160]} |")
    counts = {key: sum(meets(row)[key] for row in rows) for key in meets({})}
    sfm_line = (f"SfM's first attempt registers >= 95 % of the frames on {counts['sfm_first_attempt']} (target: all "
                "but two).")
    in_ball = [row["seed_ball_points"] for row in rows if "seed_ball_points" in row]
    if in_ball:
        sfm_line += (f" SfM points in splat_train's seed ball: {min(in_ball)}-{max(in_ball)} (median "
                     f"{int(np.median(in_ball))}).")
    shares = [row["self_check_seconds"] / row["seconds"] for row in rows if row.get("seconds")]
    cavities = sum(row.get("kept_in_cavity", 0) > 0 for row in rows)
    hidden = sum(len(row.get("held_out_views_hidden", [])) for row in rows)
    lines += ["", f"Of {len(rows)} captures: " + (sfm_line if until == "sfm" else
              f"{counts['extracts']} extract; {counts['cut']} are handed on with precision >= 0.95, recall >= 0.90 and "
              f"held-out mask IoU >= 0.90 (target: 96 %; {hidden} held-out views showing under 10 % of their "
              f"object not scored, as BOP does); {counts['refused']} refused with a message, "
              f"{counts['good_cut_refused']} of them a cut within those targets; {counts['silent_wrong_cut']} silent "
              "wrong cuts (handed on with precision < 0.80 or worst mask IoU < 0.5; target: none). Of the others "
              f"handed on, {counts['splat_limited']} limited by their splats (the worst IoU within {SPLAT_LIMIT} of "
              f"the ground truth's own cut of the splat, itself under 0.90) and {counts['hull_precision']} short of "
              "precision only inside the object's visual hull (its false positives in every view's mask). Gaussians in "
              "a container's cavity (a vase's, enclosed on every side but the top) render its inside and count as "
              f"object: {cavities} cuts keep some. " + sfm_line +
              (f" The self-check's figures take {100 * max(shares):.1f} % of extract's cut at most (target: 10 %)."
               if shares else ""))]
    return "\n".join(lines) + "\n"


def main() -> None:
    """Command line: see the module docstring."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[2, 3, 4, 5, 6],
                        help="sample renders (issue 60's 125 captures: 2-6 and 100-119)")
    parser.add_argument("--cache", type=Path, default=ROOT / "outputs" / "cache")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--until", choices=("extract", "sfm"), default="extract",
                        help="sfm: SfM alone (its columns; writes captures_sfm.md and .json)")
    parser.add_argument("--recut", action="store_true",
                        help="score this checkout's extract on the splats already in the cache (trained by any "
                             "checkout on each seed's SfM), training none: minutes for 125 captures")
    parser.add_argument("--rescore", type=Path, help="an earlier captures.json: score this checkout's extract on the "
                        "splats its rows name (in --cache), without the engine, so that entries another checkout "
                        "keyed serve (--seeds is ignored)")
    parser.add_argument("--set", nargs="*", default=[], help="config overrides (a quick check; the figures are "
                                                             "the defaults')")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s][%(name)s][%(levelname)s] - %(message)s")
    gallery = args.out / "captures"
    gallery.mkdir(parents=True, exist_ok=True)
    if args.rescore:
        rows = [rescore_row(row, args.cache, gallery) for row in json.loads(args.rescore.read_text())]
    else:
        rows = [row for seed in args.seeds
                for row in run_seed(seed, args.cache, args.workers, gallery, args.set, args.until, args.recut)]
    name = "captures" if args.until == "extract" else "captures_sfm"
    (gallery / f"{name}.json").write_text(json.dumps(rows, indent=1))
    command = "python -m benchmarks.captures " + (f"--rescore {args.rescore} --cache {args.cache}" if args.rescore else
                                                  "--seeds " + " ".join(map(str, args.seeds))) + \
        (f" --until {args.until}" if args.until != "extract" else "") + (" --recut" if args.recut else "") + \
        (" --set " + " ".join(args.set) if args.set else "")
    (args.out / "captures.md" if args.until == "extract" else gallery / f"{name}.md").write_text(
        report(rows, command, args.until))
    print(report(rows, command, args.until))


if __name__ == "__main__":
    main()
