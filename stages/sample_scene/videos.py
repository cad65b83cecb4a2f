"""Writing capture videos (MP4, OpenCV's mp4v encoder)."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np


def write_mp4(path: Path, frames: list[np.ndarray], fps: float) -> None:
    """Encode RGB uint8 frames [H, W, 3] as an mp4v MP4 at `path`.

    With the same frames and the same OpenCV/FFmpeg build the file is byte-identical (checked by the tests).
    """
    if not frames:
        raise ValueError(f"no frames to write to {path}")
    height, width = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (width, height))
    if not writer.isOpened():
        raise RuntimeError(f"OpenCV could not open an mp4v video writer for {path}")
    try:
        for frame in frames:
            writer.write(np.ascontiguousarray(frame[..., ::-1]))
    finally:
        writer.release()


def read_mp4(path: Path) -> list[np.ndarray]:
    """Decode all frames of a video as RGB uint8 [H, W, 3]."""
    capture = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        frames.append(frame[..., ::-1].copy())
    capture.release()
    return frames
