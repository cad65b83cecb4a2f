"""Tests of stages/lib/objects/silhouettes.py: distances outside a rendered body's silhouette, colours against the
background."""
from __future__ import annotations

import numpy as np
import pytest

from stages.lib.geometry import look_at_viewmat
from stages.lib.objects.silhouettes import GaussianArrays, Intrinsics, haze_scores

SIGMA = 0.1  # m: the body, one round Gaussian at the origin
RADIUS = SIGMA * np.sqrt(2 * np.log(0.99 / 0.5))  # m: where its alpha (opacity 0.99) falls to 0.5
GREY = [0.7, 0.7, 0.7]  # the background wall's colour


def _gaussian(mean: list[float], scales: list[float], color: list[float]) -> GaussianArrays:
    return GaussianArrays(np.array([mean], dtype=float), np.array([[1.0, 0.0, 0.0, 0.0]]), np.array([scales], dtype=float),
                          np.array([0.99]), np.array([color], dtype=float))


def _scores(points: np.ndarray, colors: np.ndarray, width: int = 256):
    viewmat = look_at_viewmat(np.array([0.0, -2.0, 0.0]), np.zeros(3))[None]  # [1, 4, 4] 2 m away, looking along +y
    K = np.array([[200.0, 0.0, width / 2], [0.0, 200.0, width / 2], [0.0, 0.0, 1.0]])
    body = _gaussian([0.0, 0.0, 0.0], [SIGMA] * 3, [0.8, 0.5, 0.2])
    wall = _gaussian([0.0, 1.0, 0.0], [3.0, 0.01, 3.0], GREY)  # behind the body, filling the view
    intrinsics = Intrinsics(K[None], np.array([[width, width]]))
    return (haze_scores(points, colors, body, wall, viewmat, intrinsics, min_outside=0.02),
            haze_scores(points, colors, body, wall, viewmat, intrinsics.scaled(width // 2), min_outside=0.02))


def test_distances_outside_one_gaussian_body():
    points = np.array([[0.05, 0.0, 0.0], [0.3, 0.0, 0.0], [0.0, 0.0, -0.5], [0.3, 0.5, 0.0], [5.0, 0.0, 0.0],
                       [0.0, -3.0, 0.0]])
    scores, halved = _scores(points, np.tile(GREY, (len(points), 1)))
    pixel = 2.0 / 200.0  # m per pixel at the body's depth
    distances = scores.outside
    assert distances[0] == 0.0  # inside the silhouette
    assert distances[1] == pytest.approx(0.3 - RADIUS, abs=1.5 * pixel)
    assert distances[2] == pytest.approx(0.5 - RADIUS, abs=1.5 * pixel)
    # 0.5 m farther: 0.3 m off-axis projects like 0.24 m at the body's depth, and pixels are 2.5 / 2 larger there
    assert distances[3] == pytest.approx((0.3 * 2.0 / 2.5 - RADIUS) * 2.5 / 2.0, abs=2 * pixel)
    assert distances[4] == 0.0 and distances[5] == 0.0  # outside the image, behind the camera: no view counts
    assert halved.outside[1] == pytest.approx(distances[1], abs=3 * pixel)


def test_colour_difference_to_the_background_where_outside():
    points = np.array([[0.3, 0.0, 0.0], [0.3, 0.0, 0.0], [0.0, 0.0, 0.05]])
    colors = np.array([GREY, [0.2, 0.7, 0.2], GREY])  # wall-coloured haze, a green leaf, inside the body
    scores, _ = _scores(points, colors)
    assert scores.colour_difference[0] < 0.05
    assert scores.colour_difference[1] == pytest.approx(0.5, abs=0.05)
    assert np.isnan(scores.colour_difference[2])  # never beyond min_outside: no view to compare in
