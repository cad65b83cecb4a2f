"""An orbit video of a textured box scene, ray-cast with Open3D: SfM registers it, and its true poses are known."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
from scipy.ndimage import map_coordinates

from stages.lib.geometry import camera_centres, look_at_viewmat


def textured_box_scene(seed: int) -> tuple[o3d.t.geometry.RaycastingScene, np.ndarray, np.ndarray]:
    """A textured ground slab with a few boxes, plus a random colour grid for a solid texture.

    Returns (scene, coarse noise [3, 24, 24, 24], fine noise [3, 72, 72, 72]) over the cube [-1.5, 1.5]^3.
    """
    rng = np.random.default_rng(seed)
    scene = o3d.t.geometry.RaycastingScene()
    boxes = [((3.0, 3.0, 0.1), (-1.5, -1.5, -0.1)), ((0.5, 0.4, 0.6), (-0.3, -0.2, 0.0)),
             ((0.3, 0.3, 0.3), (0.4, 0.3, 0.0)), ((0.25, 0.5, 0.2), (-0.7, 0.4, 0.0))]
    for (sx, sy, sz), corner in boxes:
        box = o3d.geometry.TriangleMesh.create_box(sx, sy, sz).translate(corner)
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(box))
    return scene, rng.random((3, 24, 24, 24)), rng.random((3, 72, 72, 72))


def render_view(scene, coarse: np.ndarray, fine: np.ndarray, K: np.ndarray, viewmat: np.ndarray,
                width: int, height: int) -> np.ndarray:
    """Ray-cast one view; returns a BGR uint8 image [H, W, 3] with solid-noise texture and Lambert shading."""
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    pixels = np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3)     # [H*W, 3]
    cam_dirs = pixels @ np.linalg.inv(K).T
    rotation = viewmat[:3, :3]
    eye = camera_centres(viewmat)
    dirs = cam_dirs @ rotation                                        # world directions [H*W, 3]
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    rays = np.concatenate([np.broadcast_to(eye, dirs.shape), dirs], 1).astype(np.float32)
    hits = scene.cast_rays(o3d.core.Tensor(rays))
    t_hit = hits["t_hit"].numpy()
    hit = np.isfinite(t_hit)
    points = eye + dirs[hit] * t_hit[hit, None]                       # [M, 3]
    colour = np.zeros((len(dirs), 3))
    for grid, weight in ((coarse, 0.6), (fine, 0.4)):
        coords = ((points + 1.5) / 3.0 * (grid.shape[1] - 1)).T        # [3, M]
        colour[hit] += weight * np.stack([map_coordinates(grid[c], coords, order=1) for c in range(3)], 1)
    normals = hits["primitive_normals"].numpy()[hit]
    light = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])
    colour[hit] *= (0.35 + 0.65 * np.abs(normals @ light))[:, None]
    colour[~hit] = 0.55
    image = (colour.reshape(height, width, 3) * 255).clip(0, 255).astype(np.uint8)
    return image[..., ::-1].copy()


def render_orbit_video(path: Path, num_frames: int, width: int, height: int, seed: int = 0,
                       radius: float = 2.6, elevation: float = 1.3) -> dict:
    """Write an mp4v orbit video of the box scene; returns {"K": [3,3], "viewmats": [N,4,4]} (truth)."""
    scene, coarse, fine = textured_box_scene(seed)
    focal = 0.9 * width
    K = np.array([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1.0]])
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (width, height))
    viewmats = []
    for index in range(num_frames):
        angle = 2 * np.pi * index / num_frames
        eye = np.array([radius * np.cos(angle), radius * np.sin(angle), elevation])
        viewmat = look_at_viewmat(eye, np.array([0.0, 0.0, 0.15]))
        writer.write(render_view(scene, coarse, fine, K, viewmat, width, height))
        viewmats.append(viewmat)
    writer.release()
    return {"K": K, "viewmats": np.stack(viewmats)}
