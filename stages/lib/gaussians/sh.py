"""Real spherical harmonics up to degree 3 (the 3DGS basis and sign convention)."""
from __future__ import annotations

import torch

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
      0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435)
MAX_DEGREE = 3


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients per colour channel for `degree`: (degree + 1) ** 2."""
    return (degree + 1) ** 2


def sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """Evaluate the real SH basis functions of bands 0..degree.

    dirs: [N, 3] unit directions. Returns [N, (degree + 1) ** 2].
    """
    if not 0 <= degree <= MAX_DEGREE:
        raise ValueError(f"SH degree must be in 0..{MAX_DEGREE}, got {degree}")
    x, y, z = dirs.unbind(-1)
    bases = [torch.full_like(x, C0)]
    if degree >= 1:
        bases += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        bases += [C2[0] * xy, C2[1] * yz, C2[2] * (2.0 * zz - xx - yy), C2[3] * xz,
                  C2[4] * (xx - yy)]
    if degree >= 3:
        bases += [C3[0] * y * (3.0 * xx - yy), C3[1] * xy * z, C3[2] * y * (4.0 * zz - xx - yy),
                  C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy), C3[4] * x * (4.0 * zz - xx - yy),
                  C3[5] * z * (xx - yy), C3[6] * x * (xx - 3.0 * yy)]
    return torch.stack(bases, dim=-1)


def eval_sh(degree: int, sh: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Sum the SH expansion of bands 0..degree in direction `dirs` (normalised here).

    sh: [N, K, 3] coefficients with K >= (degree + 1) ** 2 (extra bands are ignored);
    dirs: [N, 3] or [3] (broadcast). Returns [N, 3], the raw sum: 3DGS colour is
    clamp_min(0.5 + eval_sh(...), 0).
    """
    k = num_sh_bases(degree)
    if sh.shape[-2] < k:
        raise ValueError(f"SH degree {degree} needs {k} coefficients, tensor has {sh.shape[-2]}")
    dirs = torch.nn.functional.normalize(dirs.to(sh.dtype), dim=-1).expand(sh.shape[0], 3)
    basis = sh_basis(degree, dirs)  # [N, k]
    return (basis.unsqueeze(-1) * sh[:, :k]).sum(dim=-2)
