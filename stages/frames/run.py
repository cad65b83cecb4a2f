"""Stage `frames`: the usable, distinct frames of a video or of a folder of photos.

A folder of photos keeps every usable photo: dark, blurred and near-duplicate photos are dropped (counted
in the metrics), and `exclude` leaves named files out (e.g. photos held out for testing). A video is cut
into windows of equal camera motion (stages/lib/capture/frame_selection.py) and keeps the sharpest frame of each,
then drops blurred frames and near-duplicates; `max_frames` caps the count on long videos.

Output (docs/stage_contracts.md): `images/%04d.jpg` and `frames.json`, a list of
`{"file", "source_index", "time_s", "sharpness", "source", "scale"}` in frame order, where
`source` is the video (or the original image) the frame came from and `scale` maps source
pixels to frame pixels (frame px = scale * source px), so intrinsics of the source carry over.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING, Iterator

import cv2

from stages.contract.errors import StageError
from stages.frames.spec import FramesConfig
from stages.lib.capture import frame_selection as selection
from stages.lib.capture.video_frames import Capture, SourceFrame, read_video, resize_to_max_side
from stages.lib.imageio import IMAGE_SUFFIXES, image_size, list_images
from stages.records.frames import FrameEntry, FramesRecord

if TYPE_CHECKING:  # the engine's object; not part of the stage's cache key
    from stages.engine.context import Context

log = logging.getLogger(__name__)


def read_image_folder(folder: Path, max_side: int, exclude: list[str]) -> Capture:
    """The photos of `folder` (sorted by name) minus the names in `exclude`; unreadable ones are skipped
    with a warning. StageError when the folder has no images or `exclude` names a file it lacks."""
    paths = list_images(folder)
    if not paths:
        raise StageError(f"frames: folder {folder} contains no images ({', '.join(IMAGE_SUFFIXES)}); "
                         "point the `video` input at a video file or a folder of photos")
    missing = sorted(set(exclude) - {path.name for path in paths})
    if missing:
        raise StageError(f"frames: frames.exclude names {missing}, which are not images in {folder}; "
                         "list file names (not paths) of photos in that folder")
    paths = [path for path in paths if path.name not in set(exclude)]

    def frames() -> Iterator[SourceFrame]:
        for index, path in enumerate(paths):
            try:
                image_size(path, "photo")  # its header: a readable image file under the pixel limit
            except StageError as error:
                log.warning("frames: skipping %s", error)
                continue
            image = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if image is None:
                log.warning("frames: skipping unreadable image %s", path)
                continue
            image, scale = resize_to_max_side(image, max_side)
            yield SourceFrame(image, index, None, str(path), scale)

    return Capture(len(paths), frames, is_video=False)


def check_enough_frames(kept: int, counts: dict, source: Path, cfg: FramesConfig) -> None:
    """StageError explaining why fewer than cfg.min_frames usable frames came out of `source`."""
    if kept >= cfg.min_frames:
        return
    usable = counts["decoded"] - counts["dark"]
    if counts["decoded"] and counts["dark"] >= counts["decoded"] // 2:
        reason = (f"{counts['dark']} of {counts['decoded']} frames are too dark "
                  f"(mean grey level < {cfg.dark_threshold}); film with more light")
    elif counts["duplicates_dropped"] or counts.get("windows", usable) < min(usable, cfg.min_frames):
        reason = ("the frames are near-duplicates (the camera hardly moves); move the camera around the object")
    elif counts["blurred"]:
        reason = f"{counts['blurred']} frames are blurred; move the camera more slowly or use more light"
    else:
        reason = f"only {counts['decoded']} frames could be read; use a longer video or more photos"
    raise StageError(f"frames: {source} gives {kept} usable frames, at least {cfg.min_frames} "
                     f"are needed: {reason}")


def run(ctx: Context) -> dict:
    """Extract frames from `ctx.inputs["video"]` (video file or image folder) into ctx.out."""
    cfg = ctx.typed(FramesConfig)
    source = Path(ctx.inputs["video"])
    start = time.perf_counter()
    if not source.exists():
        raise StageError(f"frames: input {source} does not exist; check the object's video path in the data config")
    if source.is_dir():
        capture = read_image_folder(source, cfg.max_side, cfg.exclude)
    elif cfg.exclude:
        raise StageError(f"frames: frames.exclude {cfg.exclude} names photos of a folder, but {source} is a "
                         "video; clear frames.exclude or point `video` at the folder of photos")
    else:
        capture = read_video(source, cfg.max_side)
    frames = ctx.progress(capture.frames(), total=capture.count, unit="frame")
    stats = selection.scan_frames((frame.image for frame in frames), cfg.dark_threshold, capture.is_video)
    chosen, counts = selection.select_frames(stats, cfg.motion_step, cfg.max_frames, cfg.blur_ratio,
                                             cfg.duplicate_threshold, capture.is_video)
    check_enough_frames(len(chosen), counts, source, cfg)

    image_dir = ctx.out / "images"
    image_dir.mkdir(parents=True, exist_ok=True)
    wanted = iter(chosen.tolist())
    target = next(wanted)
    entries = []
    for position, frame in enumerate(capture.frames()):  # decoded again: only the chosen frames are held
        if position != target:
            continue
        name = f"{len(entries):04d}.jpg"
        cv2.imwrite(str(image_dir / name), frame.image, [cv2.IMWRITE_JPEG_QUALITY, cfg.jpeg_quality])
        entries.append(FrameEntry(f"images/{name}", frame.source_index, frame.time_s,
                                  round(float(stats.sharpness[position]), 3), frame.source, frame.scale))
        height, width = frame.image.shape[:2]
        target = next(wanted, None)
        if target is None:
            break
    FramesRecord(entries).write(ctx.out)
    metrics = {"frames": len(entries), "input_frames": capture.count, "excluded": len(cfg.exclude), **counts,
               "width": width, "height": height, "seconds": round(time.perf_counter() - start, 3)}
    log.info("frames[%s]: kept %d of %d frames from %s (%s)", ctx.item, len(entries), capture.count, source,
             ", ".join(f"{k} {v}" for k, v in counts.items()))
    return metrics
