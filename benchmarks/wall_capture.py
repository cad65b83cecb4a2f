"""Benchmark: an object hung on a wall, with no floor under it, rendered as the sample renders its captures and
run through frames, sfm, splat_train and extract with the defaults: extract must refuse it with a message that
names the object and the check (issue 60).

    python -m benchmarks.wall_capture [--object vase --height-m 0.22] [--seed 2] [--cache /tmp/wall_cache] \
        [--out benchmarks/results/extract/wall_capture.json]

The scene is one of the sample's furnished rooms (stages/lib/sample_scene), the object upright with its back
against a wall and its middle 1.4 m over the floor, nothing under it (hung on a hook, say); 60 frames at 640x480
on a half orbit in front of the wall at the sample's distance (azimuths within 70 degrees of the wall's normal,
elevations of -12 to +12 degrees, as a hand-held camera): no floor in view. The sample's lighting and photo
pipeline. The video goes in as a user's object (`data=folder`), with
the sample's backgrounds folder unused (run.until=extract). Writes the outcome (refused with the message, or
the figures of what extract handed on) to --out and the filtering panel beside it.
"""
from __future__ import annotations

import argparse
import json
import logging
import shutil
import tempfile
from pathlib import Path

import numpy as np

from stages.app.pipeline import build_graph
from stages.lib.geometry import fov_intrinsics, look_at_viewmat
from stages.lib.sample_scene.capture import CAPTURE_HFOV_DEG, capture_rng, orbit_radius
from stages.lib.sample_scene.objects import build_object, footprint_radius
from stages.lib.sample_scene.photo import auto_exposure, develop
from stages.lib.sample_scene.raytrace import TracedScene, render
from stages.lib.sample_scene.rooms import capture_lighting, make_room
from stages.lib.sample_scene.videos import write_mp4
from stages.engine.cache_entry import Outcome, read_manifest
from stages.engine.scheduler import Engine
from tests.factories.configs import compose_cfg

log = logging.getLogger("benchmarks.wall_capture")
RESULTS = Path(__file__).parent / "results"
HANG_HEIGHT_M = 1.4  # the object's axis over the floor


def free_spot_on_wall(obstacles: list[np.ndarray], wall_x: float, half_y: float) -> float:
    """A y on the wall x = wall_x where no furniture (AABBs [2, 3]) stands within 1.2 m of the wall and 0.6 m to
    either side, between 0.6 and 2.2 m over the floor: the object and the cameras in front of it stay clear."""
    for y in np.linspace(0.0, half_y - 0.6, 8).tolist() + np.linspace(0.0, -(half_y - 0.6), 8).tolist():
        region = np.array([[wall_x - 1.2, y - 0.6, 0.6], [wall_x, y + 0.6, 2.2]])
        if not any(np.all(box[0] < region[1]) and np.all(region[0] < box[1]) for box in obstacles):
            return y
    raise ValueError(f"no free spot on the wall x = {wall_x:.2f} of this room: try another --seed")


def wall_capture_frames(name: str, height_m: float, seed: int, width: int = 640, height: int = 480,
                        num_frames: int = 60, supersample: int = 2) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The frames [H, W, 3] uint8 of the wall-hung capture (module docstring) and the object's visible masks
    [H, W] bool."""
    rng = capture_rng(seed, f"{name}/wall")
    K = fov_intrinsics(width, height, CAPTURE_HFOV_DEG)
    room = make_room(rng, clutter=0)
    wall_x = room.half_x  # the inner face of the +x wall
    obj = build_object(name, height_m, seed, label=1)
    radius = footprint_radius(obj)
    base = np.array([wall_x - radius - 0.01, free_spot_on_wall(room.obstacles, wall_x, room.half_y),
                     HANG_HEIGHT_M - height_m / 2])  # its back against the wall, its middle at HANG_HEIGHT_M
    meshes = room.meshes + [m.transformed(np.eye(3), base) for m in obj]
    target = base + np.array([0.0, 0.0, 0.45 * height_m])
    distance = orbit_radius(height_m, radius, K[1, 1], height)  # as the sample films its objects
    lighting = capture_lighting(room, rng)
    traced = TracedScene(meshes)
    frames, masks, exposure = [], [], None
    for k in range(num_frames):
        azimuth = np.pi + np.radians(70.0) * np.sin(np.pi * (k / (num_frames - 1) - 0.5))  # facing the wall
        elevation = np.radians(12.0 * np.sin(4 * np.pi * k / num_frames))
        eye = target + distance * np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                                            np.sin(elevation)])
        view = render(traced, lighting, K, look_at_viewmat(eye, target), width, height, supersample)
        exposure = auto_exposure(view.radiance) if exposure is None else exposure
        frames.append(develop(view.radiance, exposure))
        masks.append(view.label == 1)
    return frames, masks


def compute_seconds(outcome: Outcome) -> float:
    """A node's own compute seconds: its manifest's when it was cached (a cached outcome took no time now)."""
    manifest = Path(outcome.path) / "manifest.json"
    return read_manifest(Path(outcome.path))["seconds"] if manifest.is_file() else outcome.seconds


def run_chain(video: Path, name: str, height_m: float, backgrounds: Path, cache: Path) -> dict:
    """frames -> sfm -> splat_train -> extract of the video as a user's object; the extract node's outcome."""
    cfg = compose_cfg(["data=folder", f"data.objects=[{{name: {name}, height_m: {height_m}, video: '{video}'}}]",
                       f"data.backgrounds='{backgrounds}'", "data.test_sets=[]", "run.until=extract"])
    engine = Engine(cache, global_seed=int(cfg.run.seed))
    graph = build_graph(cfg, video.parent)
    outcomes = engine.run(graph.targets("extract"))
    extract = next(o for o in outcomes if o.stage == "extract")
    row = {"status": extract.status, "error": extract.error, "path": str(extract.path),
           "stage_seconds": {o.stage: round(compute_seconds(o), 1) for o in outcomes}}
    record = Path(extract.path) / "extract.json"
    if record.is_file():
        row["extract"] = json.loads(record.read_text())
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--object", default="vase")
    parser.add_argument("--height-m", type=float, default=0.22)
    parser.add_argument("--seed", type=int, default=2)
    parser.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "wall_capture_cache")
    parser.add_argument("--out", type=Path, default=RESULTS / "extract" / "wall_capture.json")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    work = args.cache.parent / f"{args.cache.name}_inputs"
    (work / "backgrounds").mkdir(parents=True, exist_ok=True)
    video = work / f"wall_{args.object}.mp4"
    frames, masks = wall_capture_frames(args.object, args.height_m, args.seed)
    write_mp4(video, frames, 10.0)
    shares = [float(mask.mean()) for mask in masks]
    import cv2  # the backgrounds folder must hold a photo; run.until=extract never reads it

    cv2.imwrite(str(work / "backgrounds" / "unused.jpg"), frames[0][:, :, ::-1])
    row = {"object": args.object, "height_m": args.height_m, "seed": args.seed, "video": str(video),
           "object_share_of_frame": [round(min(shares), 3), round(max(shares), 3)],
           **run_chain(video, f"wall_{args.object}", args.height_m, work / "backgrounds", args.cache)}
    row["refused"] = row["status"] == "failed" and f"wall_{args.object}" in row["error"]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(row, indent=1, default=str))
    panel = Path(row["path"]) / "filtering.png"
    if panel.is_file():
        shutil.copyfile(panel, args.out.with_suffix(".png"))
    print(json.dumps({k: row[k] for k in ("status", "refused", "error", "stage_seconds")}, indent=1))


if __name__ == "__main__":
    main()
