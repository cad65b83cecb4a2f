"""The frames stage's spec: how frames are chosen from a capture video or a folder of photos (`video`)."""
from __future__ import annotations

from dataclasses import dataclass, field

from stages.contract.inputs import Input, Inputs


INPUTS = Inputs((Input("video", raw="capture"),))  # a video file or a folder of photos


@dataclass
class FramesConfig:
    motion_step: float = 0.015      # video: one frame per this much feature motion (fraction of the image
    #                                 diagonal); the sample's orbits (12 degrees per frame) keep every frame
    max_frames: int = 150           # video: at most this many frames (the motion step grows to fit)
    max_side: int = 800             # downscale so the longer side is at most this (never upscale)
    min_frames: int = 8             # fewer usable frames than this is an error
    dark_threshold: float = 16.0    # frames with mean grey level below this (0..255) are dropped
    blur_ratio: float = 0.2         # less sharp than this x the local 75th percentile: blurred (0 = keep all;
    #                                 views of plain sides of the test orbit go down to 0.33, sigma 1.5 blur to 0.08)
    duplicate_threshold: float = 1.5  # mean abs grey difference (0..255) of thumbnails below this = duplicate
    exclude: list[str] = field(default_factory=list)  # photo folder: file names to leave out
    jpeg_quality: int = 95
