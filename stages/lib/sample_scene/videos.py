"""Writing capture videos (MP4, OpenCV's mp4v encoder)."""
from __future__ import annotations

import itertools
from pathlib import Path
from typing import Iterable

import cv2
import numpy as np


def write_mp4(path: Path, frames: Iterable[np.ndarray], fps: float) -> None:
    """Encode RGB uint8 frames [H, W, 3] (a list, or made one at a time) as an mp4v MP4 at `path`.

    With the same frames and the same OpenCV/FFmpeg build the file is byte-identical (checked by the tests).
    """
    frames = iter(frames)
    first = next(frames, None)
    if first is None:
        raise ValueError(f"no frames to write to {path}")
    height, width = first.shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (width, height))
    if not writer.isOpened():
        raise RuntimeError(f"OpenCV could not open an mp4v video writer for {path}")
    try:
        for frame in itertools.chain([first], frames):
            writer.write(np.ascontiguousarray(frame[..., ::-1]))
    finally:
        writer.release()

