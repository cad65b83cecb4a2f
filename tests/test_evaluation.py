"""Evaluation helpers of the benchmarks (benchmarks/lib/evaluation.py)."""
from __future__ import annotations

import numpy as np
import pytest

from benchmarks.lib.evaluation import umeyama_similarity


def test_umeyama_recovers_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 3))
    rotation, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    rotation *= np.sign(np.linalg.det(rotation))
    dst = 2.5 * src @ rotation.T + np.array([1.0, -2.0, 0.5])
    scale, est_rotation, translation = umeyama_similarity(src, dst)
    assert scale == pytest.approx(2.5)
    np.testing.assert_allclose(est_rotation, rotation, atol=1e-9)
    np.testing.assert_allclose(translation, [1.0, -2.0, 0.5], atol=1e-9)
