"""EWA projection of 3D Gaussians to screen-space 2D Gaussians (differentiable, pure PyTorch)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from stages.lib.gaussians.model import quat_to_rotmat

ALPHA_MIN = 1.0 / 255.0  # contributions below this opacity are skipped (3DGS)


@dataclass
class Projection:
    """Screen-space Gaussians. Pixel centres are at integer + 0.5 (OpenCV K convention)."""

    means2d: torch.Tensor  # [N, 2] pixel positions
    conics: torch.Tensor  # [N, 3] inverse 2D covariance (a, b, c): q = a dx^2 + 2 b dx dy + c dy^2
    depths: torch.Tensor  # [N] camera z
    radii: torch.Tensor  # [N] int32, ceil(3 sigma_max) in pixels; 0 = not visible
    extents: torch.Tensor  # [N, 2] half-size in pixels (x, y) of where alpha >= 1/255; 0 = not visible


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
    # cov2d = (J W R S)(J W R S)^T, written out elementwise: batched 3x3 matmuls (bmm) of tiny
    # matrices cost several times more on the CPU.
    rs = quat_to_rotmat(quats) * scales.unsqueeze(-2)  # [N, 3, 3] world <- local, columns scaled
    cam_rs = torch.einsum("ij,njk->nik", rot, rs)  # [N, 3, 3] camera <- local
    j0 = torch.stack([fx / z_safe, torch.zeros_like(z), -fx * tx / z_safe**2], dim=-1)  # [N, 3]
    j1 = torch.stack([torch.zeros_like(z), fy / z_safe, -fy * ty / z_safe**2], dim=-1)  # [N, 3]
    m0 = (j0.unsqueeze(-1) * cam_rs).sum(-2)  # [N, 3] first row of J W R S
    m1 = (j1.unsqueeze(-1) * cam_rs).sum(-2)  # [N, 3] second row
    cov2d_xx, cov2d_xy, cov2d_yy = (m0 * m0).sum(-1), (m0 * m1).sum(-1), (m1 * m1).sum(-1)
    a = cov2d_xx + eps2d
    b = cov2d_xy
    c = cov2d_yy + eps2d
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
