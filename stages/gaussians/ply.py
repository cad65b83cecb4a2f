"""Gaussian file formats: the original Inria 3DGS binary PLY (read and write) and 32-byte .splat (read).

Inria PLY vertex properties (all float32, binary little endian), in this order:
x y z, nx ny nz (zeros), f_dc_0..2, f_rest_0..(3*(K-1)-1) (channel-major: all red coefficients of
bands >= 1, then green, then blue), opacity (logit), scale_0..2 (log), rot_0..3 (w x y z).

.splat records (antimatter15 viewer layout): position 3 x f32, scale 3 x f32 (linear), RGBA 4 x u8
(colour = 0.5 + C0 * dc, alpha = opacity), rotation 4 x u8 (w x y z, q = (byte - 128) / 128).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from stages.errors import StageError
from stages.gaussians.model import SH_C0, Gaussians

PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
SPLAT_RECORD = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])
OPACITY_EPS = 1.0 / 512.0  # keeps logit finite for alpha bytes 0 and 255


def _read_header(path: Path, handle) -> tuple[int, np.dtype]:
    """Parse a PLY header; returns (vertex count, vertex record dtype). Needs binary little endian."""
    if handle.readline().strip() != b"ply":
        raise StageError(f"{path}: not a PLY file (missing 'ply' magic line)")
    count, properties, current = None, [], None
    while True:
        line = handle.readline()
        if not line:
            raise StageError(f"{path}: PLY header has no 'end_header'")
        words = line.decode("ascii", errors="replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format" and words[1] != "binary_little_endian":
            raise StageError(f"{path}: PLY format '{words[1]}' is not supported (need binary_little_endian)")
        if words[0] == "element":
            current = words[1]
            if current == "vertex":
                count = int(words[2])
            elif count is None:
                raise StageError(f"{path}: element '{current}' before 'vertex' is not supported")
        if words[0] == "property" and current == "vertex":
            if words[1] == "list" or words[1] not in PLY_TYPES:
                raise StageError(f"{path}: unsupported vertex property '{' '.join(words[1:])}'")
            properties.append((words[2], "<" + PLY_TYPES[words[1]]))
    if count is None:
        raise StageError(f"{path}: PLY has no vertex element")
    return count, np.dtype(properties)


def read_ply(path: str | Path) -> Gaussians:
    """Load an Inria-layout 3DGS PLY (any SH degree 0-3) as Gaussians (float32, CPU)."""
    path = Path(path)
    if not path.is_file():
        raise StageError(f"{path}: Gaussian PLY file not found")
    with open(path, "rb") as handle:
        count, dtype = _read_header(path, handle)
        data = np.frombuffer(handle.read(count * dtype.itemsize), dtype=dtype)
    if data.shape[0] != count:
        raise StageError(f"{path}: truncated PLY: header says {count} vertices, file holds {data.shape[0]}")
    names = set(dtype.names)
    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
                "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [name for name in required if name not in names]
    if missing:
        raise StageError(f"{path}: not a 3DGS PLY, missing vertex properties {missing}")
    rest_count = sum(1 for name in names if name.startswith("f_rest_"))
    coeffs = rest_count // 3 + 1
    if rest_count % 3 or round(math.sqrt(coeffs)) ** 2 != coeffs:
        raise StageError(f"{path}: {rest_count} f_rest properties do not match any SH degree")

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
    """Load a 32-byte-record .splat file as SH-degree-0 Gaussians (float32, CPU)."""
    path = Path(path)
    if not path.is_file():
        raise StageError(f"{path}: .splat file not found")
    raw = path.read_bytes()
    if len(raw) % SPLAT_RECORD.itemsize:
        raise StageError(f"{path}: size {len(raw)} bytes is not a multiple of the 32-byte .splat record")
    records = np.frombuffer(raw, dtype=SPLAT_RECORD)
    scales = records["scale"].astype(np.float32)
    if (scales <= 0).any() or not np.isfinite(scales).all():
        raise StageError(f"{path}: .splat holds non-positive or non-finite scales (expects linear scales)")
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


MODEL_READERS = {".ply": read_ply, ".splat": read_splat}


def read_gaussians(path: str | Path) -> Gaussians:
    """Load a Gaussian model by its suffix: an Inria-layout .ply or a .splat file."""
    path = Path(path)
    reader = MODEL_READERS.get(path.suffix.lower())
    if reader is None:
        raise StageError(f"{path}: unknown Gaussian model format {path.suffix!r}; give an Inria-layout .ply "
                         "(3DGS output) or a .splat file")
    return reader(path)
