"""Stage `frames`: pick sharp, distinct frames spread over a video (or a folder of images).

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
from typing import Iterator

import cv2
import numpy as np

from stages.context import Context, StageError
from stages.imageio import IMAGE_SUFFIXES, list_images
from stages.records.frames import FrameEntry, FramesRecord

log = logging.getLogger(__name__)


@dataclass
class FramesConfig:
    num_frames: int = 60            # frames to keep, one per window spread over the input
    max_side: int = 800             # downscale so the longer side is at most this (never upscale)
    min_frames: int = 8             # fewer usable frames than this is an error
    dark_threshold: float = 16.0    # frames with mean grey level below this (0..255) are dropped
    duplicate_threshold: float = 1.5  # mean abs grey difference (0..255) of thumbnails below this = duplicate
    jpeg_quality: int = 95


@dataclass
class SourceFrame:
    """One decoded input frame before selection."""

    image: np.ndarray        # [H, W, 3] uint8 BGR, already resized to max_side
    source_index: int
    time_s: float | None
    source: str
    scale: float


def resize_to_max_side(image: np.ndarray, max_side: int) -> tuple[np.ndarray, float]:
    """Downscale `image` [H, W, 3] so max(H, W) <= max_side; return (image, scale applied)."""
    height, width = image.shape[:2]
    scale = min(1.0, max_side / max(height, width))
    if scale >= 1.0:
        return image, 1.0
    size = (max(1, round(width * scale)), max(1, round(height * scale)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA), scale


def laplacian_sharpness(image: np.ndarray) -> float:
    """Variance of the Laplacian of the grey image [H, W, 3] BGR uint8 (higher = sharper)."""
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())


def mean_brightness(image: np.ndarray) -> float:
    """Mean grey level (0..255) of a BGR uint8 image [H, W, 3]."""
    return float(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY).mean())


def thumbnail(image: np.ndarray) -> np.ndarray:
    """Small grey float thumbnail [24, 32] used to detect near-duplicate frames."""
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return cv2.resize(grey, (32, 24), interpolation=cv2.INTER_AREA).astype(np.float32)


def read_image_folder(folder: Path, max_side: int) -> tuple[int, Iterator[SourceFrame]]:
    """(count, iterator of frames) for a folder of images; unreadable images are skipped with a warning."""
    paths = list_images(folder)
    if not paths:
        raise StageError(f"frames: folder {folder} contains no images ({', '.join(IMAGE_SUFFIXES)}); "
                         "point the `video` input at a video file or a folder of photos")

    def frames() -> Iterator[SourceFrame]:
        for index, path in enumerate(paths):
            image = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if image is None:
                log.warning("frames: skipping unreadable image %s", path)
                continue
            image, scale = resize_to_max_side(image, max_side)
            yield SourceFrame(image, index, None, str(path), scale)

    return len(paths), frames()


def open_video(path: Path) -> cv2.VideoCapture:
    """An opened cv2.VideoCapture for `path`, or StageError if OpenCV cannot read it."""
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        capture.release()
        raise StageError(f"frames: cannot open video {path} (corrupt, truncated or an unsupported codec); "
                         "re-export it as MP4 (H.264 or mp4v) or pass a folder of images")
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


def read_video(path: Path, max_side: int) -> tuple[int, Iterator[SourceFrame]]:
    """(frame count, iterator of decoded frames) for a video file."""
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

    return count, frames()


def select_frames(frames: Iterator[SourceFrame], count: int, cfg: FramesConfig,
                  progress=lambda it, **kw: it) -> tuple[list[tuple[SourceFrame, float]], dict]:
    """Sharpest non-dark frame per window (cfg.num_frames equal windows over `count` frames),
    then drop near-duplicates of the previous kept frame.

    Returns ([(frame, sharpness)] in source order, counts dict).
    """
    num_windows = max(1, min(cfg.num_frames, count))
    best: dict[int, tuple[SourceFrame, float]] = {}
    decoded = dark = 0
    for frame in progress(frames, total=count, unit="frame"):
        decoded += 1
        if mean_brightness(frame.image) < cfg.dark_threshold:
            dark += 1
            continue
        window = min(frame.source_index * num_windows // count, num_windows - 1)
        sharpness = laplacian_sharpness(frame.image)
        if window not in best or sharpness > best[window][1]:
            best[window] = (frame, sharpness)
    kept: list[tuple[SourceFrame, float]] = []
    previous_thumb = None
    for window in sorted(best):
        thumb = thumbnail(best[window][0].image)
        if previous_thumb is not None and np.abs(thumb - previous_thumb).mean() < cfg.duplicate_threshold:
            continue
        kept.append(best[window])
        previous_thumb = thumb
    counts = {"decoded": decoded, "dark": dark, "windows": num_windows,
              "duplicates_dropped": len(best) - len(kept)}
    return kept, counts


def check_enough_frames(kept: list, counts: dict, source: Path, cfg: FramesConfig) -> None:
    """StageError explaining why fewer than cfg.min_frames usable frames came out of `source`."""
    if len(kept) >= cfg.min_frames:
        return
    if counts["decoded"] and counts["dark"] >= counts["decoded"] // 2:
        reason = (f"{counts['dark']} of {counts['decoded']} frames are too dark "
                  f"(mean grey level < {cfg.dark_threshold}); film with more light")
    elif counts["duplicates_dropped"]:
        reason = (f"{counts['duplicates_dropped']} frames were near-duplicates (the camera hardly moves); "
                  "move the camera around the object")
    else:
        reason = f"only {counts['decoded']} frames could be read; use a longer video or more photos"
    raise StageError(f"frames: {source} gives {len(kept)} usable frames, at least {cfg.min_frames} "
                     f"are needed: {reason}")


def run(ctx: Context) -> dict:
    """Extract frames from `ctx.inputs["video"]` (video file or image folder) into ctx.out."""
    cfg = FramesConfig(**ctx.params)
    source = Path(ctx.inputs["video"])
    start = time.perf_counter()
    if not source.exists():
        raise StageError(f"frames: input {source} does not exist; check the object's video path in the data config")
    if source.is_dir():
        count, frames = read_image_folder(source, cfg.max_side)
    else:
        count, frames = read_video(source, cfg.max_side)
    kept, counts = select_frames(frames, count, cfg, progress=ctx.progress)
    check_enough_frames(kept, counts, source, cfg)

    image_dir = ctx.out / "images"
    image_dir.mkdir(parents=True, exist_ok=True)
    entries = []
    for number, (frame, sharpness) in enumerate(kept):
        name = f"{number:04d}.jpg"
        cv2.imwrite(str(image_dir / name), frame.image, [cv2.IMWRITE_JPEG_QUALITY, cfg.jpeg_quality])
        entries.append(FrameEntry(f"images/{name}", frame.source_index, frame.time_s, round(sharpness, 3),
                                  frame.source, frame.scale))
    FramesRecord(entries).write(ctx.out)
    height, width = kept[0][0].image.shape[:2]
    metrics = {"frames": len(entries), "input_frames": count, **counts, "width": width, "height": height,
               "seconds": round(time.perf_counter() - start, 3)}
    log.info("frames[%s]: kept %d of %d frames from %s", ctx.item, len(entries), count, source)
    return metrics
