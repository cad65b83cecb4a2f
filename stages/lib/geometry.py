"""Camera geometry, with the conventions of the whole project stated once.

- Camera axes are OpenCV's: x right, y down, z forward (the optical axis).
- A pose is a world-to-camera `viewmat` [4, 4]: x_cam = R x_world + t with R = viewmat[:3, :3] and
  t = viewmat[:3, 3]. The rows of R are the camera axes in world coordinates: R[0] right, R[1] down,
  R[2] forward; the camera centre is -R^T t.
- Intrinsics `K` [3, 3] map a camera point to the continuous pixel (fx x / z + cx, fy y / z + cy), where
  the centre of the top-left pixel is (0.5, 0.5) (COLMAP's PINHOLE convention and the rasterizer's):
  a central principal point is (W / 2, H / 2), and pixel index (row, col) has its centre at
  (col + 0.5, row + 0.5).
- A photo whose camera is unknown has a DEFAULT_FOV_DEG horizontal field of view (the paper's 55 degrees),
  square pixels and a central principal point.

numpy float64 throughout; `camera_centres` and `image_ups` also take torch tensors (differentiable).
"""
from __future__ import annotations

import numpy as np

DEFAULT_FOV_DEG = 55.0
WORLD_UP = (0.0, 0.0, 1.0)  # the default up of look-at cameras (the sample's worlds are z up)


def camera_centres(viewmats):
    """Camera centres [..., 3] (-R^T t) of world-to-camera matrices [..., 4, 4] (numpy or torch)."""
    rotations, translations = viewmats[..., :3, :3], viewmats[..., :3, 3]
    return -(rotations.swapaxes(-1, -2) @ translations[..., None])[..., 0]


def image_ups(viewmats):
    """World directions [..., 3] of the image's up (-R[1], unit) of viewmats [..., 4, 4] (numpy or torch)."""
    return -viewmats[..., 1, :3]


def look_at_point(viewmats: np.ndarray) -> np.ndarray | None:
    """The point [3] nearest (least squares) to the optical axes of viewmats [C, 4, 4].

    None when the axes are (nearly) parallel (smallest eigenvalue of the normal equations below 1e-3 of
    the largest) or when the point lies behind the cameras on average (an outward-facing rig).
    """
    viewmats = np.asarray(viewmats, dtype=np.float64)
    centres = camera_centres(viewmats)  # [C, 3]
    forwards = viewmats[:, 2, :3]  # [C, 3] optical axes
    projectors = np.eye(3)[None] - forwards[:, :, None] * forwards[:, None, :]  # [C, 3, 3]
    system, rhs = projectors.sum(axis=0), (projectors @ centres[..., None]).sum(axis=0)[:, 0]
    eigenvalues = np.linalg.eigvalsh(system)
    if eigenvalues[0] < 1e-3 * eigenvalues[-1]:
        return None
    point = np.linalg.solve(system, rhs)
    if float(((point - centres) * forwards).sum(axis=1).mean()) <= 0:
        return None
    return point


def fov_intrinsics(width: int, height: int, fov_deg: float = DEFAULT_FOV_DEG,
                   principal_offset: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """K [3, 3] for a horizontal field of view, square pixels and the principal point at the image centre
    (W / 2, H / 2) plus `principal_offset` pixels."""
    focal = 0.5 * width / np.tan(np.radians(fov_deg) / 2)
    return np.array([[focal, 0.0, width / 2 + principal_offset[0]],
                     [0.0, focal, height / 2 + principal_offset[1]],
                     [0.0, 0.0, 1.0]], np.float64)


def look_at_viewmat(eye, target, up=WORLD_UP, roll_deg: float = 0.0) -> np.ndarray:
    """World-to-camera viewmat [4, 4] of a camera at `eye` [3] looking at `target` [3], its image up towards
    `up` [3] (any direction when looking along `up`), turned by `roll_deg` about the optical axis."""
    eye, target = np.asarray(eye, np.float64), np.asarray(target, np.float64)
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-6:  # looking straight along up
        right = np.array([1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    roll = np.radians(roll_deg)
    right, down = np.cos(roll) * right + np.sin(roll) * down, -np.sin(roll) * right + np.cos(roll) * down
    viewmat = np.eye(4)
    viewmat[:3, :3] = np.stack([right, down, forward])
    viewmat[:3, 3] = -viewmat[:3, :3] @ eye
    return viewmat
