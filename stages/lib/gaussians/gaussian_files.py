"""The bytes of Gaussian model files, read within bounds and checked (numpy only, no torch: preflight reads a user's
model with it before any stage runs); stages/lib/gaussians/ply.py turns them into Gaussians.

Inria PLY: an ASCII header (at most MAX_HEADER_BYTES, binary little endian, a `vertex` element of scalar
properties) and count x record bytes, which the file must hold before anything is allocated. .splat: 32-byte
records (SPLAT_RECORD). Every value a Gaussian is made of must be finite (positions, SH colours, opacities,
scales, rotations), a .splat's scales positive, and a model holds at least one Gaussian. Each error is a
StageError naming the file.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from stages.contract.errors import StageError
from stages.lib.file_checks import check_declared, regular_file, require_finite

PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
SPLAT_RECORD = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])
MAX_HEADER_BYTES = 1 << 16  # a 3DGS header is about 1.5 KB
REQUIRED = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
            "rot_0", "rot_1", "rot_2", "rot_3")
PLY_FIELDS = {"positions": ("x", "y", "z"), "colours": ("f_dc_", "f_rest_"), "opacities": ("opacity",),
              "scales": ("scale_",), "rotations": ("rot_",)}  # what a Gaussian is made of: name prefixes


def _header_line(path: Path, handle, read: int) -> tuple[list[str], int]:
    """The words of the next header line and the header bytes read so far; StageError past MAX_HEADER_BYTES."""
    line = handle.readline(MAX_HEADER_BYTES - read + 1)
    read += len(line)
    if read > MAX_HEADER_BYTES:
        raise StageError(f"Gaussian PLY {path}: header longer than {MAX_HEADER_BYTES} bytes (not a 3DGS PLY)")
    if not line:
        raise StageError(f"Gaussian PLY {path}: PLY header has no 'end_header'")
    return line.decode("ascii", errors="replace").split(), read


def _vertex_property(path: Path, words: list[str]) -> tuple[str, str]:
    """(name, numpy type) of a `property <type> <name>` line of the vertex element."""
    if len(words) != 3 or words[1] not in PLY_TYPES:
        raise StageError(f"Gaussian PLY {path}: unsupported vertex property '{' '.join(words[1:])}'")
    return words[2], "<" + PLY_TYPES[words[1]]


def read_header(path: Path, handle) -> tuple[int, np.dtype]:
    """Parse a PLY header from `handle` (at the file's start); returns (vertex count, vertex record dtype)."""
    if handle.readline(8).strip() != b"ply":
        raise StageError(f"Gaussian PLY {path}: not a PLY file (missing 'ply' magic line)")
    count, properties, current, read = None, [], None, 0
    while True:
        words, read = _header_line(path, handle, read)
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format" and words[1:2] != ["binary_little_endian"]:
            raise StageError(f"Gaussian PLY {path}: PLY format '{' '.join(words[1:])}' is not supported (need "
                             "binary_little_endian)")
        if words[0] == "element":
            current = words[1] if len(words) == 3 else "?"
            if current == "vertex":
                count = int(words[2]) if words[2].isdigit() else -1
                if count < 0:
                    raise StageError(f"Gaussian PLY {path}: vertex count '{words[2][:40]}' is not a whole number")
            elif count is None:
                raise StageError(f"Gaussian PLY {path}: element '{' '.join(words[1:])}' before 'vertex' is not "
                                 "supported")
        if words[0] == "property" and current == "vertex":
            properties.append(_vertex_property(path, words))
    if count is None:
        raise StageError(f"Gaussian PLY {path}: PLY has no vertex element")
    names = [name for name, _ in properties]
    if len(set(names)) != len(names):
        raise StageError(f"Gaussian PLY {path}: repeated vertex properties")
    return count, np.dtype(properties)


def _check_layout(path: Path, names: tuple[str, ...]) -> None:
    """StageError unless the vertex properties are those of a 3DGS PLY (with f_rest of some SH degree)."""
    missing = [name for name in REQUIRED if name not in names]
    if missing:
        raise StageError(f"Gaussian PLY {path}: not a 3DGS PLY, missing vertex properties {missing}")
    rest = sum(1 for name in names if name.startswith("f_rest_"))
    coeffs = rest // 3 + 1
    if rest % 3 or round(math.sqrt(coeffs)) ** 2 != coeffs or any(f"f_rest_{i}" not in names for i in range(rest)):
        raise StageError(f"Gaussian PLY {path}: {rest} f_rest properties do not match any SH degree")


def read_ply_vertices(path: str | Path) -> np.ndarray:
    """The vertex records [N] (a structured array of the header's properties) of a 3DGS PLY, checked: the header,
    the data size it declares against the file's, the 3DGS properties, N >= 1 and finite values."""
    path = Path(path)
    size = regular_file(path, "Gaussian PLY")
    with open(path, "rb") as handle:
        count, dtype = read_header(path, handle)
        check_declared(path, "Gaussian PLY", count * dtype.itemsize, size - handle.tell(),
                       f"{count} vertices of {dtype.itemsize} bytes")
        data = np.frombuffer(handle.read(count * dtype.itemsize), dtype=dtype)
    _check_layout(path, dtype.names)
    if count == 0:
        raise StageError(f"Gaussian PLY {path}: holds no Gaussians (vertex count 0)")
    require_finite(path, "Gaussian PLY", **{
        what: np.stack([data[name] for name in dtype.names if name.startswith(prefixes)], axis=1)
        for what, prefixes in PLY_FIELDS.items()})
    return data


def read_splat_records(path: str | Path) -> np.ndarray:
    """The records [N] (SPLAT_RECORD) of a .splat file, checked: a whole number of records, N >= 1, finite
    positions and finite positive scales (its colours and rotations are bytes)."""
    path = Path(path)
    size = regular_file(path, ".splat file")
    if size % SPLAT_RECORD.itemsize:
        raise StageError(f".splat file {path}: size {size} bytes is not a multiple of the 32-byte .splat record")
    if size == 0:
        raise StageError(f".splat file {path}: holds no Gaussians (empty file)")
    records = np.fromfile(path, dtype=SPLAT_RECORD)
    require_finite(path, ".splat file", positions=records["position"], scales=records["scale"])
    if (records["scale"] <= 0).any():
        raise StageError(f".splat file {path}: holds non-positive scales (expects linear scales)")
    return records


def model_suffix(path: Path) -> str:
    """The suffix of a Gaussian model file, ".ply" or ".splat"; StageError naming the file for another."""
    suffix = Path(path).suffix.lower()
    if suffix not in (".ply", ".splat"):
        raise StageError(f"{path}: unknown Gaussian model format {suffix!r}; give an Inria-layout .ply (3DGS output) "
                         "or a .splat file")
    return suffix


def check_gaussian_file(path: str | Path) -> None:
    """Read and check a Gaussian model file by its suffix (.ply or .splat); StageError naming what is wrong."""
    {".ply": read_ply_vertices, ".splat": read_splat_records}[model_suffix(Path(path))](path)
