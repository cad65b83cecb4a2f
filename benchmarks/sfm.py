"""Benchmark of frames + sfm: time, registration, and pose accuracy against ground truth.

Usage (from the repository root):
  python -m benchmarks.sfm sample outputs/.../objects/<name> [--known-intrinsics]
      a sample object folder (video.mp4 + gt.json with K and per-frame viewmats)
  python -m benchmarks.sfm synthetic [--frames 60 --width 640 --height 480]
      renders the tests' textured-box orbit (tests/factories/orbits.py) into a sample-like folder first (not timed)
  python -m benchmarks.sfm plush
      ../shared/real/plush_dog/images (no ground truth: registration, reprojection error, time)
Prints one JSON object; --json PATH also writes it.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.lib.evaluation import pose_errors, registered_viewmats
from stages.engine.context import Context
from stages.frames import run as frames
from stages.records.capture_truth import CaptureTruth
from stages.records.frames import FramesRecord
from stages.sfm import run as sfm
from tests.factories.configs import REAL
from tests.factories.orbits import render_orbit_video

PLUSH_DOG = REAL / "plush_dog" / "images"


def run_stage(module, stage: str, inputs: dict, out: Path, params: dict) -> tuple[dict, float]:
    """Run one stage's `run` into `out`; returns (metrics, seconds)."""
    out.mkdir(parents=True)
    start = time.perf_counter()
    metrics = module.run(Context(stage=stage, item="benchmark", params=params, inputs=inputs, out=out, seed=0))
    return metrics, time.perf_counter() - start


def frames_and_sfm(source: Path, work: Path, frames_params: dict, sfm_params: dict) -> dict:
    """frames + sfm on `source`; timing and the stages' metrics."""
    frames_metrics, frames_seconds = run_stage(frames, "frames", {"video": source}, work / "frames", frames_params)
    sfm_metrics, sfm_seconds = run_stage(sfm, "sfm", {"frames": work / "frames"}, work / "sfm", sfm_params)
    return {"source": str(source), "frames_seconds": round(frames_seconds, 2), "sfm_seconds": round(sfm_seconds, 2),
            "total_seconds": round(frames_seconds + sfm_seconds, 2), "frames": frames_metrics,
            "sfm": {k: v for k, v in sfm_metrics.items() if k != "unregistered"}}


def accuracy_against_truth(work: Path, gt: CaptureTruth) -> dict:
    """Rotation / position errors of the registered frames after a similarity alignment to gt.json."""
    source_index = {Path(e.file).name: e.source_index for e in FramesRecord.read(work / "frames").frames}
    estimated = registered_viewmats(work / "sfm")
    names = sorted(estimated)
    return pose_errors(np.stack([estimated[n] for n in names]), np.stack([gt.viewmats[source_index[n]] for n in names]))


def bench_sample(folder: Path, known_intrinsics: bool, work: Path) -> dict:
    """frames + sfm on a sample object folder (video.mp4 + gt.json) with pose accuracy."""
    gt = CaptureTruth.read(folder)
    K = gt.K
    sfm_params = {"intrinsics": [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]} if known_intrinsics else {}
    result = frames_and_sfm(folder / "video.mp4", work, {}, sfm_params)
    result["known_intrinsics"] = known_intrinsics
    result["accuracy"] = accuracy_against_truth(work, gt)
    return result


def write_synthetic_sample(folder: Path, num_frames: int, width: int, height: int) -> Path:
    """Render the test scene's orbit as a sample-like folder (video.mp4 + gt.json)."""
    folder.mkdir(parents=True)
    truth = render_orbit_video(folder / "video.mp4", num_frames, width, height)
    CaptureTruth("boxes", 0.0, truth["K"], width, height, 10.0, dict(enumerate(truth["viewmats"])),
                 np.array([0.0, 0.0, 1.0]), np.zeros(3)).write(folder)
    return folder


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("mode", choices=["sample", "synthetic", "plush"])
    parser.add_argument("folder", nargs="?", type=Path, help="sample object folder (mode sample)")
    parser.add_argument("--known-intrinsics", action="store_true", help="pass gt.json K to sfm")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")

    with tempfile.TemporaryDirectory(prefix="bench_sfm_") as tmp:
        work = Path(tmp)
        if args.mode == "plush":
            if not PLUSH_DOG.is_dir():
                sys.exit(f"{PLUSH_DOG} not present")
            result = frames_and_sfm(PLUSH_DOG, work, {}, {})
        else:
            if args.mode == "synthetic":
                start = time.perf_counter()
                folder = write_synthetic_sample(work / "sample", args.frames, args.width, args.height)
                logging.info("rendered %d frames in %.1f s (not timed)", args.frames, time.perf_counter() - start)
            elif args.folder is None:
                sys.exit("mode sample needs the object folder (with video.mp4 and gt.json)")
            else:
                folder = args.folder
            result = bench_sample(folder, args.known_intrinsics, work / "run")
        result["mode"] = args.mode
    text = json.dumps(result, indent=1)
    print(text)
    if args.json:
        args.json.write_text(text)


if __name__ == "__main__":
    main()
