"""Decoding the frames of a video (an object's capture, a background video), within bounds.

`open_video` refuses what is not a readable video or whose frames are above the pixel limit
(stages/lib/file_checks.py); `read_video` gives a capture's frames afresh on each pass, downscaled for analysis;
`decode_frames` gives chosen frames at full size in one pass; `header_frame_count` reads the frame count a video's
header states without decoding (milliseconds), so that the graph can size a video's frame slots before anything
runs. A folder of photos is a `Capture` too (stages/frames/run.py reads it).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Iterator

import cv2
import numpy as np

from stages.contract.errors import StageError
from stages.lib.file_checks import check_pixels, regular_file

VIDEO_SUFFIXES = (".avi", ".m4v", ".mkv", ".mov", ".mp4", ".mpeg", ".mpg", ".webm")


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


def resize_to_max_side(image: np.ndarray, max_side: int) -> tuple[np.ndarray, float]:
    """Downscale `image` [H, W, 3] so max(H, W) <= max_side; return (image, scale applied)."""
    height, width = image.shape[:2]
    scale = min(1.0, max_side / max(height, width))
    if scale >= 1.0:
        return image, 1.0
    size = (max(1, round(width * scale)), max(1, round(height * scale)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA), scale


def open_video(path: Path, stage: str = "frames", role: str = "object video") -> cv2.VideoCapture:
    """An opened cv2.VideoCapture for `path`, or StageError (naming the stage and the video's role) if it is not a
    readable file, OpenCV cannot read it, or its frames are above the pixel limit (stages/lib/file_checks.py)."""
    regular_file(path, f"{stage}: {role}")
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        capture.release()
        raise StageError(f"{stage}: cannot open video {path} (corrupt, truncated or an unsupported codec); "
                         "re-export it as MP4 (H.264 or mp4v) or pass a folder of images")
    width, height = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)), int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
    if width > 0 and height > 0:  # 0: the container does not say; the decoder's frames are then as they come
        try:
            check_pixels(path, f"{stage}: {role}", width, height)
        except StageError:
            capture.release()
            raise
    return capture


def video_header(path: Path) -> tuple[int, float]:
    """(frame count, frames per second) the header of the video at `path` states, read without decoding; a count of
    0 when the path is not a file, OpenCV cannot open it, or its header states none (a stream, a broken file), and
    a rate of 0.0 when it states none."""
    if not Path(path).is_file():
        return 0, 0.0
    capture = cv2.VideoCapture(str(path))
    try:
        count, fps = (capture.get(cv2.CAP_PROP_FRAME_COUNT), capture.get(cv2.CAP_PROP_FPS)) if capture.isOpened() \
            else (0.0, 0.0)
    finally:
        capture.release()
    return (int(count) if math.isfinite(count) and count >= 1 else 0), (fps if math.isfinite(fps) and fps > 0 else 0.0)


def header_frame_count(path: Path) -> int:
    """The frame count the header of the video at `path` states (video_header), 0 when it states none."""
    return video_header(path)[0]


def count_video_frames(path: Path, stage: str = "frames", role: str = "object video") -> int:
    """Number of decodable frames; trusts the container's count when it gives one, else decodes."""
    capture = open_video(path, stage, role)
    count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
    if count <= 0:
        count = 0
        while capture.grab():
            count += 1
    capture.release()
    return count


def read_video(path: Path, max_side: int, stage: str = "frames", role: str = "object video",
               stride: int = 1) -> Capture:
    """The frames of a video file, each downscaled so that its long side is at most `max_side`; with `stride` > 1
    only every stride-th frame (the others are decoded but not converted, which costs a fraction)."""
    count = count_video_frames(path, stage, role)
    if count == 0:
        raise StageError(f"{stage}: video {path} has no decodable frames (empty or corrupt); "
                         "check that it plays, or re-export it")

    def frames() -> Iterator[SourceFrame]:
        capture = open_video(path, stage, role)
        fps = capture.get(cv2.CAP_PROP_FPS)
        index = 0
        while True:
            if index % stride:
                if not capture.grab():
                    break
                index += 1
                continue
            ok, image = capture.read()
            if not ok:
                break
            image, scale = resize_to_max_side(image, max_side)
            yield SourceFrame(image, index, index / fps if fps > 0 else None, str(path), scale)
            index += 1
        capture.release()

    return Capture(math.ceil(count / stride), frames, is_video=True)


def decode_frames(path: Path, indices: Iterable[int], stage: str, role: str) -> Iterator[tuple[int, np.ndarray]]:
    """(index, frame [H, W, 3] BGR uint8 at the video's own size) of the frames at `indices`, in ascending order, in
    one pass that converts only those frames to colour and stops after the last; fewer when the video ends early."""
    capture = open_video(path, stage, role)
    try:
        position = 0
        for wanted in sorted(set(indices)):
            while position < wanted:
                if not capture.grab():
                    return
                position += 1
            ok, image = capture.read()
            if not ok:
                return
            yield position, image
            position += 1
    finally:
        capture.release()
