"""Tests of the Gaussian rasterizer: closed form, finite differences, C++ vs PyTorch, options."""
from __future__ import annotations

import math

import pytest
import torch

from stages.lib.gaussians.model import Gaussians
from stages.lib.gaussians.rasterize import rasterize, render
from stages.lib.gaussians.sh import C0
from tests.factories.raster import camera, needs_cpp, random_scene, requiring_grad

BACKGROUND = (0.2, 0.4, 0.6)


@pytest.mark.parametrize("backend", ["torch", "cpp"])
def test_single_gaussian_matches_closed_form(backend):
    if backend == "cpp":
        needs_cpp()
    width, height, focal, z = 40, 30, 50.0, 2.0
    viewmat, K = camera(width, height, focal)
    sigma = torch.tensor([0.08, 0.05, 0.1])
    opacity, colour = 0.7, torch.tensor([0.9, 0.5, 0.1])
    out = rasterize(torch.tensor([[0.0, 0.0, z]]), torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
                    sigma[None], torch.tensor([opacity]), colour[None], viewmat, K, width, height,
                    background=torch.tensor(BACKGROUND), backend=backend)
    # Axis-aligned Gaussian on the optical axis: 2D covariance diag((f s / z)^2 + 0.3).
    var_x, var_y = (focal * sigma[0] / z) ** 2 + 0.3, (focal * sigma[1] / z) ** 2 + 0.3
    u = torch.arange(width) + 0.5 - K[0, 2]
    v = torch.arange(height) + 0.5 - K[1, 2]
    expected = opacity * torch.exp(-0.5 * (u[None, :] ** 2 / var_x + v[:, None] ** 2 / var_y))
    expected = torch.where(expected >= 1 / 255, expected, torch.zeros_like(expected))
    assert expected.max() > 0.6 and (expected == 0).any()
    torch.testing.assert_close(out.alpha, expected, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(out.depth, z * expected, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(
        out.rgb, expected[..., None] * colour + (1 - expected[..., None]) * torch.tensor(BACKGROUND),
        atol=1e-5, rtol=1e-5)
    assert out.radii.tolist() == [math.ceil(3 * math.sqrt(max(var_x, var_y)))]
    torch.testing.assert_close(out.means2d.detach(), K[:2, 2][None])


def test_gradients_match_finite_differences():
    width, height = 14, 12
    viewmat, K = camera(width, height, 14.0, torch.float64)
    g = random_scene(4, seed=3, dtype=torch.float64, sh_degree=1)
    background = torch.tensor(BACKGROUND, dtype=torch.float64)

    def images(means, log_scales, quats, opacity_logits, sh):
        out = render(Gaussians(means, log_scales, quats, opacity_logits, sh), viewmat, K, width,
                     height, background=background, backend="torch")
        return out.rgb, out.alpha, out.depth

    inputs = tuple(t.clone().requires_grad_() for t in
                   (g.means, g.log_scales, g.quats, g.opacity_logits, g.sh))
    assert images(*inputs)[1].max() > 0.5
    assert torch.autograd.gradcheck(images, inputs, eps=1e-6, atol=1e-5, rtol=1e-3)


@pytest.mark.parametrize("opacity_shift", [0.0, 4.0])  # 4.0: opaque, so pixels terminate early
def test_cpp_matches_torch(opacity_shift):
    needs_cpp()
    width, height = 72, 56
    viewmat, K = camera(width, height, 60.0)
    scene = random_scene(300, seed=7, opacity_shift=opacity_shift)
    results = {}
    for backend in ("torch", "cpp"):
        g = requiring_grad(scene)
        out = render(g, viewmat, K, width, height, background=torch.tensor(BACKGROUND),
                     backend=backend)
        weights = torch.rand(height, width, 5, generator=torch.Generator().manual_seed(0))
        loss = ((out.rgb * weights[..., :3]).sum() + (out.alpha * weights[..., 3]).sum()
                + (out.depth * weights[..., 4]).sum())
        loss.backward()
        results[backend] = [out.rgb, out.alpha, out.depth, out.means2d.grad, g.means.grad,
                            g.log_scales.grad, g.quats.grad, g.opacity_logits.grad, g.sh.grad]
    assert results["torch"][1].max() > (0.999 if opacity_shift else 0.9)  # 0.999: T near the 1e-4 stop
    for ref, fast in zip(results["torch"][:3], results["cpp"][:3]):
        torch.testing.assert_close(fast, ref, atol=1e-5, rtol=1e-4)
    for ref, fast in zip(results["torch"][3:], results["cpp"][3:]):
        assert ref.abs().sum() > 0
        assert ((fast - ref).norm() / ref.norm()).item() < 1e-4


def test_cpp_matches_torch_on_thin_tilted_gaussians_on_black():
    """The C++ compositor skips the rows of a Gaussian's tile box that its ellipse's slice passes beside, and on a
    black background (no gradient reaches the final transmittance) the division that gradient needs; the PyTorch
    twin evaluates every pixel of the box: a pixel the C++ side left out would differ by 1/255 of a colour."""
    needs_cpp()
    width, height = 80, 64
    viewmat, K = camera(width, height, 70.0)
    scene = random_scene(400, seed=11, needles=True, opacity_shift=1.0)
    results = {}
    for backend in ("torch", "cpp"):
        g = requiring_grad(scene)
        out = render(g, viewmat, K, width, height, backend=backend)
        weights = torch.rand(height, width, 3, generator=torch.Generator().manual_seed(0)) - 0.5
        (out.rgb * weights).sum().backward()
        results[backend] = [out.rgb, g.means.grad, g.log_scales.grad, g.quats.grad, g.opacity_logits.grad, g.sh.grad]
    assert 0.5 < (results["torch"][0].sum(-1) > 0).float().mean() < 1.0  # needles cover some of the image, not all
    torch.testing.assert_close(results["cpp"][0], results["torch"][0], atol=1e-5, rtol=1e-4)
    for ref, fast in zip(results["torch"][1:], results["cpp"][1:]):
        assert ref.abs().sum() > 0
        assert ((fast - ref).norm() / ref.norm()).item() < 1e-4


def test_cpp_gradients_are_the_same_bits_for_any_thread_count():
    """The backward sums each Gaussian's tile contributions in tile-list order: 1, 2 and 3 threads (and a
    rerun) give bit-identical gradients, so one splat_train cache key gives one model."""
    needs_cpp()
    from stages.lib.gaussians.binning import bin_gaussians
    from stages.lib.gaussians.native import rasterize_tiles_cpp
    from stages.lib.gaussians.projection import project_gaussians

    width, height = 96, 80
    viewmat, K = camera(width, height, 70.0)
    scene = random_scene(2000, seed=3)
    proj = project_gaussians(scene.means, scene.quats, scene.scales, scene.opacities, viewmat, K, width, height)
    bins = bin_gaussians(proj, width, height)
    weights = torch.rand(height, width, 4, generator=torch.Generator().manual_seed(1))
    features = torch.rand(scene.num, 4, generator=torch.Generator().manual_seed(2))
    threads_before = torch.get_num_threads()
    grads = []
    try:
        for threads in (1, 2, 3, 2):
            torch.set_num_threads(threads)
            inputs = [t.detach().clone().requires_grad_() for t in (proj.means2d, proj.conics, scene.opacities, features)]
            image, trans = rasterize_tiles_cpp(*inputs, bins, width, height)
            ((image * weights).sum() + trans.sum()).backward()
            grads.append([t.grad for t in inputs])
    finally:
        torch.set_num_threads(threads_before)
    assert all(g.abs().sum() > 0 for g in grads[0])
    for other in grads[1:]:
        assert all(torch.equal(a, b) for a, b in zip(grads[0], other))


def test_white_override_colours_give_alpha():
    width, height = 32, 24
    viewmat, K = camera(width, height, 30.0)
    out = render(random_scene(50, seed=1), viewmat, K, width, height,
                 colors=torch.ones(3), backend="torch")
    assert out.alpha.max() > 0.5
    torch.testing.assert_close(out.rgb, out.alpha[..., None].expand(-1, -1, 3))


@pytest.mark.parametrize("sh_degree", [0, 2])
def test_sh_view_dir(sh_degree):
    width, height = 16, 16
    viewmat, K = camera(width, height, 20.0)
    g = Gaussians(means=torch.tensor([[0.0, 0.0, 2.0]]), log_scales=torch.full((1, 3), -2.5),
                  quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]), opacity_logits=torch.tensor([2.0]),
                  sh=torch.full((1, (sh_degree + 1) ** 2, 3), 0.3))
    default = render(g, viewmat, K, width, height, backend="torch").rgb
    along_view = render(g, viewmat, K, width, height, sh_view_dir=torch.tensor([0.0, 0.0, 5.0]),
                        backend="torch").rgb
    sideways = render(g, viewmat, K, width, height, sh_view_dir=torch.tensor([1.0, 0.0, 0.0]),
                      backend="torch").rgb
    torch.testing.assert_close(along_view, default)  # the real view direction is +z
    if sh_degree == 0:
        torch.testing.assert_close(sideways, default)
        alpha = render(g, viewmat, K, width, height, backend="torch").alpha
        torch.testing.assert_close(default, (0.5 + C0 * 0.3) * alpha[..., None].expand(-1, -1, 3))
    else:
        assert (sideways - default).abs().max() > 0.05


def test_visibility_and_view_space_gradient():
    width, height = 32, 32
    viewmat, K = camera(width, height, 30.0)
    g = requiring_grad(Gaussians(
        means=torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, -2.0], [50.0, 0.0, 2.0]]),
        log_scales=torch.full((3, 3), -2.0), quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 3),
        opacity_logits=torch.zeros(3), sh=torch.zeros(3, 1, 3)))
    out = render(g, viewmat, K, width, height, backend="torch")
    assert out.radii[0] > 0 and out.radii[1] == 0 and out.radii[2] == 0  # behind / off screen
    (out.rgb[:, :16].sum() - out.rgb[:, 16:].sum()).backward()
    grad = out.means2d.grad
    assert grad[0, 0] < 0 and grad[1:].abs().sum() == 0  # moving right brightens the right half


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu():
    width, height = 64, 48
    viewmat, K = camera(width, height, 50.0)
    scene = random_scene(200, seed=5)
    cpu = render(scene, viewmat, K, width, height, backend="torch")
    gpu = render(scene.to("cuda"), viewmat.cuda(), K.cuda(), width, height, backend="auto")
    torch.testing.assert_close(gpu.rgb.cpu(), cpu.rgb, atol=1e-3, rtol=1e-3)
    torch.testing.assert_close(gpu.alpha.cpu(), cpu.alpha, atol=1e-3, rtol=1e-3)
