"""A synthetic splat scene with known ground truth, written exactly like an sfm stage output.

Used by the trainer tests and the splat_train benchmark: random coloured Gaussians around the origin
are rendered with the reference rasterizer from an orbit of PINHOLE cameras, and the images plus a
COLMAP model (cameras, posed images, noisy points3D sampled from the true means) are written to
`<root>/images/` and `<root>/sparse/`.
"""
from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import torch

from stages.gaussians.model import SH_C0, Gaussians
from stages.gaussians.rasterize import render
from stages.geometry import look_at_viewmat


def orbit_viewmats(num_views: int, radius: float, height: float) -> torch.Tensor:
    """Cameras on a circle of `radius` at z = `height`, looking at the origin (z up). Returns [V, 4, 4]."""
    eyes = [(radius * math.cos(2 * math.pi * i / num_views), radius * math.sin(2 * math.pi * i / num_views), height)
            for i in range(num_views)]
    return torch.as_tensor(np.stack([look_at_viewmat(eye, np.zeros(3)) for eye in eyes])).float()


def random_blob_scene(num_gaussians: int, seed: int = 0) -> Gaussians:
    """Coloured anisotropic Gaussians filling a unit ball, fairly opaque, view-independent colour."""
    gen = torch.Generator().manual_seed(seed)
    direction = torch.nn.functional.normalize(torch.randn(num_gaussians, 3, generator=gen), dim=1)
    means = direction * torch.rand(num_gaussians, 1, generator=gen) ** (1 / 3)
    quats = torch.nn.functional.normalize(torch.randn(num_gaussians, 4, generator=gen), dim=1)
    log_scales = math.log(0.12) + 0.4 * torch.randn(num_gaussians, 3, generator=gen)
    colours = torch.rand(num_gaussians, 3, generator=gen)
    opacity_logits = 1.0 + torch.randn(num_gaussians, generator=gen)
    return Gaussians(means, log_scales, quats, opacity_logits, ((colours - 0.5) / SH_C0)[:, None, :])


def write_synthetic_sfm(root: Path, truth: Gaussians, viewmats: torch.Tensor, K: torch.Tensor, width: int,
                        height: int, num_points: int = 200, point_noise: float = 0.05, seed: int = 0) -> None:
    """Render `truth` from every viewmat [V, 4, 4] (K [3, 3]) and write images/ + sparse/ under root.

    points3D are `num_points` true means plus Gaussian noise of std `point_noise`, coloured with the
    true DC colour (as SfM triangulation would give roughly).
    """
    root = Path(root)
    (root / "images").mkdir(parents=True, exist_ok=True)
    (root / "sparse").mkdir(parents=True, exist_ok=True)
    reconstruction = pycolmap.Reconstruction()
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    reconstruction.add_camera_with_trivial_rig(
        pycolmap.Camera(camera_id=1, model="PINHOLE", width=width, height=height, params=[fx, fy, cx, cy]))
    with torch.no_grad():
        for index, viewmat in enumerate(viewmats):
            name = f"{index:04d}.png"
            rgb = render(truth, viewmat, K, width, height, backend="torch").rgb  # [H, W, 3]
            image = (rgb.clamp(0, 1) * 255).round().byte().numpy()
            cv2.imwrite(str(root / "images" / name), image[:, :, ::-1])
            reconstruction.add_image_with_trivial_frame(
                pycolmap.Image(name=name, camera_id=1, image_id=index + 1),
                pycolmap.Rigid3d(viewmat[:3].double().numpy()))
    rng = np.random.default_rng(seed)
    chosen = rng.choice(truth.num, size=min(num_points, truth.num), replace=False)
    colours = (0.5 + SH_C0 * truth.sh[chosen, 0]).clamp(0, 1).numpy()
    for position, colour in zip(truth.means[chosen].double().numpy(), colours):
        reconstruction.add_point3D(position + rng.normal(0.0, point_noise, 3), pycolmap.Track(),
                                   (colour * 255).round().astype(np.uint8))
    reconstruction.write_binary(str(root / "sparse"))
