"""Tests of the eval masks' guided refinement (stages/lib/masks/refine.py)."""
import kornia
import pytest
import torch

from stages.eval.spec import EvalConfig
from stages.lib.dataset_formats.polygons import mask_box
from stages.lib.masks.box import tensor_mask_box
from stages.lib.masks.refine import refine_masks, refine_radius

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def iou(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a & b).sum() / (a | b).sum())


def leaf_scene(size: int = 64) -> tuple[torch.Tensor, torch.Tensor]:
    """A green bar 3 px wide across a grey photo: image [3, H, W] in [0, 1], its true mask [H, W] bool."""
    truth = torch.zeros(size, size, dtype=torch.bool)
    truth[20:44, 30:33] = True
    image = torch.full((3, size, size), 0.5)
    image[:, truth] = torch.tensor([0.2, 0.7, 0.2])[:, None]
    return image, truth


def coarse(mask: torch.Tensor, sigma: float) -> torch.Tensor:
    """The mask as a coarse head predicts it: Gaussian-blurred, [1, H, W] in [0, 1]."""
    size = int(4 * sigma) | 1
    return kornia.filters.gaussian_blur2d(mask[None, None].float(), size, (sigma, sigma))[0]


def test_a_blurred_thin_mask_moves_onto_the_photos_edge():
    image, truth = leaf_scene()
    probability = coarse(truth, 2.0) * 1.6  # a head sure of the bar's middle, unsure of its edges
    before = iou(probability[0] > 0.5, truth)
    after = iou(refine_masks(image, probability.clamp(0, 1), 4, 3e-4)[0] > 0.5, truth)
    assert before < 0.75 and after > 0.95


def test_on_a_flat_photo_the_filter_smooths_the_mask_with_its_window():
    disc = torch.zeros(64, 64, dtype=torch.bool)
    yy, xx = torch.meshgrid(torch.arange(64), torch.arange(64), indexing="ij")
    disc[(yy - 32) ** 2 + (xx - 32) ** 2 < 15 ** 2] = True
    probability = coarse(disc, 1.5)
    refined = refine_masks(torch.full((3, 64, 64), 0.5), probability, 4, 3e-4)
    twice_boxed = kornia.filters.box_blur(kornia.filters.box_blur(probability[None], 9), 9)[0]  # no colour edge to follow
    assert torch.allclose(refined, twice_boxed, atol=1e-4)
    assert iou(refined[0] > 0.5, disc) > 0.9


def test_filtering_around_each_mask_equals_filtering_the_whole_photo():
    generator = torch.Generator().manual_seed(0)
    image = torch.rand(3, 48, 64, generator=generator)
    probability = torch.zeros(3, 48, 64)
    probability[0, 10:30, 20:40] = torch.rand(20, 20, generator=generator)
    probability[1, 0:12, 50:64] = torch.rand(12, 14, generator=generator)  # at the photo's border
    refined = refine_masks(image, probability, 3, 1e-3)
    whole = kornia.filters.guided_blur(image[None].expand(3, -1, -1, -1), probability[:, None], 7, 1e-3)[:, 0]
    assert torch.allclose(refined, whole.clamp(0, 1), atol=1e-5)
    assert (refined[0, 10:30, 20:40] != probability[0, 10:30, 20:40]).any() and not refined[2].any()  # an empty mask
    assert refine_masks(image, probability, 0, 1e-3) is probability


def test_the_radius_is_set_at_the_detectors_scale():
    assert refine_radius(6.0, (480, 640), 512) == 8
    assert refine_radius(6.0, (3000, 4000), 512) == 47
    assert refine_radius(0.0, (480, 640), 512) == 0
    with pytest.raises(ValueError, match="mask_refine_radius"):
        EvalConfig(mask_refine_radius=-1.0)
    with pytest.raises(ValueError, match="mask_refine_eps"):
        EvalConfig(mask_refine_eps=0.0)



def test_the_tensor_mask_box_is_the_numpy_one():
    generator = torch.Generator().manual_seed(1)
    for _ in range(5):
        mask = torch.rand(20, 30, generator=generator) > 0.97
        assert tensor_mask_box(mask) == mask_box(mask.numpy())
        assert tensor_mask_box(mask.float() * 0.3) == mask_box(mask.numpy())  # nonzero probabilities
    assert tensor_mask_box(torch.zeros(4, 5)) is None
