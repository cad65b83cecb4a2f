"""Choosing the frames of a capture: sharpness, feature motion between frames, motion windows, and the
blur and near-duplicate filters. Pure functions (images and arrays in, indices out); the frames stage (a
capture's frames) and the bg_frames stage (a background video's frame slots) read and write the files.

A video is cut into windows of equal camera motion, not of equal frame count: the motion between two
frames is the median displacement of corners tracked from one to the next (Lucas-Kanade, checked forwards
and backwards), as a fraction of the image diagonal. A slow pan gives few windows, a fast one many; the
sharpest frame of each window is kept.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import cv2
import numpy as np
from scipy.ndimage import percentile_filter

TRACK_SIDE = 320  # feature motion is measured on grey images with this long side
MIN_TRACKED = 8  # fewer corners tracked both ways: the motion is unknown
BLUR_NEIGHBOURS = 9  # a frame's sharpness is compared with the 75th percentile of this many neighbours


def laplacian_sharpness(image: np.ndarray) -> float:
    """Variance of the Laplacian of the grey image [H, W, 3] BGR uint8 (higher = sharper)."""
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())


def mean_brightness(image: np.ndarray) -> float:
    """Mean grey level (0..255) of a BGR uint8 image [H, W, 3]."""
    return float(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY).mean())


def thumbnail(image: np.ndarray) -> np.ndarray:
    """Small grey float thumbnail [24, 32] of a BGR uint8 image [H, W, 3], to detect near-duplicates."""
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return cv2.resize(grey, (32, 24), interpolation=cv2.INTER_AREA).astype(np.float32)


def tracking_image(image: np.ndarray) -> np.ndarray:
    """Grey uint8 image [h, w] with long side TRACK_SIDE (never upscaled) of a BGR image [H, W, 3]."""
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    factor = min(1.0, TRACK_SIDE / max(grey.shape))
    return cv2.resize(grey, None, fx=factor, fy=factor, interpolation=cv2.INTER_AREA) if factor < 1 else grey


def feature_motion(previous: np.ndarray, current: np.ndarray, max_corners: int = 300) -> float | None:
    """Median displacement of corners tracked from `previous` to `current` (grey uint8 [h, w] each), as a
    fraction of the image diagonal; None when fewer than MIN_TRACKED corners track forwards and back
    within a pixel (a cut, a dark or featureless frame)."""
    corners = cv2.goodFeaturesToTrack(previous, max_corners, 0.01, 5)
    if corners is None or len(corners) < MIN_TRACKED:
        return None
    window = {"winSize": (21, 21), "maxLevel": 3}
    moved, forward, _ = cv2.calcOpticalFlowPyrLK(previous, current, corners, None, **window)
    back, backward, _ = cv2.calcOpticalFlowPyrLK(current, previous, moved, None, **window)
    good = (forward[:, 0] == 1) & (backward[:, 0] == 1) & (np.linalg.norm(back - corners, axis=2)[:, 0] < 1.0)
    if good.sum() < MIN_TRACKED:
        return None
    displacement = np.linalg.norm(moved - corners, axis=2)[:, 0][good]
    return float(np.median(displacement) / np.hypot(*previous.shape))


def motion_windows(motions: list[float | None], step: float, max_windows: int) -> tuple[np.ndarray, float]:
    """Window id [N] of each frame and the step used, for motions [N] (frame i's motion from frame i-1;
    the first is ignored; None = unknown, counted as a full step so that a cut starts a new window).

    Windows are intervals of `step` along the cumulative motion; when that gives more than `max_windows`,
    the step grows so that exactly `max_windows` cover the capture.
    """
    increments = np.array([0.0] + [step if m is None else m for m in motions[1:]])  # [N]
    travelled = np.cumsum(increments)  # [N]
    if travelled[-1] / step >= max_windows:
        step = travelled[-1] / (max_windows - 0.5)
    return np.floor(travelled / step).astype(np.int64), float(step)


def sharpest_per_window(window_ids: np.ndarray, sharpness: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """Indices (ascending) of the sharpest usable frame of each window. window_ids [N] int,
    sharpness [N], usable [N] bool."""
    best: dict[int, int] = {}
    for index in np.flatnonzero(usable):
        window = int(window_ids[index])
        if window not in best or sharpness[index] > sharpness[best[window]]:
            best[window] = int(index)
    return np.array(sorted(best.values()), dtype=np.int64)


def blurred(sharpness: np.ndarray, ratio: float) -> np.ndarray:
    """Mask [M] of frames (sharpness [M], in capture order) less sharp than `ratio` x the 75th percentile
    of their BLUR_NEIGHBOURS neighbours: motion-blurred or out-of-focus frames among sharp ones (a capture
    that is soft throughout keeps its frames)."""
    if len(sharpness) == 0 or ratio <= 0:
        return np.zeros(len(sharpness), dtype=bool)
    local = percentile_filter(np.asarray(sharpness, dtype=np.float64), 75, size=BLUR_NEIGHBOURS, mode="nearest")
    return sharpness < ratio * local


def distinct(thumbnails: list[np.ndarray], threshold: float) -> np.ndarray:
    """Mask [M] of frames kept when each is compared with the previous kept one: a frame whose thumbnail
    [24, 32] differs from it by less than `threshold` grey levels (mean absolute) is a near-duplicate."""
    keep = np.zeros(len(thumbnails), dtype=bool)
    previous = None
    for index, thumb in enumerate(thumbnails):
        if previous is None or np.abs(thumb - previous).mean() >= threshold:
            keep[index] = True
            previous = thumb
    return keep


@dataclass
class FrameStats:
    """What selection needs of every decoded frame, in source order."""

    sharpness: np.ndarray  # [N] variance of the Laplacian
    dark: np.ndarray  # [N] bool
    thumbnails: list[np.ndarray]  # [N] x [24, 32]
    motions: list[float | None]  # [N] feature motion from the previous frame (videos only)


def scan_frames(images: Iterable[np.ndarray], dark_threshold: float, is_video: bool) -> FrameStats:
    """Sharpness, darkness (mean grey level below `dark_threshold`), thumbnail and, for a video, feature motion
    from the previous frame of every image [H, W, 3] BGR uint8, in order."""
    sharpness, dark, thumbnails, motions = [], [], [], []
    previous = None
    for image in images:
        sharpness.append(laplacian_sharpness(image))
        dark.append(mean_brightness(image) < dark_threshold)
        thumbnails.append(thumbnail(image))
        if is_video:
            tracked = tracking_image(image)
            motions.append(None if previous is None else feature_motion(previous, tracked))
            previous = tracked
    return FrameStats(np.array(sharpness), np.array(dark, dtype=bool), thumbnails, motions)


def select_frames(stats: FrameStats, motion_step: float, max_windows: int, blur_ratio: float,
                  duplicate_threshold: float, is_video: bool) -> tuple[np.ndarray, dict]:
    """Indices [K] (into the scanned frames, ascending) of the frames to keep, and the counts of each filter.

    Photos: every non-dark photo; video: the sharpest non-dark frame of each window of `motion_step` motion (at
    most `max_windows` windows: motion_windows). Then blurred frames (`blur_ratio`) and near-duplicates of the
    previous kept frame (`duplicate_threshold`) are dropped.
    """
    decoded = len(stats.sharpness)
    counts = {"decoded": decoded, "dark": int(stats.dark.sum())}
    if is_video and decoded:
        windows, step = motion_windows(stats.motions, motion_step, max_windows)
        candidates = sharpest_per_window(windows, stats.sharpness, ~stats.dark)
        counts.update({"windows": len(np.unique(windows[~stats.dark])) if (~stats.dark).any() else 0,
                       "motion_step": round(step, 5),
                       "motion_total": round(float(np.sum([m for m in stats.motions if m is not None])), 4),
                       "motion_unknown": sum(m is None for m in stats.motions[1:])})
    else:
        candidates = np.flatnonzero(~stats.dark)
    is_blurred = blurred(stats.sharpness[candidates], blur_ratio)
    sharp = candidates[~is_blurred]
    keep = distinct([stats.thumbnails[i] for i in sharp], duplicate_threshold)
    counts.update({"blurred": int(is_blurred.sum()), "duplicates_dropped": int((~keep).sum())})
    return sharp[keep], counts
