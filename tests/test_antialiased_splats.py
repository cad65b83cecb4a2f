"""The antialiased mode the splat benchmark trains with (benchmarks/antialiased_splats.py): each Gaussian's opacity
scaled by sqrt(det(cov2d) / det(cov2d + 0.3 I)), so a sub-pixel Gaussian draws fainter and a large one as before."""
import numpy as np
import torch

from benchmarks.antialiased_splats import LOW_PASS, antialiased, compensation
from stages.lib.gaussians.rasterize import rasterize


def test_the_factor_is_the_unfiltered_over_the_filtered_area():
    variances = torch.tensor([0.05, 1.0, 30.0])  # px^2, isotropic
    conics = torch.stack([1 / (variances + LOW_PASS), torch.zeros(3), 1 / (variances + LOW_PASS)], dim=-1)  # [3, 3]
    assert torch.allclose(compensation(conics), variances / (variances + LOW_PASS), rtol=1e-4)


def peak_alpha(scale: float) -> float:
    """Alpha at the image centre of one opaque isotropic Gaussian of world `scale` 1 m in front of a 64 px camera."""
    K = torch.tensor([[64.0, 0.0, 32.0], [0.0, 64.0, 32.0], [0.0, 0.0, 1.0]])
    out = rasterize(torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
                    torch.full((1, 3), scale), torch.tensor([0.99]), torch.ones(1, 3), torch.eye(4), K, 64, 64)
    return float(out.alpha[32, 32])


def test_a_subpixel_gaussian_draws_fainter_and_a_large_one_as_before():
    tiny, large = 0.002, 0.1  # 0.13 px and 6.4 px standard deviations
    plain = peak_alpha(tiny), peak_alpha(large)
    with antialiased():
        filtered = peak_alpha(tiny), peak_alpha(large)
    assert filtered[0] < 0.5 * plain[0]
    assert np.isclose(filtered[1], plain[1], rtol=0.01)
    assert (peak_alpha(tiny), peak_alpha(large)) == plain  # the plain rasterizer is back
