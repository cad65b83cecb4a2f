"""The sfm stage's spec: how COLMAP poses the frames (`frames`, a frames output folder)."""
from __future__ import annotations

from dataclasses import dataclass

from stages.contract.choices import choices
from stages.contract.inputs import Input, Inputs


Matching = choices("Matching", ("auto", "sequential", "exhaustive"))  # sfm.matching


# sfm.camera_model: COLMAP's perspective models, which undistort_images maps to the PINHOLE frames splat_train reads
CameraModel = choices("CameraModel", ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV", "SIMPLE_PINHOLE", "PINHOLE"))


INPUTS = Inputs((Input("frames"),))


@dataclass
class SfmConfig:
    matching: Matching = Matching.auto
    exhaustive_max_images: int = 40        # "auto" matches exhaustively up to this many frames
    sequential_overlap: int = 10           # each frame is matched with the next `overlap` frames
    loop_closure_frames: int = 5           # first k frames are matched with the last k (orbit closes)
    quadratic_overlap: bool = True         # sequential: also frame i with i + 2^k beyond the window (COLMAP's default)
    guided_matching: bool = False          # match again guided by each pair's two-view geometry: registers captures
    #                                        that break in two at the first attempt, but costs 1.2-2.2x the SfM time
    first_octave: int = 0                  # SIFT first octave: 0 ~5x faster than -1, accurate enough
    peak_threshold: float = 0.0066667      # SIFT peak threshold (COLMAP default)
    camera_model: CameraModel = CameraModel.SIMPLE_RADIAL  # model refined when intrinsics are unknown
    intrinsics: list[float] | None = None  # known [fx, fy, cx, cy] in source-video pixels (PINHOLE, fixed)
    robust_fallback: bool = True           # retry with the robust option set when too few frames register
    robust_below_ratio: float = 0.9        # ... i.e. when registered / total is below this
    robust_first_octave: int = 0           # robust SIFT first octave (-1: ~2.4x the points, ~4x slower)
    min_registered_ratio: float = 0.7      # quality gate
    max_reprojection_error_px: float = 2.0  # quality gate
    min_frames: int = 3
    num_threads: int = 1                   # 1: bit-reproducible (pycolmap with more threads is not); 0 = all cores
