"""benchmarks/supersampling.py: one sample per pixel widens a thin object's mask more than a thick one's, and more
samples per pixel bring the mask to the finely sampled one."""
from __future__ import annotations

import numpy as np

from benchmarks.supersampling import mask_agreement
from stages.lib.gaussians.model import Gaussians
from stages.records.extract import ExtractRecord
from tests.factories.splats import make_blob

STANDING = ExtractRecord(np.array([0.0, 0.0, 1.0]), np.zeros(3), 2.0)  # make_blob's frame: z up, 2 units tall


def thin_stick(radius: float = 0.04, seed: int = 0) -> Gaussians:
    """An opaque vertical stick of Gaussians, 2 model units tall, `radius` wide (a leaf's stem)."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(0.0, 2.0, 400)
    angle = rng.uniform(0.0, 2 * np.pi, 400)
    r = radius * np.sqrt(rng.uniform(0.0, 1.0, 400))
    points = np.stack([r * np.cos(angle), r * np.sin(angle), z], axis=1)  # [400, 3]
    g = Gaussians.from_points(points, np.full((400, 3), 0.5), sh_degree=0)
    g.opacity_logits[:] = 4.0
    return g


def test_one_sample_per_pixel_widens_a_thin_object_more():
    thick = mask_agreement(make_blob(), STANDING, 60)
    thin = mask_agreement(thin_stick(), STANDING, 60)
    assert thin[1]["area_ratio"] > thick[1]["area_ratio"] > 1.0
    assert thin[1]["iou"] < thick[1]["iou"] < 1.0
    for result in (thick, thin):
        assert result[1]["iou"] < result[2]["iou"] <= result[4]["iou"] <= 1.0
