"""benchmarks/wall_capture.py's scene: an object hung on a wall of a sample room, seen in every frame of a half
orbit in front of it, with no floor in view (the capture extract must refuse: the benchmark runs the chain)."""
from __future__ import annotations

import numpy as np
import pytest

from benchmarks.wall_capture import free_spot_on_wall, wall_capture_frames


def test_the_object_fills_every_frame_of_the_half_orbit():
    frames, masks = wall_capture_frames("vase", 0.22, seed=2, width=80, height=60, num_frames=6, supersample=1)
    assert len(frames) == 6 and frames[0].shape == (60, 80, 3) and frames[0].dtype == np.uint8
    shares = [mask.mean() for mask in masks]
    assert min(shares) > 0.05 and max(shares) < 0.6  # the object in view, the wall around it


def test_a_wall_spot_keeps_clear_of_furniture():
    cabinet = np.array([[2.0, -0.5, 0.0], [2.5, 0.5, 0.9]])  # against the wall x = 2.5, around y = 0
    y = free_spot_on_wall([cabinet], wall_x=2.5, half_y=2.0)
    assert abs(y) >= 1.1  # 0.6 m of room on either side of the spot, past the cabinet's 0.5
    with pytest.raises(ValueError, match="no free spot"):
        free_spot_on_wall([np.array([[1.0, -3.0, 0.0], [2.5, 3.0, 2.5]])], wall_x=2.5, half_y=2.0)
