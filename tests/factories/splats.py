"""Gaussian scenes with known ground truth and the stage folders built from them.

random_blob_scene / orbit_viewmats / write_synthetic_sfm: coloured Gaussians rendered from an orbit and
written exactly like an sfm output (images/ + sparse/). make_blob: an opaque cylinder object.
synthetic_scene: a splat-like scene (object on a floor, halo, floaters) with the object's Gaussians
known, write_splat_folder its splat_train output and scene_intrinsics its cameras' intrinsics.
write_blob_object: an extract output.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import torch

from stages.lib.gaussians.model import SH_C0, Gaussians, inverse_sigmoid
from stages.lib.gaussians.ply import write_ply
from stages.lib.gaussians.rasterize import render
from stages.lib.geometry import camera_centres, look_at_viewmat
from stages.lib.objects.silhouettes import Intrinsics
from stages.records.cameras import CameraFrame, CamerasRecord
from stages.records.extract import ExtractRecord
from stages.records.sfm import SfmRecord


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
    """Render `truth` from every viewmat [V, 4, 4] (K [3, 3]) and write an sfm output folder at root (images/,
    sparse/ and sfm.json, through SfmRecord).

    points3D are `num_points` true means plus Gaussian noise of std `point_noise`, coloured with the
    true DC colour (as SfM triangulation would give roughly).
    """
    root, staging = Path(root), Path(root) / ".undistorted"
    (staging / "images").mkdir(parents=True, exist_ok=True)
    (staging / "sparse").mkdir(parents=True, exist_ok=True)
    reconstruction = pycolmap.Reconstruction()
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    reconstruction.add_camera_with_trivial_rig(
        pycolmap.Camera(camera_id=1, model="PINHOLE", width=width, height=height, params=[fx, fy, cx, cy]))
    with torch.no_grad():
        for index, viewmat in enumerate(viewmats):
            name = f"{index:04d}.png"
            rgb = render(truth, viewmat, K, width, height, backend="torch").rgb  # [H, W, 3]
            image = (rgb.clamp(0, 1) * 255).round().byte().numpy()
            cv2.imwrite(str(staging / "images" / name), image[:, :, ::-1])
            reconstruction.add_image_with_trivial_frame(
                pycolmap.Image(name=name, camera_id=1, image_id=index + 1),
                pycolmap.Rigid3d(viewmat[:3].double().numpy()))
    rng = np.random.default_rng(seed)
    chosen = rng.choice(truth.num, size=min(num_points, truth.num), replace=False)
    colours = (0.5 + SH_C0 * truth.sh[chosen, 0]).clamp(0, 1).numpy()
    for position, colour in zip(truth.means[chosen].double().numpy(), colours):
        reconstruction.add_point3D(position + rng.normal(0.0, point_noise, 3), pycolmap.Track(),
                                   (colour * 255).round().astype(np.uint8))
    reconstruction.write_binary(str(staging / "sparse"))
    camera = {"model": "PINHOLE", "width": width, "height": height, "params": [fx, fy, cx, cy]}
    SfmRecord.write(root, {"registered": len(viewmats), "total": len(viewmats), "camera": camera,
                           "source_camera": camera}, staging / "sparse", staging / "images")
    staging.rmdir()


def make_blob(seed: int = 0, view_dependent: bool = False) -> Gaussians:
    """An opaque cylinder of Gaussians, 2 model units tall (z in [0, 2]), radius 0.5."""
    rng = np.random.default_rng(seed)
    points = rng.uniform(-1.0, 1.0, (2500, 3))
    points = points[np.linalg.norm(points[:, :2], axis=1) < 0.5]
    points[:, 2] += 1.0
    g = Gaussians.from_points(points, rng.uniform(0.2, 0.8, points.shape), sh_degree=1)
    g.opacity_logits[:] = 4.0
    if view_dependent:
        g.sh[:, 1:] = torch.as_tensor(rng.normal(0, 0.6, g.sh[:, 1:].shape), dtype=torch.float32)
    return g


def write_blob_object(folder: Path) -> Path:
    """An extract output folder (object.ply + extract.json) holding make_blob's opaque cylinder."""
    folder.mkdir(parents=True, exist_ok=True)
    write_ply(folder / "object.ply", make_blob())
    ExtractRecord(np.array([0.0, 0.0, 1.0]), np.zeros(3), 2.0).write(folder)
    return folder


SCENE_K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])  # a synthetic scene's cameras
SCENE_IMAGE_SIZE = (640, 480)  # (width, height) pixels


@dataclass
class SyntheticScene:
    """A procedural splat-like scene: object on a floor, with halo and floaters, in a random frame."""

    means: np.ndarray  # [N, 3]
    opacities: np.ndarray  # [N]
    scales: np.ndarray  # [N, 3] linear
    colors: np.ndarray  # [N, 3] in [0, 1]
    viewmats: np.ndarray  # [C, 4, 4] world-to-camera, OpenCV
    is_object: np.ndarray  # [N] bool
    normal: np.ndarray  # [3] true floor normal (towards the object)
    height: float  # true object height (model units)
    base_point: np.ndarray  # [3] true foot of the object's axis on the floor


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Uniformly random rotation matrix [3, 3]."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def synthetic_scene(seed: int = 0, floor_points: int = 20000, object_points: int = 4000, halo_points: int = 400,
                    floater_points: int = 200, wall_points: int = 0, transform: bool = True) -> SyntheticScene:
    """Cylinder (radius 0.1, height 0.3) on a floor disc (radius 1.5) with a halo around the object and
    floaters under the floor, orbit cameras at distance ~0.9; then a random similarity transform.
    Like a trained splat, the floor has no Gaussians under the object (no camera sees that floor).
    Built in metres with z up; `floor_points` small gives a plain floor, `wall_points` adds two walls.
    """
    rng = np.random.default_rng(seed)
    radius, height = 0.1, 0.3
    angle = rng.uniform(0, 2 * np.pi, floor_points)
    distance = 1.5 * np.sqrt(rng.uniform((radius / 1.5) ** 2, 1, floor_points))  # none under the object: unseen
    floor = np.stack([distance * np.cos(angle), distance * np.sin(angle), rng.normal(0, 0.002, floor_points)], 1)
    side = int(object_points * 0.8)
    angle = rng.uniform(0, 2 * np.pi, object_points)
    r = np.concatenate([np.full(side, radius), radius * np.sqrt(rng.uniform(0, 1, object_points - side))])
    z = np.concatenate([rng.uniform(0.0, height, side), np.full(object_points - side, height)])
    blob = np.stack([r * np.cos(angle), r * np.sin(angle), z], 1) + rng.normal(0, 0.002, (object_points, 3))
    direction = rng.normal(size=(halo_points, 3))
    direction[:, 2] = np.abs(direction[:, 2])
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    halo = direction * rng.uniform(0.3, 0.7, (halo_points, 1)) + [0, 0, 0.05]
    floaters = np.stack([rng.uniform(-1, 1, floater_points), rng.uniform(-1, 1, floater_points),
                         rng.uniform(-0.5, -0.05, floater_points)], 1)
    walls = []
    for axis in (0, 1)[: 2 if wall_points else 0]:
        wall = np.stack([rng.uniform(-1.5, 1.5, wall_points // 2), rng.uniform(-1.5, 1.5, wall_points // 2),
                         rng.uniform(0, 1.5, wall_points // 2)], 1)
        wall[:, axis] = 1.5 + rng.normal(0, 0.002, wall_points // 2)
        walls.append(wall)
    parts = [floor, blob, halo, floaters, *walls]
    means = np.concatenate(parts)
    is_object = np.zeros(len(means), dtype=bool)
    is_object[len(floor):len(floor) + object_points] = True
    opacities = np.where(is_object, rng.uniform(0.5, 1.0, len(means)), rng.uniform(0.3, 1.0, len(means)))
    halo_slice = slice(len(floor) + object_points, len(floor) + object_points + halo_points)
    opacities[halo_slice] = rng.uniform(0.01, 0.4, halo_points)
    scales = np.full((len(means), 3), 0.004) * rng.uniform(0.5, 1.5, (len(means), 1))
    colors = np.where(is_object[:, None], [0.8, 0.5, 0.2], rng.uniform(0.2, 0.9, (len(means), 3)))
    target = np.array([0.0, 0.0, height / 2])
    viewmats = np.stack([look_at_viewmat(np.array([0.8 * np.cos(a), 0.8 * np.sin(a), 0.4 + 0.1 * np.sin(3 * a)]),
                                         target)
                         for a in np.linspace(0, 2 * np.pi, 24, endpoint=False)])
    normal, base_point = np.array([0.0, 0.0, 1.0]), np.zeros(3)
    if transform:
        rotation, scale, shift = random_rotation(rng), float(np.exp(rng.uniform(np.log(0.2), np.log(5)))), rng.normal(0, 2, 3)
        means = scale * means @ rotation.T + shift
        scales = scales * scale
        normal, base_point = rotation @ normal, shift.copy()
        moved = np.empty_like(viewmats)
        for i, viewmat in enumerate(viewmats):
            centre = scale * rotation @ camera_centres(viewmat) + shift
            moved[i] = np.eye(4)
            moved[i, :3, :3] = viewmat[:3, :3] @ rotation.T
            moved[i, :3, 3] = -moved[i, :3, :3] @ centre
        viewmats = moved
        height *= scale
    return SyntheticScene(means.astype(np.float32), opacities.astype(np.float32), scales.astype(np.float32),
                          colors.astype(np.float32), viewmats, is_object, normal, height, base_point)


def write_splat_folder(folder: Path, scene: SyntheticScene) -> None:
    """A splat_train output folder (scene.ply + cameras.json) of a synthetic scene."""
    folder.mkdir()
    n = len(scene.means)
    sh = torch.zeros(n, 16, 3)
    sh[:, 0] = (torch.as_tensor(scene.colors) - 0.5) / SH_C0
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1.0
    gaussians = Gaussians(torch.as_tensor(scene.means), torch.as_tensor(scene.scales).log(), quats,
                          inverse_sigmoid(torch.as_tensor(scene.opacities).clamp(1e-4, 1 - 1e-4)), sh)
    write_ply(folder / "scene.ply", gaussians)
    width, height = SCENE_IMAGE_SIZE
    frames = [CameraFrame(f"{i:04d}.jpg", SCENE_K, viewmat, width, height) for i, viewmat in enumerate(scene.viewmats)]
    CamerasRecord(width, height, frames).write(folder)


def scene_intrinsics(scene: SyntheticScene) -> Intrinsics:
    """The intrinsics of a synthetic scene's cameras (those write_splat_folder writes)."""
    count = len(scene.viewmats)
    return Intrinsics(np.tile(SCENE_K, (count, 1, 1)), np.tile(SCENE_IMAGE_SIZE, (count, 1)))
