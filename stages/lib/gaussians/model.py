"""The Gaussian scene model: a dataclass of per-Gaussian tensors plus its geometric operations.

Conventions (shared by the whole `stages.lib.gaussians` package):
- `means` [N, 3] world positions; `log_scales` [N, 3] natural-log standard deviations along the
  Gaussian's local axes; `quats` [N, 4] unit quaternions (w, x, y, z) rotating local axes to world;
  `opacity_logits` [N] (opacity = sigmoid); `sh` [N, K, 3] real spherical-harmonic colour
  coefficients with K = (degree + 1) ** 2 and `sh[:, 0]` the DC term (colour = 0.5 + C0 * sh_dc).
- A world covariance is Sigma = R(q) diag(exp(log_scales))^2 R(q)^T.
- `transformed` moves the Gaussians themselves (not the camera): positions, orientations, sizes and
  the view-dependent colour (SH bands rotated with the scene), so a transformed model renders like
  the original seen by a correspondingly moved camera.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np
import torch
from scipy.spatial import cKDTree

from stages.lib.gaussians.sh import sh_basis

SH_C0 = 0.28209479177387814
INIT_OPACITY = 0.1
SH_ROTATION_SAMPLES = 128  # directions used to fit each band's rotation matrix by least squares


def inverse_sigmoid(x: torch.Tensor) -> torch.Tensor:
    """logit(x) for x in (0, 1)."""
    return torch.log(x / (1.0 - x))


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices of (w, x, y, z) quaternions (normalised here).

    quats: [N, 4]. Returns [N, 3, 3].
    """
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(q.shape[:-1] + (3, 3))


def rotmat_to_quat(rotation: torch.Tensor) -> torch.Tensor:
    """Unit (w, x, y, z) quaternion of one proper rotation matrix [3, 3] (w >= 0). Returns [4]."""
    r = rotation.double()
    trace = r[0, 0] + r[1, 1] + r[2, 2]
    # Shepperd's method: pick the largest of 4w^2, 4x^2, 4y^2, 4z^2 for numerical stability.
    candidates = torch.stack([trace, r[0, 0], r[1, 1], r[2, 2]])
    largest = int(torch.argmax(candidates))
    if largest == 0:
        s = torch.sqrt(1.0 + trace) * 2
        q = torch.stack([0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s])
    elif largest == 1:
        s = torch.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2]) * 2
        q = torch.stack([(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s])
    elif largest == 2:
        s = torch.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2]) * 2
        q = torch.stack([(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s])
    else:
        s = torch.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1]) * 2
        q = torch.stack([(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s])
    q = q / q.norm()
    return (q if q[0] >= 0 else -q).to(rotation.dtype)


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a * b of (w, x, y, z) quaternions. a: [..., 4], b: [..., 4]. Returns [..., 4]."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], dim=-1)


def fibonacci_sphere(count: int, dtype=torch.float64) -> torch.Tensor:
    """`count` well-spread unit directions [count, 3] (deterministic)."""
    i = torch.arange(count, dtype=dtype) + 0.5
    z = 1.0 - 2.0 * i / count
    radius = torch.sqrt(1.0 - z * z)
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    return torch.stack([radius * torch.cos(phi), radius * torch.sin(phi), z], dim=-1)


def sh_rotation_matrices(degree: int, rotation: torch.Tensor) -> list[torch.Tensor]:
    """Per-band matrices D_l [(2l+1), (2l+1)] (l = 1..degree) with Y_l(R^T d) = Y_l(d) @ D_l.

    A colour function f(d) = Y(d) c rotated by R is f'(d) = f(R^T d) = Y(d) (D c), so the rotated
    band coefficients are D_l @ c_l. Each D_l is fitted by least squares on well-spread directions
    (exact up to float precision since the rotated band spans the same space).
    """
    if degree == 0:
        return []
    dirs = fibonacci_sphere(SH_ROTATION_SAMPLES)  # [M, 3] float64
    rotated_back = dirs @ rotation.double()  # rows are R^T d  [M, 3]
    basis = sh_basis(degree, dirs)  # [M, K]
    basis_rotated = sh_basis(degree, rotated_back)  # [M, K]
    matrices = []
    for band in range(1, degree + 1):
        band_slice = slice(band * band, (band + 1) * (band + 1))
        solution = torch.linalg.lstsq(basis[:, band_slice], basis_rotated[:, band_slice]).solution
        matrices.append(solution)
    return matrices


@dataclass
class Gaussians:
    """A set of 3D Gaussians (see the module docstring for conventions)."""

    means: torch.Tensor  # [N, 3]
    log_scales: torch.Tensor  # [N, 3]
    quats: torch.Tensor  # [N, 4] (w, x, y, z), unit
    opacity_logits: torch.Tensor  # [N]
    sh: torch.Tensor  # [N, K, 3], K = (degree + 1) ** 2

    def __post_init__(self) -> None:
        n = self.means.shape[0]
        k = self.sh.shape[1] if self.sh.dim() == 3 else -1
        if (self.means.shape != (n, 3) or self.log_scales.shape != (n, 3) or self.quats.shape != (n, 4)
                or self.opacity_logits.shape != (n,) or self.sh.dim() != 3 or self.sh.shape[0] != n
                or self.sh.shape[2] != 3 or round(math.sqrt(k)) ** 2 != k):
            raise ValueError(
                "inconsistent Gaussian tensor shapes: means %s, log_scales %s, quats %s, opacity_logits %s, sh %s"
                % tuple(tuple(t.shape) for t in (self.means, self.log_scales, self.quats, self.opacity_logits, self.sh)))

    @property
    def num(self) -> int:
        """Number of Gaussians N."""
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        """SH degree: K = (degree + 1) ** 2 coefficients per colour channel."""
        return round(math.sqrt(self.sh.shape[1])) - 1

    @property
    def opacities(self) -> torch.Tensor:
        """Opacities in (0, 1) [N]."""
        return torch.sigmoid(self.opacity_logits)

    @property
    def scales(self) -> torch.Tensor:
        """Standard deviations along the local axes [N, 3]."""
        return torch.exp(self.log_scales)

    @property
    def device(self) -> torch.device:
        """Device of the tensors."""
        return self.means.device

    def rotation_matrices(self) -> torch.Tensor:
        """Local-to-world rotations [N, 3, 3]."""
        return quat_to_rotmat(self.quats)

    def covariances(self) -> torch.Tensor:
        """World covariances R S S R^T [N, 3, 3]."""
        rs = self.rotation_matrices() * self.scales[:, None, :]  # [N, 3, 3], columns scaled
        return rs @ rs.transpose(1, 2)

    def _map(self, fn) -> Gaussians:
        return Gaussians(**{f.name: fn(getattr(self, f.name)) for f in fields(self)})

    def subset(self, mask_or_index: torch.Tensor | np.ndarray) -> Gaussians:
        """The Gaussians selected by a boolean mask [N] or an index array [M]."""
        select = torch.as_tensor(mask_or_index, device=self.device)
        return self._map(lambda t: t[select])

    def to(self, device: torch.device | str) -> Gaussians:
        """A copy on `device`."""
        return self._map(lambda t: t.to(device))

    def detach(self) -> Gaussians:
        """Detached tensors (no autograd history)."""
        return self._map(lambda t: t.detach())

    def clone(self) -> Gaussians:
        """Deep copy of the tensors."""
        return self._map(lambda t: t.clone())

    def with_sh_degree(self, degree: int) -> Gaussians:
        """The same Gaussians with SH truncated or zero-padded to `degree`."""
        k = (degree + 1) ** 2
        sh = self.sh[:, :k]
        if sh.shape[1] < k:
            sh = torch.cat([sh, sh.new_zeros(self.num, k - sh.shape[1], 3)], dim=1)
        return Gaussians(self.means, self.log_scales, self.quats, self.opacity_logits, sh)

    @staticmethod
    def cat(parts: list[Gaussians]) -> Gaussians:
        """Concatenation of several Gaussian sets with the same SH degree."""
        return Gaussians(**{f.name: torch.cat([getattr(p, f.name) for p in parts]) for f in fields(Gaussians)})

    def transformed(self, rotation: torch.Tensor, translation: torch.Tensor, scale: float = 1.0) -> Gaussians:
        """The similarity transform x' = scale * R @ x + t applied to the Gaussians.

        rotation: [3, 3] proper rotation; translation: [3]; scale > 0. Covariances become
        scale^2 R Sigma R^T and view-dependent colour is rotated with the scene (SH bands l >= 1).
        """
        dtype, device = self.means.dtype, self.device
        rotation = torch.as_tensor(rotation, dtype=torch.float64).cpu()
        translation = torch.as_tensor(translation, dtype=dtype, device=device).reshape(3)
        if not (torch.allclose(rotation @ rotation.T, torch.eye(3, dtype=torch.float64), atol=1e-4)
                and torch.det(rotation) > 0):
            raise ValueError("transformed() needs a proper rotation matrix (orthonormal, det +1)")
        if scale <= 0:
            raise ValueError(f"transformed() needs scale > 0, got {scale}")
        means = scale * self.means @ rotation.to(dtype=dtype, device=device).T + translation
        quat_r = rotmat_to_quat(rotation).to(dtype=self.quats.dtype, device=device)
        quats = quat_multiply(quat_r.expand_as(self.quats), self.quats)
        sh = self.sh.clone()
        for band, matrix in enumerate(sh_rotation_matrices(self.sh_degree, rotation), start=1):
            band_slice = slice(band * band, (band + 1) * (band + 1))
            sh[:, band_slice] = torch.einsum("ij,njc->nic", matrix.to(dtype=sh.dtype, device=device), sh[:, band_slice])
        return Gaussians(means, self.log_scales + math.log(scale), quats, self.opacity_logits.clone(), sh)

    @classmethod
    def from_points(cls, points: torch.Tensor | np.ndarray, colors: torch.Tensor | np.ndarray,
                    sh_degree: int = 3) -> Gaussians:
        """Isotropic Gaussians at points [N, 3] with colours [N, 3] in [0, 1] (3DGS initialisation).

        Each scale is the RMS distance to the 3 nearest neighbours, opacity 0.1, SH beyond DC zero.
        """
        means = torch.as_tensor(np.asarray(points, dtype=np.float32))
        colours = torch.as_tensor(np.asarray(colors, dtype=np.float32)).clamp(0.0, 1.0)
        if means.ndim != 2 or means.shape[1] != 3 or colours.shape != means.shape or means.shape[0] < 2:
            raise ValueError(f"from_points needs >= 2 points [N,3] and colours [N,3]; got {tuple(means.shape)}, "
                             f"{tuple(colours.shape)}")
        n = means.shape[0]
        neighbours = min(3, n - 1)
        dists, _ = cKDTree(means.numpy()).query(means.numpy(), k=neighbours + 1)
        mean_sq = np.mean(np.square(dists[:, 1:]), axis=1).clip(1e-7)  # [N]
        log_scales = torch.as_tensor(0.5 * np.log(mean_sq), dtype=torch.float32)[:, None].repeat(1, 3)
        quats = torch.zeros(n, 4)
        quats[:, 0] = 1.0
        opacity_logits = inverse_sigmoid(torch.full((n,), INIT_OPACITY))
        sh = torch.zeros(n, (sh_degree + 1) ** 2, 3)
        sh[:, 0] = (colours - 0.5) / SH_C0
        return cls(means, log_scales, quats, opacity_logits, sh)
