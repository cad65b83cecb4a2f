"""Stage `frames`: the usable, distinct frames of a video or of a folder of photos.

A folder of photos keeps every usable photo: dark, blurred and near-duplicate photos are dropped (counted
in the metrics), and `exclude` leaves named files out (e.g. photos held out for testing). A video is cut
into windows of equal camera motion (stages/frame_selection.py) and keeps the sharpest frame of each,
then drops blurred frames and near-duplicates; `max_frames` caps the count on long videos.

Output (docs/stage_contracts.md): `images/%04d.jpg` and `frames.json`, a list of
`{"file", "source_index", "time_s", "sharpness", "source", "scale"}` in frame order, where
`source` is the video (or the original image) the frame came from and `scale` maps source
pixels to frame pixels (frame px = scale * source px), so intrinsics of the source carry over.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterator

import cv2
import numpy as np

from stages import frame_selection as selection
from stages.errors import StageError
from stages.file_checks import check_pixels, regular_file
from stages.imageio import IMAGE_SUFFIXES, image_size, list_images
from stages.records.frames import FrameEntry, FramesRecord
from stages.specs.frames import FramesConfig

if TYPE_CHECKING:  # the engine's object; not part of the stage's cache key
    from stages.context import Context

log = logging.getLogger(__name__)


@dataclass
class SourceFrame:
    """One decoded input frame before selection."""

    image: np.ndarray        # [H, W, 3] uint8 BGR, already resized to max_side
    source_index: int
    time_s: float | None
    source: str
    scale: float


@dataclass
class Capture:
    """A video or photo folder: its frame count and a function that decodes its frames afresh."""

    count: int
    frames: Callable[[], Iterator[SourceFrame]]
    is_video: bool


@dataclass
class FrameStats:
    """What selection needs of every decoded frame, in source order."""

    sharpness: np.ndarray  # [N] variance of the Laplacian
    dark: np.ndarray  # [N] bool
    thumbnails: list[np.ndarray]  # [N] x [24, 32]
    motions: list[float | None]  # [N] feature motion from the previous frame (videos only)


def resize_to_max_side(image: np.ndarray, max_side: int) -> tuple[np.ndarray, float]:
    """Downscale `image` [H, W, 3] so max(H, W) <= max_side; return (image, scale applied)."""
    height, width = image.shape[:2]
    scale = min(1.0, max_side / max(height, width))
    if scale >= 1.0:
        return image, 1.0
    size = (max(1, round(width * scale)), max(1, round(height * scale)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA), scale


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


def open_video(path: Path) -> cv2.VideoCapture:
    """An opened cv2.VideoCapture for `path`, or StageError if it is not a readable file, OpenCV cannot read it,
    or its frames are above the pixel limit (stages/file_checks.py)."""
    regular_file(path, "frames: object video")
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        capture.release()
        raise StageError(f"frames: cannot open video {path} (corrupt, truncated or an unsupported codec); "
                         "re-export it as MP4 (H.264 or mp4v) or pass a folder of images")
    width, height = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)), int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
    if width > 0 and height > 0:  # 0: the container does not say; the decoder's frames are then as they come
        try:
            check_pixels(path, "frames: object video", width, height)
        except StageError:
            capture.release()
            raise
    return capture


def count_video_frames(path: Path) -> int:
    """Number of decodable frames; trusts the container's count when it gives one, else decodes."""
    capture = open_video(path)
    count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
    if count <= 0:
        count = 0
        while capture.grab():
            count += 1
    capture.release()
    return count


def read_video(path: Path, max_side: int) -> Capture:
    """The frames of a video file."""
    count = count_video_frames(path)
    if count == 0:
        raise StageError(f"frames: video {path} has no decodable frames (empty or corrupt); "
                         "check that it plays, or re-export it")

    def frames() -> Iterator[SourceFrame]:
        capture = open_video(path)
        fps = capture.get(cv2.CAP_PROP_FPS)
        index = 0
        while True:
            ok, image = capture.read()
            if not ok:
                break
            image, scale = resize_to_max_side(image, max_side)
            yield SourceFrame(image, index, index / fps if fps > 0 else None, str(path), scale)
            index += 1
        capture.release()

    return Capture(count, frames, is_video=True)


def scan(capture: Capture, cfg: FramesConfig, progress=lambda it, **kw: it) -> FrameStats:
    """Sharpness, darkness, thumbnail and (videos) feature motion of every decoded frame."""
    sharpness, dark, thumbnails, motions = [], [], [], []
    previous = None
    for frame in progress(capture.frames(), total=capture.count, unit="frame"):
        sharpness.append(selection.laplacian_sharpness(frame.image))
        dark.append(selection.mean_brightness(frame.image) < cfg.dark_threshold)
        thumbnails.append(selection.thumbnail(frame.image))
        if capture.is_video:
            tracked = selection.tracking_image(frame.image)
            motions.append(None if previous is None else selection.feature_motion(previous, tracked))
            previous = tracked
    return FrameStats(np.array(sharpness), np.array(dark, dtype=bool), thumbnails, motions)


def select_frames(stats: FrameStats, cfg: FramesConfig, is_video: bool) -> tuple[np.ndarray, dict]:
    """Indices (into the decoded frames, ascending) of the frames to keep, and the counts of each filter.

    Photos: every non-dark photo; video: the sharpest non-dark frame of each motion window. Then
    blurred frames and near-duplicates of the previous kept frame are dropped.
    """
    decoded = len(stats.sharpness)
    counts = {"decoded": decoded, "dark": int(stats.dark.sum())}
    if is_video and decoded:
        windows, step = selection.motion_windows(stats.motions, cfg.motion_step, cfg.max_frames)
        candidates = selection.sharpest_per_window(windows, stats.sharpness, ~stats.dark)
        counts.update({"windows": len(np.unique(windows[~stats.dark])) if (~stats.dark).any() else 0,
                       "motion_step": round(step, 5),
                       "motion_total": round(float(np.sum([m for m in stats.motions if m is not None])), 4),
                       "motion_unknown": sum(m is None for m in stats.motions[1:])})
    else:
        candidates = np.flatnonzero(~stats.dark)
    blurred = selection.blurred(stats.sharpness[candidates], cfg.blur_ratio)
    sharp = candidates[~blurred]
    distinct = selection.distinct([stats.thumbnails[i] for i in sharp], cfg.duplicate_threshold)
    counts.update({"blurred": int(blurred.sum()), "duplicates_dropped": int((~distinct).sum())})
    return sharp[distinct], counts


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
    cfg = FramesConfig(**ctx.params)
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
    stats = scan(capture, cfg, progress=ctx.progress)
    chosen, counts = select_frames(stats, cfg, capture.is_video)
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
