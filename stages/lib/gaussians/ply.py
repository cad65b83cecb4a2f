"""Gaussian file formats: the original Inria 3DGS binary PLY (read and write) and 32-byte .splat (read).

Inria PLY vertex properties (all float32, binary little endian), in this order:
x y z, nx ny nz (zeros), f_dc_0..2, f_rest_0..(3*(K-1)-1) (channel-major: all red coefficients of
bands >= 1, then green, then blue), opacity (logit), scale_0..2 (log), rot_0..3 (w x y z).

.splat records (antimatter15 viewer layout): position 3 x f32, scale 3 x f32 (linear), RGBA 4 x u8
(colour = 0.5 + C0 * dc, alpha = opacity), rotation 4 x u8 (w x y z, q = (byte - 128) / 128).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from stages.lib.gaussians.gaussian_files import model_suffix, read_ply_vertices, read_splat_records
from stages.lib.gaussians.model import SH_C0, Gaussians

OPACITY_EPS = 1.0 / 512.0  # keeps logit finite for alpha bytes 0 and 255


def read_ply(path: str | Path) -> Gaussians:
    """Load an Inria-layout 3DGS PLY (any SH degree 0-3) as Gaussians (float32, CPU); StageError naming the file
    when it is not one, is truncated or holds non-finite values (stages/lib/gaussians/gaussian_files.py)."""
    data = read_ply_vertices(path)  # [N] records
    count = data.shape[0]
    rest_count = sum(1 for name in data.dtype.names if name.startswith("f_rest_"))
    coeffs = rest_count // 3 + 1

    def columns(*keys: str) -> torch.Tensor:
        return torch.from_numpy(np.stack([data[k].astype(np.float32) for k in keys], axis=1))

    sh = torch.zeros(count, coeffs, 3)
    sh[:, 0] = columns("f_dc_0", "f_dc_1", "f_dc_2")
    if coeffs > 1:
        rest = columns(*[f"f_rest_{i}" for i in range(rest_count)])  # [N, 3*(K-1)]
        sh[:, 1:] = rest.reshape(count, 3, coeffs - 1).transpose(1, 2)
    quats = columns("rot_0", "rot_1", "rot_2", "rot_3")
    quats = quats / quats.norm(dim=1, keepdim=True).clamp_min(1e-12)
    return Gaussians(
        means=columns("x", "y", "z"),
        log_scales=columns("scale_0", "scale_1", "scale_2"),
        quats=quats,
        opacity_logits=columns("opacity")[:, 0],
        sh=sh,
    )


def write_ply(path: str | Path, g: Gaussians) -> None:
    """Write Gaussians in the Inria 3DGS binary PLY layout (loads in common splat viewers)."""
    g = g.detach().to("cpu")
    coeffs = g.sh.shape[1]
    names = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
             + [f"f_rest_{i}" for i in range(3 * (coeffs - 1))]
             + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    values = torch.cat([
        g.means, torch.zeros(g.num, 3), g.sh[:, 0],
        g.sh[:, 1:].transpose(1, 2).reshape(g.num, -1),
        g.opacity_logits[:, None], g.log_scales, g.quats,
    ], dim=1).float().numpy()  # [N, len(names)]
    header = "\n".join(["ply", "format binary_little_endian 1.0", f"element vertex {g.num}"]
                       + [f"property float {name}" for name in names] + ["end_header"]) + "\n"
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as handle:
        handle.write(header.encode("ascii"))
        handle.write(np.ascontiguousarray(values, dtype="<f4").tobytes())


def read_splat(path: str | Path) -> Gaussians:
    """Load a 32-byte-record .splat file as SH-degree-0 Gaussians (float32, CPU); StageError naming the file when
    it is not one (stages/lib/gaussians/gaussian_files.py)."""
    records = read_splat_records(path)  # [N] SPLAT_RECORD
    scales = records["scale"].astype(np.float32)
    rgba = torch.from_numpy(records["rgba"].astype(np.float32) / 255.0)  # [N, 4]
    quats = (torch.from_numpy(records["rot"].astype(np.float32)) - 128.0) / 128.0  # [N, 4] w x y z
    norms = quats.norm(dim=1, keepdim=True)
    quats = torch.where(norms > 1e-6, quats / norms.clamp_min(1e-6), torch.tensor([1.0, 0.0, 0.0, 0.0]))
    alpha = rgba[:, 3].clamp(OPACITY_EPS, 1.0 - OPACITY_EPS)
    return Gaussians(
        means=torch.from_numpy(records["position"].astype(np.float32)),
        log_scales=torch.log(torch.from_numpy(scales)),
        quats=quats,
        opacity_logits=torch.log(alpha / (1.0 - alpha)),
        sh=((rgba[:, :3] - 0.5) / SH_C0)[:, None, :],
    )


def read_gaussians(path: str | Path) -> Gaussians:
    """Load a Gaussian model by its suffix: an Inria-layout .ply or a .splat file."""
    return {".ply": read_ply, ".splat": read_splat}[model_suffix(Path(path))](path)
