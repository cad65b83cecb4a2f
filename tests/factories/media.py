"""Image and video files: a written image, mp4v videos, their frames, a blurred copy, colour noise."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from stages.lib.sample_scene.videos import write_mp4


def write_image(path: Path, array: np.ndarray) -> Path:
    """Write `array` (BGR or grey, uint8 or uint16) with OpenCV; returns `path`."""
    assert cv2.imwrite(str(path), array)
    return path


def write_video(path: Path, images: list[np.ndarray], fps: float = 10.0) -> Path:
    """Write BGR uint8 images [H, W, 3] as an mp4v video (the sample's writer); returns `path`."""
    write_mp4(path, [image[..., ::-1] for image in images], fps)
    return path


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


def read_video_frames(path: Path) -> list[np.ndarray]:
    """All frames of a video as BGR uint8 [H, W, 3]."""
    return [frame[..., ::-1] for frame in read_mp4(path)]


def blurred_copy(source: Path, target: Path, sigma: float) -> Path:
    """`source` re-encoded with every frame Gaussian-blurred (cv2.GaussianBlur, sigma in pixels)."""
    return write_video(target, [cv2.GaussianBlur(image, (0, 0), sigma) for image in read_video_frames(source)])


def noise_video(path: Path, count: int, width: int, height: int, seed: int = 0) -> Path:
    """`count` frames of independent colour noise: distinct frames that no SfM can match."""
    rng = np.random.default_rng(seed)
    return write_video(path, [rng.integers(0, 256, (height, width, 3), dtype=np.uint8) for _ in range(count)])
