"""The gsplat backend: which backend `auto` and explicit requests give (CPU), and on a CUDA GPU with gsplat,
gsplat against our PyTorch path on the same scene (images, gradients, densification decisions)."""
from __future__ import annotations

import logging
import sys

import pytest
import torch

from stages.lib.gaussians import rasterize
from stages.lib.gaussians.losses import photometric_loss
from stages.lib.gaussians.model import Gaussians
from stages.lib.gaussians.rasterize import choose_backend, gaussian_colors, render
from stages.lib.gaussians.rasterize_gsplat import gsplat_unavailable
from stages.lib.gaussians.strategy import DensifyStrategy
from stages.lib.gaussians.train_config import TrainConfig
from stages.lib.gaussians.trainer import GaussianTrainer, TrainView, view_index
from tests.factories.splats import orbit_viewmats, random_blob_scene

CPU, CUDA = torch.device("cpu"), torch.device("cuda")  # a device object needs no GPU: the choice is plain logic
GRAD_THRESHOLD = 2e-3  # densification threshold of the 64x48 scene below
BACKGROUND = (0.2, 0.4, 0.6)


def orbit_camera(width: int, height: int, focal: float) -> tuple[torch.Tensor, torch.Tensor]:
    """A camera of the blob scenes' orbit with an off-centre principal point: (viewmat [4, 4], K [3, 3])."""
    K = torch.tensor([[focal, 0.0, 0.45 * width], [0.0, focal, 0.55 * height], [0.0, 0.0, 1.0]])
    return orbit_viewmats(5, radius=3.2, height=1.2)[1], K


def leaves(g: Gaussians) -> Gaussians:
    """A copy of `g` whose tensors are leaves requiring gradients."""
    return Gaussians(*(t.detach().clone().requires_grad_() for t in (g.means, g.log_scales, g.quats,
                                                                        g.opacity_logits, g.sh)))


needs_gsplat_gpu = pytest.mark.skipif(
    not torch.cuda.is_available() or gsplat_unavailable(CUDA, torch.float32) is not None,
    reason="no CUDA device, or gsplat cannot run here (pip install -e \".[gpu]\"; its build needs nvcc)")


@pytest.fixture
def fresh_choices(monkeypatch):
    """An empty record of backend choices, as in a new process (each choice is made and logged once)."""
    monkeypatch.setattr(rasterize, "_chosen", {})


@pytest.fixture
def without_gsplat(monkeypatch, fresh_choices):
    """`import gsplat` fails, as where the [gpu] extra is not installed (None in sys.modules: ImportError)."""
    monkeypatch.setitem(sys.modules, "gsplat", None)


# ------------------------------------------------------------------------------------------- CPU: the choice

@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_auto_on_cpu_tensors_never_picks_gsplat(fresh_choices, dtype):
    assert choose_backend("auto", CPU, dtype) in ("cpp", "torch")


def test_auto_on_cuda_tensors_picks_gsplat_when_it_imports(fresh_choices):
    pytest.importorskip("gsplat", reason="gsplat not installed (pip install -e \".[gpu]\")")
    assert choose_backend("auto", CUDA, torch.float32) == "gsplat"
    assert choose_backend("auto", CUDA, torch.float64) == "cuda"  # gsplat renders float32 only


def test_auto_on_cuda_falls_back_to_the_pytorch_path_without_gsplat(without_gsplat, caplog):
    with caplog.at_level(logging.INFO, logger="stages.lib.gaussians.rasterize"):
        assert choose_backend("auto", CUDA, torch.float32) == "cuda"
    [record] = [r for r in caplog.records if r.name == "stages.lib.gaussians.rasterize"]
    assert record.levelno == logging.WARNING
    assert "'cuda'" in record.getMessage() and "pip install" in record.getMessage()


def test_auto_on_cuda_falls_back_without_a_cuda_toolkit_to_build_gsplat(fresh_choices, monkeypatch, caplog):
    pytest.importorskip("gsplat", reason="gsplat not installed (pip install -e \".[gpu]\")")
    import torch.utils.cpp_extension

    monkeypatch.setattr(torch.utils.cpp_extension, "CUDA_HOME", None)
    monkeypatch.setenv("PATH", "")  # no nvcc anywhere
    with caplog.at_level(logging.INFO, logger="stages.lib.gaussians.rasterize"):
        assert choose_backend("auto", CUDA, torch.float32) == "cuda"
    [record] = [r for r in caplog.records if r.name == "stages.lib.gaussians.rasterize"]
    assert "no CUDA toolkit (nvcc)" in record.getMessage()


def test_explicit_gsplat_fails_clearly_on_cpu_tensors(fresh_choices):
    g = random_blob_scene(20, seed=1)
    viewmat, K = orbit_camera(16, 12, 20.0)
    with pytest.raises(ValueError, match="backend 'gsplat' cannot render here: gsplat renders CUDA tensors only"):
        render(g, viewmat, K, 16, 12, backend="gsplat")


def test_explicit_gsplat_fails_clearly_without_gsplat(without_gsplat):
    with pytest.raises(ValueError, match=r"gsplat cannot be imported .*pip install -e \"\.\[gpu\]\""):
        choose_backend("gsplat", CUDA, torch.float32)
    with pytest.raises(ValueError, match="float32 tensors only"):
        choose_backend("gsplat", CUDA, torch.float64)


@pytest.mark.parametrize("backend, device, message", [("cpp", CUDA, "'cpp' needs CPU tensors"),
                                                      ("cuda", CPU, "'cuda' needs CUDA tensors"),
                                                      ("optix", CPU, "unknown rasterizer backend 'optix'")])
def test_other_impossible_requests_fail_clearly(fresh_choices, backend, device, message):
    with pytest.raises(ValueError, match=message):
        choose_backend(backend, device, torch.float32)


def test_the_choice_is_logged_once_per_process(fresh_choices, caplog):
    g = random_blob_scene(30, seed=2)
    viewmat, K = orbit_camera(16, 12, 20.0)
    with caplog.at_level(logging.INFO, logger="stages.lib.gaussians.rasterize"):
        for _ in range(3):
            render(g, viewmat, K, 16, 12)
    [record] = [r for r in caplog.records if r.name == "stages.lib.gaussians.rasterize"]
    assert record.getMessage().startswith("rasterizer backend 'cpp' for cpu float32 tensors: auto: ") or \
        record.getMessage().startswith("rasterizer backend 'torch' for cpu float32 tensors: auto: ")


# ------------------------------------------------------------------------------- CUDA: gsplat against ours

def rendered_with_grads(scene: Gaussians, backend: str, width: int, height: int, focal: float) -> list[torch.Tensor]:
    """[rgb, alpha, depth, radii, means2d, means2d.grad, then the gradients of means, log_scales, quats,
    opacity_logits, sh] of one render on the GPU, for a fixed random weighting of rgb, alpha and depth."""
    viewmat, K = orbit_camera(width, height, focal)
    g = leaves(scene.to("cuda"))
    out = render(g, viewmat.cuda(), K.cuda(), width, height, background=torch.tensor(BACKGROUND), backend=backend)
    weights = torch.rand(height, width, 5, generator=torch.Generator().manual_seed(0)).cuda()
    loss = ((out.rgb * weights[..., :3]).sum() + (out.alpha * weights[..., 3]).sum()
            + (out.depth * weights[..., 4]).sum())
    loss.backward()
    return [t.detach().cpu() for t in (out.rgb, out.alpha, out.depth, out.radii, out.means2d, out.means2d.grad,
                                       g.means.grad, g.log_scales.grad, g.quats.grad, g.opacity_logits.grad,
                                       g.sh.grad)]


@needs_gsplat_gpu
def test_gsplat_matches_the_pytorch_path():
    """Tolerances: both are float32, but gsplat's kernels use the fast __expf, sum in another order and
    recover transmittance by division in the backward pass. Per pixel that is ~1e-6 relative per Gaussian
    over up to a few hundred Gaussians: 2e-4 absolute on colour and alpha (0.05 of one 8-bit level), the
    same relative to the depth scale (z ~ 3). Gradients sum thousands of such terms: 5e-3 relative L2 per
    parameter. Opacities stay below 0.99 (ours caps alpha at 0.99, gsplat at 0.999)."""
    width, height, focal = 96, 72, 80.0
    scene = random_blob_scene(400, seed=0)
    assert torch.sigmoid(scene.opacity_logits).max() < 0.99
    ours = rendered_with_grads(scene, "cuda", width, height, focal)
    theirs = rendered_with_grads(scene, "gsplat", width, height, focal)
    assert ours[1].max() > 0.9  # a scene with overlapping, nearly opaque pixels
    torch.testing.assert_close(theirs[0], ours[0], atol=2e-4, rtol=0)
    torch.testing.assert_close(theirs[1], ours[1], atol=2e-4, rtol=0)
    torch.testing.assert_close(theirs[2], ours[2], atol=2e-4 * float(ours[2].max()), rtol=0)
    visible_ours, visible_theirs = ours[3] > 0, theirs[3] > 0
    # gsplat rounds its culling box up to whole pixels: it may also count Gaussians whose footprint ends
    # within a pixel of the border (they add nothing to any pixel), never fewer
    assert visible_ours.sum() > 100 and bool((visible_theirs | ~visible_ours).all())
    assert int((visible_theirs & ~visible_ours).sum()) <= 0.02 * scene.num
    both = visible_ours & visible_theirs
    assert (theirs[3][both] - ours[3][both]).abs().max() <= 1  # ceil of the same 3-sigma radius
    assert (theirs[3][both] == ours[3][both]).float().mean() > 0.99
    torch.testing.assert_close(theirs[4][both], ours[4][both], atol=1e-3, rtol=0)  # pixel positions
    for ref, fast in zip(ours[5:], theirs[5:]):
        assert ref.abs().sum() > 0
        assert ((fast - ref).norm() / ref.norm()).item() < 5e-3


@needs_gsplat_gpu
def test_gsplat_sh_colours_match_ours():
    """gaussian_colors through gsplat's spherical_harmonics against our eval_sh at every degree: values and the
    gradients to the means (through the view direction) and to the coefficients."""
    scene = random_scene_sh(300, seed=3).to("cuda")
    viewmat = orbit_camera(32, 24, 30.0)[0].cuda()
    weights = torch.rand(scene.num, 3, generator=torch.Generator().manual_seed(1)).cuda()
    for degree in range(4):
        results = []
        for backend in ("torch", "gsplat"):
            g = leaves(scene)
            colours = gaussian_colors(g, viewmat, sh_degree=degree, backend=backend)
            (colours * weights).sum().backward()
            # at degree 0 the colour does not depend on the view direction: gsplat leaves the means no gradient
            means_grad = torch.zeros_like(g.means) if degree == 0 and g.means.grad is None else g.means.grad
            results.append((colours.detach(), means_grad, g.sh.grad))
        for ours, theirs in zip(*results):
            torch.testing.assert_close(theirs, ours, atol=1e-5, rtol=1e-4)


def random_scene_sh(n: int, seed: int) -> Gaussians:
    """random_blob_scene with SH degree 3 coefficients of a few tenths (view-dependent colour)."""
    g = random_blob_scene(n, seed=seed).with_sh_degree(3)
    sh = g.sh + 0.3 * torch.randn(g.sh.shape, generator=torch.Generator().manual_seed(seed))
    return Gaussians(g.means, g.log_scales, g.quats, g.opacity_logits, sh)


def densify_candidates(strategy: DensifyStrategy, threshold: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(chosen [N] bool: mean view-space gradient >= threshold, borderline [N] bool: within 2 % of it)."""
    mean_grad = strategy.grad_accum / strategy.grad_count.clamp_min(1)
    return mean_grad >= threshold, (mean_grad / threshold - 1).abs() < 0.02


def densification_comparisons(device: str, backend: str, shadow_backend: str) -> tuple[list[tuple[int, int]], int]:
    """The trainer runs 100 steps with `backend` and densifies every 10; beside it a second strategy gathers
    the view-space gradients and radii that `shadow_backend` gives for the same parameters and views. Returns,
    per densification, (Gaussians the trainer chose to clone or split, Gaussians on which the two choices
    differ, not counting those within 2 % of the threshold), and the final Gaussian count."""
    width, height = 64, 48
    K = torch.tensor([[60.0, 0, width / 2], [0, 60.0, height / 2], [0, 0, 1]], device=device)
    truth = random_blob_scene(300, seed=1).to(device)
    with torch.no_grad():
        views = [TrainView(f"{i}", render(truth, viewmat, K, width, height, backend="torch").rgb, viewmat, K)
                 for i, viewmat in enumerate(orbit_viewmats(8, radius=3.2, height=1.2).to(device))]
    cfg = TrainConfig(iterations=100, sh_degree=0, sh_degree_every=0, densify_from=5, densify_until=100,
                      densify_every=10, grad_threshold=GRAD_THRESHOLD, max_growth=10.0, max_gaussians=100000,
                      opacity_reset_every=0, backend=backend)
    trainer = GaussianTrainer(random_blob_scene(150, seed=5), cfg, extent=1.0, focus_centre=None, focus_radius=0.0,
                              device=device, seed=0)
    shadow = DensifyStrategy(cfg, trainer.num, 1.0, None, 0.0, device=device)
    compared = []
    densify = trainer.strategy.densify_and_prune

    def compare_then_densify(params, optimizer, iteration, image_long_side):
        ours, ours_borderline = densify_candidates(trainer.strategy, cfg.grad_threshold)
        theirs, theirs_borderline = densify_candidates(shadow, cfg.grad_threshold)
        differing = (ours != theirs) & ~(ours_borderline | theirs_borderline)
        compared.append((int(ours.sum()), int(differing.sum())))
        densify(params, optimizer, iteration, image_long_side)
        shadow.reset_stats(trainer.num)

    trainer.strategy.densify_and_prune = compare_then_densify
    for _ in range(cfg.iterations):
        view = views[view_index(trainer.seed, trainer.iteration, len(views))]
        g = trainer.gaussians().detach()  # the parameters of this step, their own leaves
        g = Gaussians(g.means.requires_grad_(), g.log_scales, g.quats, g.opacity_logits, g.sh)
        out = render(g, view.viewmat, view.K, width, height, backend=shadow_backend)
        photometric_loss(out.rgb, view.image, cfg.lambda_dssim).backward()
        shadow.accumulate(out.means2d.grad, out.radii, width, height)
        trainer.step(view)
    return compared, trainer.num


def check_same_decisions(compared: list[tuple[int, int]], final_count: int) -> None:
    """Ten densifications (iterations 10, ..., 100), each with the same choices, and growth."""
    assert len(compared) == 10
    assert all(differing == 0 for _, differing in compared), compared
    assert sum(chosen for chosen, _ in compared) > 50 and final_count > 150, compared


def test_cpp_and_torch_take_the_same_densification_decisions():
    """The harness of the gsplat test below on our two CPU backends (cpp drives, torch shadows)."""
    if rasterize.choose_backend("auto", CPU, torch.float32) != "cpp":
        pytest.skip("the C++ rasterizer is not built here")
    check_same_decisions(*densification_comparisons("cpu", "cpp", "torch"))


@needs_gsplat_gpu
def test_gsplat_takes_the_same_densification_decisions_over_100_steps():
    check_same_decisions(*densification_comparisons("cuda", "cuda", "gsplat"))
