"""A box room with a table, ray cast exactly: metric depth, the support mask and the camera's height, for checks
of relative-depth recovery (stages/lib/depth/recovery.py) and the depth models (tests/factories/depth_models.py)."""
from __future__ import annotations

import numpy as np

from stages.lib.geometry import fov_intrinsics

ROOM_HALF_WIDTH, ROOM_DEPTH, ROOM_HEIGHT = 2.5, 5.0, 2.7  # metres: walls x = +-half width, y = depth; ceiling
TABLE = (-0.9, 0.5, 1.8, 2.6, 0.75)  # x0, x1, y0, y1, top height (metres); its front face is y = y0


def room_depth(width: int = 160, height: int = 120, camera_height: float = 1.4, pitch_deg: float = 25.0,
               yaw_deg: float = 15.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(depth [H, W] float32 camera-z metres, support [H, W] bool (floor and table top), K [3, 3] of the 55
    degree camera) of the room seen from (0, 0, camera_height) looking along +y, pitched down and turned by yaw."""
    K = fov_intrinsics(width, height)
    pitch, yaw = np.radians(pitch_deg), np.radians(yaw_deg)
    forward = np.array([np.sin(yaw) * np.cos(pitch), np.cos(yaw) * np.cos(pitch), -np.sin(pitch)])
    right = np.array([np.cos(yaw), -np.sin(yaw), 0.0])
    down = np.cross(forward, right)
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    rays = (((u - K[0, 2]) / K[0, 0])[..., None] * right + ((v - K[1, 2]) / K[1, 1])[..., None] * down
            + forward)                                                         # [H, W, 3] world, camera z = 1
    centre = np.array([0.0, 0.0, camera_height])
    hits = {name: np.full((height, width), np.inf) for name in ("floor", "ceiling", "walls", "top", "front")}
    with np.errstate(divide="ignore", invalid="ignore"):
        hits["floor"] = np.where(rays[..., 2] < 0, -camera_height / rays[..., 2], np.inf)
        hits["ceiling"] = np.where(rays[..., 2] > 0, (ROOM_HEIGHT - camera_height) / rays[..., 2], np.inf)
        back = np.where(rays[..., 1] > 0, ROOM_DEPTH / rays[..., 1], np.inf)
        side = np.where(rays[..., 0] != 0, np.sign(rays[..., 0]) * ROOM_HALF_WIDTH / rays[..., 0], np.inf)
        hits["walls"] = np.minimum(back, side)
        x0, x1, y0, y1, top = TABLE
        t_top = np.where(rays[..., 2] < 0, (top - camera_height) / rays[..., 2], np.inf)
        on_top = _inside(centre + t_top[..., None] * rays, (x0, x1), (y0, y1), axes=(0, 1))
        hits["top"] = np.where(on_top, t_top, np.inf)
        t_front = np.where(rays[..., 1] > 0, y0 / rays[..., 1], np.inf)
        on_front = _inside(centre + t_front[..., None] * rays, (x0, x1), (0.0, top), axes=(0, 2))
        hits["front"] = np.where(on_front, t_front, np.inf)
    stack = np.stack(list(hits.values()))                                      # [5, H, W]
    nearest = np.argmin(stack, axis=0)
    depth = np.min(stack, axis=0)
    support = (nearest == 0) | (nearest == 3)
    return np.where(np.isfinite(depth), depth, 0.0).astype(np.float32), support, K


def _inside(points: np.ndarray, first: tuple[float, float], second: tuple[float, float],
            axes: tuple[int, int]) -> np.ndarray:
    """Whether points [..., 3] lie in the rectangle first x second of coordinates `axes`."""
    a, b = points[..., axes[0]], points[..., axes[1]]
    return (a >= first[0]) & (a <= first[1]) & (b >= second[0]) & (b <= second[1])


def affine_disparity(depth: np.ndarray, scale: float, shift: float) -> np.ndarray:
    """What a relative depth model gives for depth [H, W] (0 = none): scale * (1 / depth) / median + shift * scale,
    i.e. disparity normalised to median 1, shifted by `shift` and scaled; 0 where there is no depth."""
    valid = depth > 0
    inverse = np.where(valid, 1.0 / np.where(valid, depth, 1.0), 0.0)
    return np.where(valid, scale * (inverse / np.median(inverse[valid]) + shift), 0.0).astype(np.float32)
