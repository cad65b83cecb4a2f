"""Stress cases of issue 9 (`+experiment=stability`): what the real stages do with bad captures.

Cases (inputs built by tests/factories/: the orbit renderer, the procedural splat scene, the stress
backgrounds and the stage chains that tests/test_stress_cases.py runs small):
  1 few frames        orbit videos with fewer / barely enough frames -> frames (+ sfm)
  2 blurred video     the orbit Gaussian-blurred (cv2.GaussianBlur) -> frames + sfm, beside the sharp one
  3 plain white floor splat scenes whose floor is white with few (or no) Gaussians -> extract
  4 no horizontal     a room corner (walls only, sidecar depth) -> bg_depth + planes + compose
  5 missing depth     no sidecar, bg_depth.model=none -> bg_depth provider "none" -> planes + compose
  6 SfM failure       two objects (orbit, noise video) in one Engine run of frames -> sfm nodes
  6b missing video    the same run with one object's video path missing

Each row says what happened: a clear error (StageError, quoted), a fallback (which), a result (its
figures), or a crash (any other exception: a stage defect). Usage (repository root):
  OMP_NUM_THREADS=1 python -m benchmarks.stability [--quick] [--json PATH] [--table PATH]
Prints the JSON rows; --table writes the markdown table.
"""
from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from benchmarks.lib.evaluation import score
from stages.contract.errors import StageError
from stages.extract import run as extract
from stages.frames import run as frames
from stages.lib.gaussians.ply import read_ply
from stages.lib.objects.pointcloud import nearest_distance
from stages.records.frames import FramesRecord
from stages.sfm import run as sfm
from tests.factories.backgrounds import write_background
from tests.factories.media import blurred_copy, noise_video
from tests.factories.orbits import render_orbit_video
from tests.factories.runs import depth_planes_compose, frames_sfm_run, stage_ctx
from tests.factories.splats import synthetic_scene, write_splat_folder

log = logging.getLogger("stability")


@dataclass
class Settings:
    """Input sizes of one benchmark run (full or --quick)."""

    width: int
    height: int
    orbit_frames: int
    few_frame_counts: tuple[int, ...]
    blur_sigmas: tuple[float, ...]
    floor_points: tuple[int, ...]
    compose_images: int
    noise_frames: int


FULL = Settings(320, 240, 36, (5, 8, 12, 18), (3.0, 6.0), (300, 50, 0), 12, 24)
QUICK = Settings(240, 180, 36, (5, 12), (3.0,), (300,), 4, 10)
SFM_PARAMS = {"num_threads": 1}  # SfmConfig defaults otherwise (robust fallback on), single-threaded


@dataclass
class Row:
    """One line of the table."""

    case: str
    input: str
    outcome: str  # "clear error" | "fallback" | "result" | "crash"
    detail: str
    seconds: float
    figures: dict


def attempt(case: str, description: str, body: Callable[[], tuple[str, str, dict]]) -> Row:
    """Run one case; a StageError is a clear error, any other exception a crash (a stage defect)."""
    start = time.perf_counter()
    try:
        outcome, detail, figures = body()
    except StageError as error:
        outcome, detail, figures = "clear error", f"StageError: {error}", {}
    except Exception as error:  # noqa: BLE001 - the point is to record unclear failures, not hide them
        outcome, detail, figures = "crash", f"{type(error).__name__}: {error}", {}
    row = Row(case, description, outcome, detail, round(time.perf_counter() - start, 2), figures)
    log.info("%s | %s | %s | %s", case, description, outcome, detail)
    return row


def sfm_summary(metrics: dict) -> tuple[str, dict]:
    """A one-line description and the figures of an sfm metrics dict."""
    figures = {"registered": metrics["registered"], "total": metrics["total"],
               "registered_ratio": round(metrics["registered_ratio"], 3),
               "reprojection_error_px": round(metrics["mean_reprojection_error_px"], 3),
               "points": metrics["points"], "robust": metrics["robust"]}
    text = (f"{figures['registered']}/{figures['total']} registered, reprojection "
            f"{figures['reprojection_error_px']:.2f} px, {figures['points']} points"
            + (" (robust fallback model)" if figures["robust"] else ""))
    return text, figures


def frames_then_sfm(video: Path, work: Path, frames_params: dict) -> tuple[str, str, dict]:
    """frames + sfm on one video; (outcome, detail, figures). StageErrors propagate."""
    frames_metrics = frames.run(stage_ctx("frames", {"video": video}, work / "frames", frames_params))
    sharpness = float(np.mean([entry.sharpness for entry in FramesRecord.read(work / "frames").frames]))
    try:
        metrics = sfm.run(stage_ctx("sfm", {"frames": work / "frames"}, work / "sfm", SFM_PARAMS))
    except StageError as error:
        return "clear error", (f"frames kept {frames_metrics['frames']} (mean sharpness {sharpness:.0f}); "
                               f"StageError: {error}"), {"frames": frames_metrics["frames"], "sharpness": sharpness}
    text, figures = sfm_summary(metrics)
    return "result", f"frames kept {frames_metrics['frames']} (mean sharpness {sharpness:.0f}); sfm: {text}", \
        {"frames": frames_metrics["frames"], "sharpness": round(sharpness, 1), **figures}


def case_few_frames(work: Path, settings: Settings) -> list[Row]:
    """1: orbit captures with few frames through frames (+ sfm when frames accepts them)."""
    rows = []
    for count in settings.few_frame_counts:
        video = work / f"orbit_{count}_frames.mp4"
        render_orbit_video(video, count, settings.width, settings.height)
        rows.append(attempt("1 few frames", f"{count}-frame orbit ({360 // count} deg steps), "
                            f"{settings.width}x{settings.height}",
                            lambda v=video, c=count: frames_then_sfm(v, work / f"few_{c}", {})))
    return rows


def case_blurred(work: Path, settings: Settings) -> list[Row]:
    """2: the orbit, sharp and Gaussian-blurred, through frames + sfm."""
    sharp = work / "orbit.mp4"
    render_orbit_video(sharp, settings.orbit_frames, settings.width, settings.height)
    params: dict = {}
    size = f"{settings.orbit_frames}-frame orbit, {settings.width}x{settings.height}"
    rows = [attempt("2 blurred video", f"reference: sharp {size}",
                    lambda: frames_then_sfm(sharp, work / "sharp", params))]
    for sigma in settings.blur_sigmas:
        blurred = blurred_copy(sharp, work / f"blur_{sigma:g}.mp4", sigma)
        rows.append(attempt("2 blurred video", f"{size}, GaussianBlur sigma {sigma:g}",
                            lambda v=blurred, s=sigma: frames_then_sfm(v, work / f"blurred_{s:g}", params)))
    return rows


def white_floor_scene(floor_points: int, seed: int):
    """The procedural splat scene (tests/factories/splats.py) with `floor_points` floor Gaussians, all white."""
    scene = synthetic_scene(seed, floor_points=floor_points)
    scene.colors[:floor_points] = 1.0                        # the floor Gaussians come first
    return scene


def extract_scene(work: Path, name: str, scene) -> tuple[str, str, dict]:
    """extract.run on a procedural splat scene; scored against its true object Gaussians."""
    splat, out = work / f"splat_{name}", work / f"extract_{name}"
    write_splat_folder(splat, scene)
    metrics = extract.run(stage_ctx("extract", {"splat": splat}, out))
    kept = nearest_distance(scene.means, read_ply(out / "object.ply").means.numpy()) == 0   # [N]
    figures = {**score(kept, scene.is_object), "plane_source": metrics["plane_source"],
               "height_error_rel": round(abs(metrics["height"] - scene.height) / scene.height, 4)}
    detail = (f"plane source {figures['plane_source']}; precision {figures['precision']:.3f}, recall "
              f"{figures['recall']:.3f}, height error {100 * figures['height_error_rel']:.1f} %")
    return ("fallback" if metrics["plane_source"] != "ransac" else "result"), detail, figures


def case_white_floor(work: Path, settings: Settings) -> list[Row]:
    """3: extract on scenes whose plain white floor got few Gaussians, beside a textured floor."""
    rows = [attempt("3 plain white floor", "reference: textured floor, 20000 floor Gaussians, 4000 object",
                    lambda: extract_scene(work, "textured", synthetic_scene(1)))]
    for count in settings.floor_points:
        rows.append(attempt("3 plain white floor", f"white floor, {count} floor Gaussians, 4000 object",
                            lambda c=count: extract_scene(work, f"white_{c}", white_floor_scene(c, seed=1))))
    return rows


def placement_outcome(result: dict) -> tuple[str, str, dict]:
    """(outcome, detail, figures) of a bg_depth -> planes -> compose run."""
    stats = result["stats_json"]
    figures = {"provider": result["bg_depth"]["provider"], "planes": result["planes"]["planes"],
               "patches": result["planes"]["patches"], "placement": stats["placement"],
               "random_placement_fallbacks": stats["random_placement_fallbacks"],
               "instances": stats["instances"], "images": stats["images"]}
    fallbacks = ", ".join(f"{reason!r} x{count}" for reason, count in stats["random_placement_fallbacks"].items())
    detail = (f"bg_depth provider {figures['provider']!r}; planes: {figures['planes']} planes "
              f"({figures['patches']} patches); compose: placement {stats['placement']}, fallbacks {fallbacks or 'none'}, "
              f"{stats['instances']} instances in {stats['images']} images")
    return ("fallback" if stats["random_placement_fallbacks"] else "result"), detail, figures


def case_placement(work: Path, settings: Settings) -> list[Row]:
    """4 and 5: a walls-only photo (sidecar depth) and a photo without any depth, through compose."""
    size = f"{settings.width}x{settings.height}"
    corner = write_background(work / "photos_corner", "corner", settings.width, settings.height, with_wall_depth=True)
    plain = write_background(work / "photos_plain", "plain", settings.width, settings.height, with_wall_depth=False)
    return [
        attempt("4 no horizontal surfaces", f"room corner (two walls, sidecar depth), {size}",
                lambda: placement_outcome(depth_planes_compose(work / "corner", corner, settings.compose_images))),
        attempt("5 missing depth", f"photo without depth sidecar, provider auto, model none, {size}",
                lambda: placement_outcome(depth_planes_compose(work / "nodepth", plain, settings.compose_images))),
    ]


def engine_outcome(work: Path, settings: Settings) -> tuple[str, str, dict]:
    """6: frames -> sfm for an orbit and a noise video in one Engine run; per-node statuses."""
    work.mkdir(parents=True, exist_ok=True)
    orbit = work / "good_orbit.mp4"
    render_orbit_video(orbit, settings.orbit_frames, settings.width, settings.height)
    noise = noise_video(work / "noise_capture.mp4", settings.noise_frames, settings.width, settings.height)
    records = frames_sfm_run(work / "cache", {"good": orbit, "bad": noise},
                             {"duplicate_threshold": 0}, SFM_PARAMS)
    statuses = {f"{r.stage}[{r.item}]": r.status for r in records}
    failures = [f"{r.stage}[{r.item}]: {r.error}" for r in records if r.status in ("failed", "blocked")]
    good = next((r for r in records if r.stage == "sfm" and r.item == "good" and r.status == "ran"), None)
    detail = "; ".join(f"{label} {status}" for label, status in statuses.items())
    figures: dict = {"statuses": statuses, "errors": failures}
    if good is not None:
        text, sfm_figures = sfm_summary(json.loads((Path(good.path) / "sfm.json").read_text()))
        detail += f"; sfm[good]: {text}"
        figures["good"] = sfm_figures
    detail += "".join(f"; FAILED {failure}" for failure in failures)
    outcome = "clear error (others continue)" if failures and good is not None else "result"
    return outcome, detail, figures


def missing_video_outcome(work: Path, settings: Settings) -> tuple[str, str, dict]:
    """6b: the same Engine run where one object's video path does not exist: what the run returns
    or raises, and which nodes reached the cache."""
    work.mkdir(parents=True, exist_ok=True)
    orbit = work / "good_orbit.mp4"
    render_orbit_video(orbit, settings.orbit_frames, settings.width, settings.height)
    try:
        records = frames_sfm_run(work / "cache", {"good": orbit, "bad": work / "missing_capture.mp4"},
                                 {}, SFM_PARAMS)
        raised = None
    except StageError as error:
        records, raised = [], error
    cached = sorted(f"{manifest.parent.parent.name}[{json.loads(manifest.read_text())['item']}]"
                    for manifest in (work / "cache").glob("*/*/manifest.json"))
    statuses = {f"{r.stage}[{r.item}]": r.status for r in records}
    if raised is None:
        return "result", "; ".join(f"{label} {status}" for label, status in statuses.items()), {"statuses": statuses}
    return ("clear error (run aborted)", f"Engine.run raised StageError: {raised}; no records returned; "
            f"cached before the abort: {', '.join(cached) or 'nothing'}", {"cached": cached})


def case_sfm_failure(work: Path, settings: Settings) -> list[Row]:
    """6: one object of two fails SfM in an Engine run (and, 6b, one object's video is missing)."""
    size = f"{settings.width}x{settings.height}, Engine(strict=False)"
    return [attempt("6 object fails SfM", f"objects good ({settings.orbit_frames}-frame orbit) + bad "
                    f"({settings.noise_frames} noise frames), {size}", lambda: engine_outcome(work / "engine", settings)),
            attempt("6b object video missing", f"objects good ({settings.orbit_frames}-frame orbit) + bad (video path "
                    f"does not exist), {size}", lambda: missing_video_outcome(work / "missing", settings))]


CASES = (case_few_frames, case_blurred, case_white_floor, case_placement, case_sfm_failure)


def markdown_table(rows: list[Row]) -> str:
    """The table: case | input | outcome | what happened | seconds."""
    lines = ["| case | input | outcome | what happened | s |", "|---|---|---|---|---|"]
    for row in rows:
        detail = row.detail.replace("|", "\\|").replace("\n", " ")
        lines.append(f"| {row.case} | {row.input} | **{row.outcome}** | {detail} | {row.seconds:.1f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    """Command line: see the module docstring."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="smaller inputs and fewer variants")
    parser.add_argument("--json", type=Path, help="also write the rows as JSON here")
    parser.add_argument("--table", type=Path, help="write the markdown table here")
    parser.add_argument("--work", type=Path, help="keep the inputs and outputs in this folder (default: temp)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    settings = QUICK if args.quick else FULL
    with tempfile.TemporaryDirectory(prefix="stability_") as temp:
        work = args.work or Path(temp)
        rows = []
        for case in CASES:
            folder = work / case.__name__
            folder.mkdir(parents=True, exist_ok=True)
            rows.extend(case(folder, settings))
    payload = [asdict(row) for row in rows]
    print(json.dumps(payload, indent=1, default=str))
    if args.json:
        args.json.write_text(json.dumps(payload, indent=1, default=str))
    table = markdown_table(rows)
    if args.table:
        args.table.write_text(table)
    print(table)


if __name__ == "__main__":
    main()
