"""The sample's ground truth of one capture as the scoring needs it, rebuilt from the sample's own generator.

The sample writes each capture's *visible* object masks and a support plane at the floor (or table top) under
the object. Two things follow that a score of a cut splat must take into account:
  - clutter in front of the object hides part of it in some frames, while a cut object is rendered alone:
    those pixels are left out of the mask comparison (`TruthViews.masks`);
  - an object standing on a rug (8 mm thick) has its base sunk into it: the surface it stands on is the
    rug's top, not the floor of gt.json (`supported_truth`).
Both come from the capture scene rebuilt from (name, height, seed, focal length, image height), which is
deterministic; the object's own meshes are checked against object_points.npy by the caller.

A view that shows less than MIN_VISIBLE of the object's silhouette is not scored, as in the BOP benchmark
(`scored_views`): there the cut's outline beside the hidden part counts against the few pixels left, which measures
the occluder, not the cut (seed 5's eyedrops: 4 % visible in one held-out view, IoU 0.875 over its 534 pixels,
against 0.977-0.986 in the other seven).
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d

from stages.lib.dataset_formats.polygons import mask_iou
from stages.lib.sample_scene.capture import build_capture_scene
from stages.lib.sample_scene.meshes import Mesh
from stages.records.capture_truth import CaptureTruth

MIN_VISIBLE = 0.1  # BOP's visibility threshold: views showing less of the object's silhouette are not scored


def raycasting_scene(meshes: list[Mesh]) -> o3d.t.geometry.RaycastingScene:
    """An Open3D raycasting scene of `meshes`."""
    scene = o3d.t.geometry.RaycastingScene()
    for mesh in meshes:
        scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                            o3d.core.Tensor(mesh.triangles.astype(np.uint32)))
    return scene


def support_top(gt: CaptureTruth) -> float:
    """Height (metres, along gt.ground_normal above gt.ground_point) of the top of what the object stands on,
    found by a ray cast straight down through the rebuilt scene without the object: 0.008 on a rug, else 0."""
    scene = build_capture_scene(gt.name, gt.height_m, gt.seed, float(gt.K[1, 1]), gt.height)
    room = [mesh for mesh in scene.meshes if not any(mesh is part for part in scene.object_meshes)]
    start = gt.ground_point + 0.5 * gt.height_m * gt.ground_normal  # [3] inside the object, above any rug
    ray = np.concatenate([start, -gt.ground_normal])[None].astype(np.float32)  # [1, 6]
    distance = float(raycasting_scene(room).cast_rays(o3d.core.Tensor(ray))["t_hit"].numpy()[0])
    return round(0.5 * gt.height_m - distance, 6) + 0.0 if np.isfinite(distance) else 0.0  # (+ 0.0: no -0.0)


def supported_truth(gt: CaptureTruth) -> tuple[CaptureTruth, float]:
    """gt with its support plane moved up to the top of what the object stands on, and that rise in metres
    (`support_top`)."""
    rise = support_top(gt)
    return dataclasses.replace(gt, ground_point=gt.ground_point + rise * gt.ground_normal), rise


class TruthViews:
    """The true masks of one capture's frames: the visible object mask and the pixels to leave out."""

    def __init__(self, gt: CaptureTruth, gt_dir: Path, object_meshes: list[Mesh]):
        """gt: with its support plane at the object's support (`supported_truth`); object_meshes: the object's
        meshes in gt's world."""
        self.gt, self.gt_dir = gt, Path(gt_dir)
        self.scene = raycasting_scene(object_meshes)
        self.computed: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # frame index -> masks(index)

    def silhouette(self, index: int) -> np.ndarray:
        """[H, W] bool: pixels whose ray (through the pixel centre) meets the object above its support, as if
        nothing else were in the scene."""
        gt = self.gt
        viewmat = gt.viewmats[index]
        rotation, centre = viewmat[:3, :3], -viewmat[:3, :3].T @ viewmat[:3, 3]  # [3, 3], [3]
        v, u = np.mgrid[0:gt.height, 0:gt.width]
        pixels = np.stack([u + 0.5, v + 0.5, np.ones_like(u)], axis=-1).reshape(-1, 3).astype(np.float64)  # [HW, 3]
        directions = pixels @ np.linalg.inv(gt.K).T @ rotation  # [HW, 3] world (rotation.T applied per row)
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        rays = np.concatenate([np.broadcast_to(centre, directions.shape), directions], axis=1).astype(np.float32)
        hit = self.scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()  # [HW]
        points = centre + np.where(np.isfinite(hit), hit, 0.0)[:, None] * directions  # [HW, 3]
        above = (points - gt.ground_point) @ gt.ground_normal >= 0.0
        return (np.isfinite(hit) & above).reshape(gt.height, gt.width)

    def masks(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """The visible mask [H, W] bool of frame `index` (masks/<index>.png) and the pixels [H, W] bool where
        something else hides the object (its silhouette less the visible mask, without one-pixel slivers
        along the outline, where the two samplings of the same edge differ). Computed once per frame."""
        if index in self.computed:
            return self.computed[index]
        visible = cv2.imread(str(self.gt_dir / "masks" / f"{index:04d}.png"), cv2.IMREAD_GRAYSCALE) > 127
        hidden = (self.silhouette(index) & ~visible).astype(np.uint8)
        hidden = cv2.morphologyEx(hidden, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)) > 0
        self.computed[index] = visible, hidden
        return visible, hidden

    def visible_share(self, index: int) -> float:
        """Share of the object's silhouette visible in frame `index` (BOP's visib_fract; 0 when it is off-frame)."""
        visible, hidden = self.masks(index)
        return float(visible.sum() / max(int((visible | hidden).sum()), 1))

    def scored_views(self, indices: list[int]) -> tuple[list[int], list[int]]:
        """The frame indices showing at least MIN_VISIBLE of the object, and the others (not scored)."""
        shares = {index: self.visible_share(index) for index in indices}
        return ([index for index in indices if shares[index] >= MIN_VISIBLE],
                [index for index in indices if shares[index] < MIN_VISIBLE])


def visible_iou(predicted: np.ndarray, truth: np.ndarray, hidden: np.ndarray) -> float:
    """IoU of two masks [H, W] bool over the pixels that are not `hidden` [H, W] bool."""
    return mask_iou(predicted & ~hidden, truth & ~hidden)
