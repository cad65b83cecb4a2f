"""Trainer and densification strategy: densification / pruning / budget on hand-made statistics, the view
order, and a real short optimisation on a rendered synthetic scene, interrupted and resumed."""
from __future__ import annotations

import math

import pytest
import torch

from stages.lib.gaussians.densify_ops import reset_opacity
from stages.lib.gaussians.model import Gaussians, inverse_sigmoid
from stages.lib.gaussians.rasterize import render
from stages.lib.gaussians.strategy import RESET_OPACITY
from tests.factories.splats import orbit_viewmats, random_blob_scene
from stages.lib.gaussians.train_config import TrainConfig
from stages.lib.gaussians.trainer import GaussianTrainer, TrainView, psnr, scene_extent, train, view_index


def hand_made_trainer(max_gaussians: int = 100, max_growth: float = 10.0,
                      background_grad_threshold: float = 0.0) -> GaussianTrainer:
    """Six Gaussians, one per densification case (extent 1, focus radius 1 around the origin)."""
    means = torch.tensor([[0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1], [0.2, 0.2, 0], [5.0, 0, 0], [0, 0.3, 0]])
    scales = torch.tensor([0.005, 0.05, 0.005, 0.005, 0.5, 0.5])[:, None].repeat(1, 3)
    opacities = torch.tensor([0.5, 0.5, 0.5, 0.001, 0.5, 0.5])
    init = Gaussians(means, scales.log(), torch.tensor([[1.0, 0, 0, 0]]).repeat(6, 1),
                     inverse_sigmoid(opacities), torch.zeros(6, 16, 3))
    cfg = TrainConfig(max_gaussians=max_gaussians, max_growth=max_growth, percent_dense=0.01, prune_scale=0.1,
                      grad_threshold=2e-4, background_grad_threshold=background_grad_threshold)
    trainer = GaussianTrainer(init, cfg, extent=1.0, focus_centre=torch.zeros(3), focus_radius=1.0)
    # One Adam step with known gradients so every row has Adam moments to carry along.
    for name, param in trainer.params.items():
        param.grad = torch.arange(param.shape[0], dtype=torch.float32).reshape(-1, *[1] * (param.dim() - 1)) \
            .expand_as(param).clone() + 1.0
    trainer.optimizer.step()
    trainer.strategy.grad_count[:] = 1
    trainer.strategy.grad_accum[:] = torch.tensor([1e-3, 2e-3, 1e-5, 1e-3, 1e-3, 1e-3])
    return trainer


def densify_now(trainer: GaussianTrainer) -> None:
    """One densification of the trainer's strategy, at its current iteration, for a 64 px image."""
    trainer.strategy.densify_and_prune(trainer.params, trainer.optimizer, trainer.iteration, image_long_side=64)


def test_densify_clone_split_prune_focus():
    trainer = hand_made_trainer()
    old_means = trainer.params["means"].detach().clone()
    old_log_scales = trainer.params["log_scales"].detach().clone()
    old_moment = trainer.optimizer.state[trainer.params["means"]]["exp_avg"].clone()
    old_opacities = torch.sigmoid(trainer.params["opacity_logits"].detach().clone())
    densify_now(trainer)
    means = trainer.params["means"].detach()
    # kept: 0 (cloned), 2 (low gradient), 4 (huge but outside the focus: background); pruned: 3 (transparent),
    # 5 (huge, near the object); split: 1 -> two children with scales / 1.6. Order: kept rows, clones, split children.
    assert trainer.num == 6
    torch.testing.assert_close(means[:4], old_means[[0, 2, 4, 0]])
    children = trainer.params["log_scales"].detach()[4:]
    torch.testing.assert_close(children, old_log_scales[[1, 1]] - math.log(1.6))
    assert ((means[4:] - old_means[1]).abs() < 0.05 * 5).all()
    assert not torch.equal(means[4], means[5])
    # A clone and its original share the opacity 1 - sqrt(1 - o): together they composite like the original.
    opacities = torch.sigmoid(trainer.params["opacity_logits"].detach())
    torch.testing.assert_close(opacities[[0, 3]], (1 - torch.sqrt(1 - old_opacities[0])).repeat(2))
    torch.testing.assert_close(opacities[[1, 2, 4, 5]], old_opacities[[2, 4, 1, 1]])
    # Adam moments follow their rows; new rows start from zero moments.
    moments = trainer.optimizer.state[trainer.params["means"]]
    torch.testing.assert_close(moments["exp_avg"][:3], old_moment[[0, 2, 4]])
    assert not moments["exp_avg"][3:].any() and moments["exp_avg_sq"].shape == (6, 3)
    assert all(len(g["params"]) == 1 and g["params"][0] is trainer.params[g["name"]]
               for g in trainer.optimizer.param_groups)
    assert not trainer.strategy.grad_accum.any() and trainer.strategy.grad_accum.shape == (6,)


def test_background_densifies_above_its_own_threshold():
    # Gaussian 4 (outside the focus, huge, gradient 1e-3) is never size-pruned; it splits only when the
    # gradient passes background_grad_threshold (0 = never).
    for threshold, splits in ((5e-4, True), (2e-3, False), (0.0, False)):
        trainer = hand_made_trainer(background_grad_threshold=threshold)
        old_means = trainer.params["means"].detach().clone()
        old_log_scale = trainer.params["log_scales"].detach()[4].clone()  # [3]
        densify_now(trainer)
        far = (trainer.params["means"].detach() - old_means[4]).norm(dim=1) < 2.0  # [N] near Gaussian 4
        far_log_scales = trainer.params["log_scales"].detach()[far]  # [1 or 2, 3]
        assert int(far.sum()) == (2 if splits else 1), threshold
        expected = old_log_scale - (math.log(1.6) if splits else 0.0)
        torch.testing.assert_close(far_log_scales, expected.expand_as(far_log_scales))
        assert trainer.num == (7 if splits else 6)  # in-focus cases as in the test above


def test_densify_respects_budget_by_gradient():
    trainer = hand_made_trainer(max_gaussians=5)  # 4 survive pruning: room for one more
    densify_now(trainer)
    assert trainer.num == 5  # only the split (highest gradient) happened: 4 - 1 + 2
    log_scales = trainer.params["log_scales"].detach()[:, 0]
    assert (log_scales.gt(math.log(0.01)) & log_scales.lt(math.log(0.1))).sum() == 2  # the two children


def test_densify_growth_per_round_is_capped():
    trainer = hand_made_trainer(max_growth=0.2)  # 6 Gaussians: at most one densified this round
    densify_now(trainer)
    assert trainer.num == 5  # pruned 3 and 5; only the split (highest gradient): 4 - 1 + 2


def test_statistics_gather_only_what_the_view_sees():
    """The strategy's per-step statistics, written without mask indexing (no wait for a GPU), against the masked
    formula of 3DGS: only Gaussians with a radius gain a gradient norm, a count and a radius; a view that sees
    none changes nothing."""
    trainer = hand_made_trainer()
    strategy = trainer.strategy
    gen = torch.Generator().manual_seed(3)
    for step in range(4):
        grad = torch.randn(6, 2, generator=gen) * 1e-3
        radii = torch.tensor([0, 3, 7, 0, 1, 12], dtype=torch.int32) * (step != 2)  # step 2's view sees none
        visible = radii > 0
        accum, count, max_radii = (t.clone() for t in (strategy.grad_accum, strategy.grad_count, strategy.max_radii))
        accum[visible] += (grad[visible] * torch.tensor([40.0, 30.0])).norm(dim=-1)
        count[visible] += 1
        max_radii[visible] = torch.maximum(max_radii[visible], radii[visible].float())
        strategy.accumulate(grad, radii, 80, 60)
        assert torch.equal(strategy.grad_accum, accum)
        assert torch.equal(strategy.grad_count, count)
        assert torch.equal(strategy.max_radii, max_radii)
    assert strategy.grad_count.tolist() == [1, 4, 4, 1, 4, 4]  # hand_made_trainer's 1, plus the three seeing views


def test_reset_opacity_clamps():
    trainer = hand_made_trainer()
    reset_opacity(trainer.params, trainer.optimizer, RESET_OPACITY)
    opacities = torch.sigmoid(trainer.params["opacity_logits"].detach())
    assert opacities.max() <= 0.01 + 1e-6 and opacities[3] < 0.002


def test_scene_extent_and_view_order():
    assert math.isclose(scene_extent(orbit_viewmats(12, radius=3.0, height=1.0).numpy()), 3.0 * 1.1, rel_tol=1e-5)
    # Each epoch visits every view exactly once.
    assert sorted(view_index(3, i, 7) for i in range(7, 14)) == list(range(7))


def make_views(truth: Gaussians, num_views: int, width: int, height: int) -> list[TrainView]:
    K = torch.tensor([[1.1 * width, 0, width / 2], [0, 1.1 * width, height / 2], [0, 0, 1]])
    views = []
    with torch.no_grad():
        for i, viewmat in enumerate(orbit_viewmats(num_views, radius=3.2, height=1.2)):
            image = render(truth, viewmat, K, width, height, backend="torch").rgb.clamp(0, 1)
            views.append(TrainView(f"{i:04d}", image, viewmat, K))
    return views


def noisy_init(truth: Gaussians, seed: int = 1) -> Gaussians:
    gen = torch.Generator().manual_seed(seed)
    points = truth.means + 0.05 * torch.randn(truth.means.shape, generator=gen)
    return Gaussians.from_points(points, torch.full((truth.num, 3), 0.5), sh_degree=1)


class Interrupt(Exception):
    pass


def interrupt_after(count: int):
    """A progress wrapper that crashes the loop after `count` iterations (like a killed process)."""
    def wrap(iterable):
        for index, item in enumerate(iterable):
            if index == count:
                raise Interrupt
            yield item
    return wrap


def test_training_raises_psnr_and_resumes_exactly(tmp_path):
    torch.set_num_threads(1)
    truth = random_blob_scene(120, seed=0)
    views = make_views(truth, 9, 40, 30)
    train_views, test_views = views[1:], views[:1]
    cfg = TrainConfig(iterations=30, sh_degree=1, sh_degree_every=8, densify_from=4, densify_until=16,
                      densify_every=6, opacity_reset_every=0, eval_every=6, checkpoint_every=6, backend="auto",
                      lr_opacity=0.2, lr_sh_dc=0.02)  # faster rates: a few dozen iterations must show progress
    extent = scene_extent(torch.stack([v.viewmat for v in views]))

    def fresh() -> GaussianTrainer:
        return GaussianTrainer(noisy_init(truth), cfg, extent, torch.zeros(3), 2.0, seed=5)

    straight = fresh()
    stats = train(straight, train_views, test_views)
    curve = [p for _, p in stats["psnr_curve"]]
    assert curve[-1] > curve[0] + 1.0, curve
    assert stats["num_gaussians"] > truth.num and stats["iterations_run"] == 30
    assert straight.active_sh_degree == 1

    checkpoint = tmp_path / "ckpt.pt"
    with pytest.raises(Interrupt):
        train(fresh(), train_views, test_views, checkpoint, progress=interrupt_after(13))
    assert torch.load(checkpoint, weights_only=False)["trainer"]["iteration"] == 12
    resumed = fresh()
    resumed_stats = train(resumed, train_views, test_views, checkpoint)
    assert resumed_stats["resumed_from"] == 12 and resumed.num == straight.num
    for name, param in straight.params.items():
        torch.testing.assert_close(resumed.params[name], param, atol=1e-5, rtol=1e-4, msg=name)
    assert [it for it, _ in resumed_stats["psnr_curve"]] == [it for it, _ in stats["psnr_curve"]]
    final = psnr(resumed.render(test_views[0]).rgb, test_views[0].image)
    assert math.isclose(final, resumed_stats["final_psnr"], rel_tol=1e-6)
