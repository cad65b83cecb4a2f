"""Digests of what the C++ kernels compute, for comparing builds and machines: a projection, a raster, a loss
(each forward and backward) and a few dozen training steps with densification, on a synthetic scene, and the raster
of a Gaussian whose alpha reaches 1/255 a hair beyond its computed extent.

    python -m tests.factories.kernel_probe [--steps N]     # prints {part: sha256} as JSON

The kernel build is this process's (stages/lib/gaussians/kernel_builds.py: $CUT_AND_SPLAT_KERNELS); torch's own
kernels follow $ATEN_CPU_CAPABILITY when it is set before torch loads (stages/__init__.py pins it).
"""
from __future__ import annotations

import argparse
import hashlib
import json

import stages  # noqa: F401  (first: the environment torch reads when it loads)
import torch

from stages.lib.gaussians.losses import photometric_loss
from stages.lib.gaussians.native import bin_gaussians_cpp, project_gaussians_cpp, rasterize_tiles_cpp
from stages.lib.gaussians.projection import Projection
from stages.lib.gaussians.rasterize import render
from stages.lib.gaussians.train_config import TrainConfig
from stages.lib.gaussians.trainer import GaussianTrainer, TrainView, view_index
from tests.factories.raster import camera
from tests.factories.splats import orbit_viewmats, random_blob_scene

WIDTH, HEIGHT = 96, 72


def digest(*tensors: torch.Tensor) -> str:
    """sha256 of the tensors' bytes (in order)."""
    h = hashlib.sha256()
    for t in tensors:
        h.update(t.detach().contiguous().cpu().numpy().tobytes())
    return h.hexdigest()


def views(truth, count: int) -> list[TrainView]:
    """`count` orbit views of `truth`, rendered by the PyTorch reference (the targets do not depend on the build)."""
    _, K = camera(WIDTH, HEIGHT, 80.0)
    with torch.no_grad():
        return [TrainView(f"{i:02d}", render(truth, viewmat, K, WIDTH, HEIGHT, backend="torch").rgb.clamp(0, 1),
                          viewmat, K) for i, viewmat in enumerate(orbit_viewmats(count, 3.0, 1.0))]


# A Gaussian far off screen whose 2D covariance is nearly singular (from the sample plant's splat at iteration
# 1820): float rounding puts an alpha of 1/255 at pixel (71, 129), one column beyond the extent the rasterizer
# computes for it. The 8-lane builds skipped that pixel's half row while a 16-lane row took it (x86-64-v4 and v3
# splats differed); the column window now keeps it out at every lane count.
EDGE_MEAN = (667.1474609375, 742.6329956054688)
EDGE_CONIC = (0.11031733453273773, -0.10712762922048569, 0.10405150800943375)
EDGE_OPACITY = 0.21780413389205933
EDGE_PIXEL = (129, 71)  # (row, column) just outside its reached columns


def edge_raster() -> tuple[torch.Tensor, torch.Tensor]:
    """The image [240, 320, 4] and transmittance [240, 320] of the EDGE Gaussian alone."""
    means2d, conics = torch.tensor([EDGE_MEAN]), torch.tensor([EDGE_CONIC])
    proj = Projection(means2d, conics, torch.ones(1), torch.tensor([2000], dtype=torch.int32),
                      torch.tensor([[2000.0, 2000.0]]))
    return rasterize_tiles_cpp(means2d, conics, torch.tensor([EDGE_OPACITY]), torch.ones(1, 4),
                               bin_gaussians_cpp(proj, 320, 240), 320, 240)


def kernel_digests(steps: int = 30) -> dict[str, str]:
    """{part: sha256} of the kernels' outputs and gradients, and of a model after `steps` training steps."""
    truth = random_blob_scene(300, seed=1)
    start = random_blob_scene(200, seed=2)
    train_views = views(truth, 6)
    view = train_views[0]
    found = {}

    means, quats, scales = (t.detach().clone().requires_grad_() for t in
                            (start.means, start.quats, start.log_scales.exp()))
    opacities = torch.sigmoid(start.opacity_logits)
    proj = project_gaussians_cpp(means, quats, scales, opacities, view.viewmat, view.K, WIDTH, HEIGHT)
    (proj.means2d.sum() + proj.conics.sum() + proj.depths.sum()).backward()
    found["projection"] = digest(proj.means2d, proj.conics, proj.depths, means.grad, quats.grad, scales.grad)

    features = torch.rand(start.num, 4, generator=torch.Generator().manual_seed(3)).requires_grad_()
    raster_in = [t.detach().clone().requires_grad_() for t in (proj.means2d, proj.conics, opacities)]
    image, trans = rasterize_tiles_cpp(*raster_in, features, bin_gaussians_cpp(proj, WIDTH, HEIGHT), WIDTH, HEIGHT)
    ((image * torch.linspace(0, 1, image.numel()).reshape(image.shape)).sum() + trans.sum()).backward()
    found["raster"] = digest(image, trans, *(t.grad for t in raster_in), features.grad)

    found["raster_edge"] = digest(*edge_raster())

    prediction = image[..., :3].detach().clone().requires_grad_()
    loss = photometric_loss(prediction, view.image, 0.2)
    loss.backward()
    found["loss"] = digest(loss, prediction.grad)

    cfg = TrainConfig(iterations=steps, sh_degree=1, sh_degree_every=10, densify_from=5, densify_until=steps,
                      densify_every=5, eval_every=steps, max_gaussians=400, backend="cpp")
    trainer = GaussianTrainer(start, cfg, extent=1.5, focus_centre=torch.zeros(3), focus_radius=2.0, seed=0)
    for _ in range(steps):
        trainer.step(train_views[view_index(0, trainer.iteration, len(train_views))])
    found["training"] = digest(*trainer.params.values())
    found["gaussians"] = str(trainer.num)
    return found


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=30)
    print(json.dumps(kernel_digests(parser.parse_args().steps)))
