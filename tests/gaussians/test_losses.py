"""The training loss's stacked SSIM (the path on a GPU and for other dtypes) against kornia's SSIM, values and
gradients to both images."""
from __future__ import annotations

import pytest
import torch

from stages.lib.gaussians.losses import photometric_loss_stacked
from tests.factories.reference_losses import photometric_loss_reference


@pytest.mark.parametrize("size", [(48, 64), (6, 9), (33, 6)])
@pytest.mark.parametrize("noise", [1.0, 0.05])  # unrelated images; a close render of its photo
def test_stacked_loss_is_kornias(size, noise):
    gen = torch.Generator().manual_seed(5)
    photo = torch.rand(*size, 3, generator=gen, dtype=torch.float64)
    render_ = (photo + noise * torch.randn(*size, 3, generator=gen, dtype=torch.float64)).clamp(0, 1)
    values, grads = [], []
    for loss_fn in (photometric_loss_reference, photometric_loss_stacked):
        prediction = render_.clone().requires_grad_()
        target = photo.clone().requires_grad_()
        loss = loss_fn(prediction, target, 0.2)
        values.append(loss.detach())
        grads.append(torch.autograd.grad(loss * 3.0, (prediction, target)))
    torch.testing.assert_close(values[1], values[0], rtol=1e-12, atol=1e-13)
    for ours, kornias in zip(grads[1], grads[0]):
        torch.testing.assert_close(ours, kornias, rtol=1e-9, atol=1e-12)
