"""EWA projection of 3D Gaussians to screen-space 2D Gaussians (differentiable, pure PyTorch)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

ALPHA_MIN = 1.0 / 255.0  # contributions below this opacity are skipped (3DGS)


@dataclass
class Projection:
    """Screen-space Gaussians. Pixel centres are at integer + 0.5 (OpenCV K convention)."""

    means2d: torch.Tensor  # [N, 2] pixel positions
    conics: torch.Tensor  # [N, 3] inverse 2D covariance (a, b, c): q = a dx^2 + 2 b dx dy + c dy^2
    depths: torch.Tensor  # [N] camera z
    radii: torch.Tensor  # [N] int32, ceil(3 sigma_max) in pixels; 0 = not visible
    extents: torch.Tensor  # [N, 2] half-size in pixels (x, y) of where alpha >= 1/255; 0 = not visible


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices from quaternions (w, x, y, z), normalised here. [N, 4] -> [N, 3, 3]."""
    w, x, y, z = torch.nn.functional.normalize(quats, dim=-1).unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(-1, 3, 3)


def covariance_3d(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """World covariance R S S^T R^T. quats [N, 4] (w, x, y, z), scales [N, 3] -> [N, 3, 3]."""
    rs = quat_to_rotmat(quats) * scales.unsqueeze(-2)  # [N, 3, 3]
    return rs @ rs.transpose(-1, -2)


def project_gaussians(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                      opacities: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor,
                      width: int, height: int, *, eps2d: float = 0.3,
                      near: float = 0.01) -> Projection:
    """Project Gaussians with the EWA local affine approximation and a low-pass dilation.

    means [N, 3] world, quats [N, 4], scales [N, 3], opacities [N] in (0, 1), viewmat [4, 4]
    world-to-camera, K [3, 3]. The 2D covariance gets `eps2d` added to its diagonal (the 3DGS
    0.3 px anti-aliasing filter). As in 3DGS the Jacobian is evaluated at a position clamped to
    1.3x the field of view, so Gaussians far outside the image stay well conditioned. A Gaussian
    is visible when it is in front of `near`, its opacity can reach 1/255 and its alpha >= 1/255
    footprint overlaps the image.
    """
    rot, trans = viewmat[:3, :3], viewmat[:3, 3]
    p_cam = means @ rot.T + trans  # [N, 3]
    x, y, z = p_cam.unbind(-1)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    z_safe = torch.where(z > near, z, torch.ones_like(z))
    lim_x_pos = (width - cx) / fx + 0.3 * width / fx
    lim_x_neg = cx / fx + 0.3 * width / fx
    lim_y_pos = (height - cy) / fy + 0.3 * height / fy
    lim_y_neg = cy / fy + 0.3 * height / fy
    tx = z_safe * torch.minimum(torch.maximum(x / z_safe, -lim_x_neg), lim_x_pos)
    ty = z_safe * torch.minimum(torch.maximum(y / z_safe, -lim_y_neg), lim_y_pos)
    zeros = torch.zeros_like(z)
    jac = torch.stack([fx / z_safe, zeros, -fx * tx / z_safe**2,
                       zeros, fy / z_safe, -fy * ty / z_safe**2], dim=-1).reshape(-1, 2, 3)
    jw = jac @ rot  # [N, 2, 3]
    cov2d = jw @ covariance_3d(quats, scales) @ jw.transpose(-1, -2)  # [N, 2, 2]
    a = cov2d[:, 0, 0] + eps2d
    b = cov2d[:, 0, 1]
    c = cov2d[:, 1, 1] + eps2d
    det = a * c - b * b
    det_safe = torch.where(det > 0, det, torch.ones_like(det))
    conics = torch.stack([c / det_safe, -b / det_safe, a / det_safe], dim=-1)
    means2d = torch.stack([fx * x / z_safe + cx, fy * y / z_safe + cy], dim=-1)

    with torch.no_grad():
        mid = 0.5 * (a + c)
        lambda_max = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.1))
        radii = torch.ceil(3.0 * torch.sqrt(lambda_max))
        # alpha = o * exp(-q / 2) >= 1/255  <=>  q <= 2 ln(255 o): an ellipse with these half-sizes
        reach = 2.0 * torch.log(torch.clamp(opacities.detach() / ALPHA_MIN, min=1e-30))
        ext = torch.stack([torch.sqrt(torch.clamp(reach * a, min=0.0)),
                           torch.sqrt(torch.clamp(reach * c, min=0.0))], dim=-1)  # [N, 2]
        m2 = means2d.detach()
        on_screen = ((m2[:, 0] + ext[:, 0] > 0) & (m2[:, 0] - ext[:, 0] < width)
                     & (m2[:, 1] + ext[:, 1] > 0) & (m2[:, 1] - ext[:, 1] < height))
        visible = (z > near) & (det > 0) & (reach > 0) & on_screen & torch.isfinite(m2).all(-1)
        radii = torch.where(visible, radii, torch.zeros_like(radii)).to(torch.int32)
        extents = torch.where(visible.unsqueeze(-1), ext, torch.zeros_like(ext))
    return Projection(means2d=means2d, conics=conics, depths=z, radii=radii, extents=extents)


def tile_grid(width: int, height: int, tile_size: int) -> tuple[int, int]:
    """Number of tiles (x, y) covering a width x height image."""
    return math.ceil(width / tile_size), math.ceil(height / tile_size)
