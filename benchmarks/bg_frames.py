"""Benchmark of the bg_frames stage (issue 55's target: a 30 s 1080p room video becomes photo nodes in at most 30 s on
the 2 cores, the depth model not counted).

    python -m benchmarks.bg_frames [--video PATH] [--seconds 30] [--fps 30] [--render-width 480] [--workers 2]
                                   [--count 20] [--json PATH]

Makes the video unless PATH exists: the sample's walk through its in-domain rooms (stages/lib/sample_scene/walk.py, the
sample's seed-0 test rooms, each in turn) at --fps for --seconds, ray-traced at --render-width x 9/16 (rendering
1080p frames would take the machine most of an hour) and upscaled to 1920x1080 (bicubic), mp4v. Then times, in this
process, what turns it into photo nodes: the graph's slots from the video's header (the plan's share), and the
bg_frames stage (decoding, choosing the frames, writing them at 1080p). Prints one JSON object.
"""
from __future__ import annotations

import argparse
import json
import logging
import resource
import tempfile
import time
from functools import partial
from pathlib import Path

import cv2
import numpy as np

from stages.bg_frames import run as bg_frames
from stages.engine.context import Context
from stages.lib.capture.video_frames import header_frame_count
from stages.lib.processes import spawn_pool
from stages.lib.sample_scene.raytrace import RAY_THREADS, TracedScene
from stages.lib.sample_scene.rooms import make_room, scene_lighting
from stages.lib.sample_scene.testsets import camera_k
from stages.lib.sample_scene.videos import write_mp4
from stages.lib.sample_scene.walk import chunks, render_frame, room_frames, room_walk
from stages.records.bg_frames import BgFramesRecord

ROOMS = 4  # the sample's test rooms (SampleConfig.test_rooms)
SIZE = (1920, 1080)


def render_piece(count: int, width: int, piece: int) -> list[np.ndarray]:
    """The frames (RGB uint8 [h, width, 3], 16:9) of one piece of a `count`-frame walk."""
    RAY_THREADS["count"] = 1
    room_index, frames = chunks(count, ROOMS)[piece]
    part = room_frames(count, ROOMS)[room_index]
    room = make_room(np.random.default_rng([0, 31, room_index]))  # the sample's seed-0 test room
    viewmats = room_walk(room, np.random.default_rng([0, 51, room_index]), len(part))
    lighting = scene_lighting(room, np.random.default_rng([0, 52, room_index]))
    height = round(width * SIZE[1] / SIZE[0])
    traced, K = TracedScene(room.meshes), camera_k("a", width, height)
    return [render_frame(traced, lighting, K, viewmats[index - part.start], width, height, 1)[0] for index in frames]


def make_video(path: Path, seconds: float, fps: float, width: int, workers: int) -> float:
    """Render the walk into `path`; returns the seconds it took."""
    started = time.perf_counter()
    count = round(seconds * fps)
    with spawn_pool(workers) as pool:
        frames = [f for piece in pool.map(partial(render_piece, count, width), range(len(chunks(count, ROOMS))))
                  for f in piece]
    write_mp4(path, (cv2.resize(frame, SIZE, interpolation=cv2.INTER_CUBIC) for frame in frames), fps)
    return time.perf_counter() - started


def cpu_seconds() -> float:
    """CPU seconds of this process (user + system)."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--video", type=Path, default=Path(tempfile.gettempdir()) / "bg_frames_walk_1080p.mp4")
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--render-width", type=int, default=480)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--count", type=int, default=20)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO)
    report = {"video": str(args.video)}
    if not args.video.is_file():
        report["render_s"] = round(make_video(args.video, args.seconds, args.fps, args.render_width, args.workers), 1)
    report["video_mb"] = round(args.video.stat().st_size / 1e6, 1)
    started = time.perf_counter()
    report["header_frames"] = header_frame_count(args.video)
    report["slots_s"] = round(time.perf_counter() - started, 4)  # what the plan spends on the video
    out = Path(tempfile.mkdtemp(prefix="bg_frames_bench_"))
    cpu, started = cpu_seconds(), time.perf_counter()
    metrics = bg_frames.run(Context("bg_frames", args.video.stem, {"count": args.count}, {"video": args.video}, out))
    report.update({"stage_wall_s": round(time.perf_counter() - started, 2),
                   "stage_cpu_s": round(cpu_seconds() - cpu, 2), "metrics": metrics, "out": str(out),
                   "chosen": [slot.source_index for slot in BgFramesRecord.read(out).slots]})
    print(json.dumps(report, indent=1))
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
