"""Stage bg_frames: the frame slots of one background video, each a background photo of its own.

The graph gives a video min(`count`, the frame count its header states) slots before anything runs
(stages/app/pipeline.py), and one bg_depth and planes node per slot, whose photo is that slot's frame here. This stage
decodes the video, chooses its frames as the frames stage chooses a capture's (stages/lib/capture/frame_selection.py:
windows of equal feature motion, at most one per slot, the sharpest non-dark frame of each; then blurred frames and
near-duplicates dropped, and counted), and writes the chosen frames in time order into the first slots
(`images/%04d.png`, at the video's own size). A slot it cannot fill (the camera moved too little, the frames were
blurred or near-duplicates) is empty: its bg_depth node finds nothing to compute (stages/contract/errors.py EmptyInput)
and the datasets are made without it. With `depth` (a folder of one depth file per video frame: the sample's walk), each
chosen frame's depth file is copied beside it as its depth sidecar.

Sharpness and motion are measured on `analysis_fps` frames per second of video (a 30 fps video: every third frame;
the others are decoded, not converted), downscaled to `analysis_side`; the video is decoded a second time to write
the chosen frames at full size, so that no more than one full-size frame is held at a time.

Output (docs/stage_contracts.md): `images/%04d.png` (+ `images/%04d.depth.png`) and `bg_frames.json`
(stages/records/bg_frames.py: per slot the source frame's index, time and sharpness, or why it is empty).
"""
from __future__ import annotations

import logging
import shutil
import time
from pathlib import Path
from typing import TYPE_CHECKING, Iterator

import cv2
import numpy as np

from stages.bg_frames.spec import BgFramesConfig
from stages.contract.errors import StageError
from stages.lib.capture import frame_selection as selection
from stages.lib.capture.video_frames import decode_frames, read_video, video_header
from stages.records.bg_frames import BgFramesRecord, FrameSlot, depth_frame

if TYPE_CHECKING:  # the engine's object; not part of the stage's cache key
    from stages.engine.context import Context

log = logging.getLogger(__name__)
ROLE = "background video"


def slots_and_stride(video: Path, cfg: BgFramesConfig) -> tuple[int, int]:
    """The video's frame slots, min(cfg.count, the frame count its header states: as the graph sized them), and every
    how many frames it is analysed (cfg.analysis_fps of its frame rate). StageError when its header states no count."""
    stated, fps = video_header(video)
    if stated == 0:
        raise StageError(f"bg_frames: background video {video}: its header states no frame count, so it has no "
                         "frame slots; re-encode it as MP4 (H.264 or mp4v)")
    return min(cfg.count, stated), max(1, round(fps / cfg.analysis_fps)) if fps else 1


def empty_reason(video: Path, chosen: int, slots: int, counts: dict) -> str:
    """Why the slots after the first `chosen` of `slots` are empty, from the selection's counts."""
    return (f"{video.name} gives {chosen} frames for {slots} slots ({counts.get('windows', 0)} windows of "
            f"{counts.get('motion_step', 0)} motion, {counts['dark']} dark, {counts['blurred']} blurred, "
            f"{counts['duplicates_dropped']} near-duplicates dropped)")


def copy_depth(depth_folder: Path, index: int, target: Path) -> None:
    """Copy video frame `index`'s depth file of `depth_folder` to `target`; StageError naming it when it is missing."""
    source = depth_folder / depth_frame(index)
    if not source.is_file():
        raise StageError(f"bg_frames: depth folder {depth_folder} has no depth file {source.name} for video frame "
                         f"{index}; it must hold one per frame")
    shutil.copyfile(source, target)


def run(ctx: Context) -> dict:
    """Choose the frames of ctx.inputs["video"] and write them (and their depth) into its slots under ctx.out."""
    cfg = ctx.typed(BgFramesConfig)
    video = Path(ctx.inputs["video"])
    depth = Path(ctx.inputs["depth"]) if "depth" in ctx.inputs else None
    started = time.perf_counter()
    slots, stride = slots_and_stride(video, cfg)
    capture = read_video(video, cfg.analysis_side, "bg_frames", ROLE, stride)
    sources: list[tuple[int, float | None]] = []  # [N] (index in the video, time) of the analysed frames

    def analysed() -> Iterator[np.ndarray]:
        """The analysed frames [h, w, 3], downscaled to analysis_side; their indices and times kept in `sources`."""
        for frame in ctx.progress(capture.frames(), total=capture.count, unit="frame"):
            sources.append((frame.source_index, frame.time_s))
            yield frame.image

    stats = selection.scan_frames(analysed(), cfg.dark_threshold, is_video=True)
    chosen, counts = selection.select_frames(stats, cfg.motion_step, slots, cfg.blur_ratio, cfg.duplicate_threshold,
                                             is_video=True)
    scanned = time.perf_counter()

    (ctx.out / "images").mkdir()
    position = {sources[p][0]: p for p in chosen.tolist()}  # video frame index -> position among the analysed
    filled: list[FrameSlot] = []
    for slot, (index, image) in enumerate(decode_frames(video, position, "bg_frames", ROLE)):
        if not cv2.imwrite(str(ctx.out / BgFramesRecord.image(slot)), image):
            raise StageError(f"bg_frames: could not write {ctx.out / BgFramesRecord.image(slot)}")
        if depth is not None:
            copy_depth(depth, index, ctx.out / BgFramesRecord.depth(slot))
        filled.append(FrameSlot(index, sources[position[index]][1], round(float(stats.sharpness[position[index]]), 3)))
        height, width = image.shape[:2]
    if not filled:
        raise StageError(f"bg_frames: background video {video} gives no usable frame ({counts}); film with more "
                         "light and a steadier camera, or leave it out")
    reason = empty_reason(video, len(filled), slots, counts)
    BgFramesRecord(str(video), filled + [FrameSlot(empty=reason) for _ in range(slots - len(filled))],
                   counts).write(ctx.out)
    log.info("bg_frames[%s]: %d of %d slots filled from %d analysed frames of %s (%s)", ctx.item, len(filled), slots,
             len(sources), video, ", ".join(f"{k} {v}" for k, v in counts.items()))
    return {"slots": slots, "filled": len(filled), "analysed_every": stride, **counts, "width": width,
            "height": height, "scan_s": round(scanned - started, 3), "write_s": round(time.perf_counter() - scanned, 3),
            "seconds": round(time.perf_counter() - started, 3)}
