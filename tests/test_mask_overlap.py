"""Tests of disjoint masks across classes (stages/lib/masks/overlap.py)."""
import pytest
import torch

from stages.eval.spec import EvalConfig
from stages.lib.masks.overlap import separate_classes

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def neighbours() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A plant whose mask takes in the vase beside it, and the vase: probability [2, 8, 12], scores [2], labels [2].

    Columns 0-5 are the plant's (0.9 in its mask), columns 6-11 the vase's: the plant's mask claims them at 0.7,
    the vase's at 0.95; the vase's mask reaches one column into the plant at 0.6. The plant's mask is the larger.
    """
    probability = torch.zeros(2, 8, 12)
    probability[0, :, :6] = 0.9
    probability[0, :, 6:] = 0.7
    probability[1, :, 6:] = 0.95
    probability[1, :, 5] = 0.6
    return probability, torch.tensor([0.9, 0.8]), torch.tensor([1, 2])


def test_the_spilt_mask_gives_the_neighbour_back():
    probability, scores, labels = neighbours()
    separated = separate_classes(probability, scores, labels, 0.5, 0.5)
    assert (separated[0, :, :6] == 0.9).all() and (separated[0, :, 6:] == 0).all()  # the plant gives the vase back
    assert torch.equal(separated[1], probability[1])  # the larger plant takes nothing, though surer of column 5


def test_the_surer_of_two_masks_of_one_size_takes_the_pixel():
    probability = torch.zeros(2, 4, 8)
    probability[0, :, :5] = torch.tensor([0.9, 0.9, 0.9, 0.9, 0.55])
    probability[1, :, 3:] = torch.tensor([0.6, 0.8, 0.9, 0.9, 0.9])
    separated = separate_classes(probability, torch.tensor([0.9, 0.9]), torch.tensor([1, 2]), 0.5, 0.5)
    assert torch.equal(separated > 0.5, torch.tensor([[1, 1, 1, 1, 0, 0, 0, 0], [0, 0, 0, 0, 1, 1, 1, 1]]).bool()[:, None]
                       .expand(2, 4, 8))


def test_an_unsure_detection_takes_nothing_and_can_lose_pixels():
    probability, _, labels = neighbours()
    unsure_vase = separate_classes(probability, torch.tensor([0.9, 0.3]), labels, 0.5, 0.5)
    assert torch.equal(unsure_vase, probability)
    unsure_plant = separate_classes(probability, torch.tensor([0.3, 0.9]), labels, 0.5, 0.5)
    assert (unsure_plant[0, :, 6:] == 0).all() and (unsure_plant[0, :, :6] == 0.9).all()


def test_the_same_class_keeps_its_overlaps():
    probability, scores, _ = neighbours()
    assert torch.equal(separate_classes(probability, scores, torch.tensor([1, 1]), 0.5, 0.5), probability)
    one = probability[:1]
    assert separate_classes(one, scores[:1], torch.tensor([1]), 0.5, 0.5) is one
    none = torch.zeros(0, 8, 12)
    assert separate_classes(none, torch.zeros(0), torch.zeros(0, dtype=torch.int64), 0.5, 0.5) is none


def test_it_equals_comparing_every_pair():
    generator = torch.Generator().manual_seed(0)
    probability = torch.zeros(7, 16, 20)
    for k in range(7):  # masks of different sizes, overlapping
        y, x = torch.randint(0, 8, (2,), generator=generator).tolist()
        h, w = torch.randint(3, 9, (2,), generator=generator).tolist()
        probability[k, y:y + h, x:x + w] = torch.rand(h, w, generator=generator)
    scores = torch.rand(7, generator=generator)
    labels = torch.randint(1, 4, (7,), generator=generator)
    masks = probability > 0.5
    areas = masks.sum(dim=(1, 2))
    expected = probability.clone()
    for i in range(7):
        for j in range(7):
            if labels[j] != labels[i] and scores[j] >= 0.4 and areas[j] <= areas[i]:
                expected[i][masks[i] & (probability[j] > probability[i])] = 0.0
    separated = separate_classes(probability, scores, labels, 0.5, 0.4)
    assert torch.equal(separated, expected) and not torch.equal(separated, probability)


def test_the_owner_score_is_a_probability():
    assert EvalConfig(mask_owner_score=None).mask_owner_score is None
    for wrong in (-0.1, 1.5):
        with pytest.raises(ValueError, match="mask_owner_score"):
            EvalConfig(mask_owner_score=wrong)
