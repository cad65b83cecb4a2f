"""The C++ twins of the training step's PyTorch parts (projection, binning, SH colours, photometric loss) give the
PyTorch results, and a whole training step's gradients are the same bits for any thread count."""
from __future__ import annotations

import pytest
import torch

from stages.lib.gaussians.binning import bin_gaussians
from stages.lib.gaussians.losses import photometric_loss
from stages.lib.gaussians.model import Gaussians
from stages.lib.gaussians.projection import project_gaussians
from stages.lib.gaussians.rasterize import gaussian_colors, render
from tests.factories.raster import camera, needs_cpp, random_scene, requiring_grad
from tests.factories.reference_losses import photometric_loss_reference


def awkward_scene(seed: int) -> Gaussians:
    """Random Gaussians in front of an identity camera, plus the cases the projection treats apart: behind the
    near plane, far outside the view (the Jacobian's clamp), too faint to reach 1/255, unnormalised quaternions."""
    g = random_scene(400, seed=seed, sh_degree=3)
    means = g.means.clone()
    means[:20, 2] = -0.5  # behind the camera
    means[20:40, 0] = 40.0  # far right: clamped
    means[40:60, 1] = -35.0  # far up: clamped
    logits = g.opacity_logits.clone()
    logits[60:80] = -9.0  # opacity < 1/255: invisible
    return Gaussians(means, g.log_scales, g.quats * 2.5, logits, g.sh)


def test_cpp_projection_matches_torch():
    from stages.lib.gaussians.native import project_gaussians_cpp

    needs_cpp()
    width, height = 80, 60
    viewmat, K = camera(width, height, 70.0)
    g = awkward_scene(seed=11)
    results = []
    for project in (project_gaussians, project_gaussians_cpp):
        means, quats, scales = (t.detach().clone().requires_grad_() for t in (g.means, g.quats, g.scales))
        proj = project(means, quats, scales, g.opacities, viewmat, K, width, height)
        gen = torch.Generator().manual_seed(5)
        loss = ((proj.means2d * torch.randn(proj.means2d.shape, generator=gen)).sum()
                + (proj.conics * torch.randn(proj.conics.shape, generator=gen)).sum()
                + (proj.depths * torch.randn(proj.depths.shape, generator=gen)).sum())
        results.append((proj, torch.autograd.grad(loss, (means, quats, scales))))
    (ref, ref_grads), (fast, fast_grads) = results
    visible = ref.radii > 0
    assert 0 < int(visible.sum()) < 340 and torch.equal(ref.radii, fast.radii)
    for name in ("means2d", "conics", "depths", "extents"):
        torch.testing.assert_close(getattr(fast, name)[visible], getattr(ref, name)[visible], rtol=1e-4, atol=1e-4)
    for a, b in zip(fast_grads, ref_grads):
        assert b.abs().sum() > 0
        assert ((a - b).norm() / b.norm()).item() < 1e-4


def test_cpp_binning_equals_torch():
    from stages.lib.gaussians.native import bin_gaussians_cpp

    needs_cpp()
    width, height = 100, 70
    viewmat, K = camera(width, height, 60.0)
    g = awkward_scene(seed=12)
    proj = project_gaussians(g.means, g.quats, g.scales, g.opacities, viewmat, K, width, height)
    ref, fast = bin_gaussians(proj, width, height), bin_gaussians_cpp(proj, width, height)
    assert ref.gauss_ids.numel() > proj.radii.gt(0).sum()  # Gaussians reach several tiles
    assert (ref.tiles_x, ref.tiles_y) == (fast.tiles_x, fast.tiles_y)
    assert torch.equal(ref.offsets, fast.offsets) and torch.equal(ref.gauss_ids, fast.gauss_ids)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_cpp_sh_colours_match_torch(degree):
    needs_cpp()
    viewmat = torch.eye(4)
    viewmat[:3, 3] = torch.tensor([0.3, -0.2, 0.5])
    results = []
    for backend in ("torch", "cpp"):
        scene = awkward_scene(seed=13)
        g = requiring_grad(Gaussians(scene.means, scene.log_scales, scene.quats, scene.opacity_logits, 4 * scene.sh))
        colours = gaussian_colors(g, viewmat, sh_degree=degree, backend=backend)
        weights = torch.randn(colours.shape, generator=torch.Generator().manual_seed(3))
        grads = torch.autograd.grad((colours * weights).sum(), (g.sh, g.means), allow_unused=True)
        results.append((colours, [torch.zeros_like(g.means) if x is None else x for x in grads]))
    (ref, ref_grads), (fast, fast_grads) = results
    assert (ref == 0).any() and (ref > 0).any()  # both sides of the clamp at 0
    torch.testing.assert_close(fast, ref, rtol=1e-5, atol=1e-6)
    for a, b in zip(fast_grads, ref_grads):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("size", [(48, 64), (7, 9)])
@pytest.mark.parametrize("noise", [1.0, 0.05])  # unrelated images; a close render of its photo
def test_fused_loss_matches_kornia(size, noise):
    needs_cpp()
    gen = torch.Generator().manual_seed(4)
    photo = torch.rand(*size, 3, generator=gen)
    render_ = (photo + noise * torch.randn(*size, 3, generator=gen)).clamp(0, 1) if noise < 1 else torch.rand(
        *size, 3, generator=gen)
    values, grads = [], []
    for loss_fn in (photometric_loss_reference, photometric_loss):
        prediction = render_.clone().requires_grad_()
        loss = loss_fn(prediction, photo, 0.2)
        values.append(loss.detach())
        grads.append(torch.autograd.grad(loss * 3.0, prediction)[0])  # a scaled upstream gradient
    assert values[1].dtype == torch.float32
    torch.testing.assert_close(values[1], values[0], rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-4, atol=1e-6 * grads[0].abs().max().item())


def test_a_training_step_gives_the_same_bits_for_any_thread_count():
    """Projection, binning, SH colours, compositor and loss on the CPU: 1, 2 and 3 threads give the same loss and
    gradients, bit for bit (one splat_train cache key, one model)."""
    needs_cpp()
    width, height = 96, 80
    viewmat, K = camera(width, height, 70.0)
    scene = random_scene(1500, seed=8, sh_degree=3)
    photo = torch.rand(height, width, 3, generator=torch.Generator().manual_seed(9))
    threads_before = torch.get_num_threads()
    runs = []
    try:
        for threads in (1, 2, 3):
            torch.set_num_threads(threads)
            g = requiring_grad(scene)
            out = render(g, viewmat, K, width, height, backend="cpp")
            loss = photometric_loss(out.rgb, photo, 0.2)
            loss.backward()
            runs.append([loss.detach(), g.means.grad, g.log_scales.grad, g.quats.grad, g.opacity_logits.grad,
                         g.sh.grad])
    finally:
        torch.set_num_threads(threads_before)
    assert all(t.abs().sum() > 0 for t in runs[0][1:])
    for other in runs[1:]:
        assert all(torch.equal(a, b) for a, b in zip(runs[0], other))
