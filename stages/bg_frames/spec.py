"""The bg_frames stage's spec: how a background video (`video`) becomes frame slots, each a background photo, and
the per-frame depth (`depth`: a folder of one depth file per video frame, the sample's walk) that goes with them."""
from __future__ import annotations

from dataclasses import dataclass

from stages.contract.errors import StageError
from stages.contract.inputs import Input, Inputs

INPUTS = Inputs((Input("video", raw="video"), Input("depth", required=False)))


@dataclass
class BgFramesConfig:
    count: int = 20                 # frame slots per video (fewer when its header states fewer frames): at most this
    #                                 many frames are chosen, one per window of equal camera motion
    motion_step: float = 0.015      # windows of at least this much feature motion (a fraction of the image diagonal):
    #                                 a camera that hardly moves fills fewer slots
    analysis_fps: float = 10.0      # frames analysed per second of video (a 30 fps video: every third frame)
    analysis_side: int = 640        # sharpness and motion are measured on frames downscaled to this long side; the
    #                                 chosen frames are written at the video's own size
    dark_threshold: float = 16.0    # frames with a mean grey level below this (0..255) are not chosen
    blur_ratio: float = 0.2         # less sharp than this x the local 75th percentile: blurred (0 = keep all)
    duplicate_threshold: float = 1.5  # mean abs grey difference (0..255) of thumbnails below this = near-duplicate

    def __post_init__(self) -> None:
        if self.count < 1 or self.analysis_side < 32 or self.motion_step <= 0 or self.analysis_fps <= 0:
            raise StageError(f"bg_frames: need count >= 1, analysis_side >= 32, motion_step > 0 and analysis_fps > 0, "
                             f"got {self.count}, {self.analysis_side}, {self.motion_step} and {self.analysis_fps}")
