"""Textured triangle meshes and the primitives the sample's scenes are built from (units: metres)."""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np


@dataclass
class Mesh:
    """One textured surface with a Blinn-Phong material.

    vertices [V, 3] float32, triangles [F, 3] int32, uvs [V, 2] float32 (texture repeats outside [0, 1]),
    normals [V, 3] float32 shading normals, texture [Th, Tw, 3] sRGB float32.
    label: 0 for the scene, k > 0 for object instance k. support: its upward faces are horizontal
    support surfaces (floors, table tops, shelf boards) for the support ground truth.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    uvs: np.ndarray
    normals: np.ndarray
    texture: np.ndarray
    specular: float = 0.04
    shininess: float = 16.0
    label: int = 0
    support: bool = False

    def transformed(self, rotation: np.ndarray, translation, scale: float = 1.0) -> "Mesh":
        """The mesh moved by x' = scale * R @ x + t (R [3, 3], t [3])."""
        rotation = np.asarray(rotation, np.float32)
        vertices = scale * self.vertices @ rotation.T + np.asarray(translation, np.float32)
        return replace(self, vertices=vertices.astype(np.float32), normals=(self.normals @ rotation.T).astype(np.float32))

    def with_material(self, **changes) -> "Mesh":
        """A copy with some fields changed (label, support, specular, ...)."""
        return replace(self, **changes)


def rotation_z(angle: float) -> np.ndarray:
    """Rotation by `angle` radians about +z, [3, 3]."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], np.float32)


def box(center, size, texture: np.ndarray, tile_m: float = 0.5, **material) -> Mesh:
    """Axis-aligned box of `size` (dx, dy, dz) at `center`; UVs in metres / tile_m on every face."""
    center, half = np.asarray(center, np.float32), np.asarray(size, np.float32) / 2
    vertices, uvs, normals, triangles = [], [], [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            a, b = [k for k in range(3) if k != axis]
            normal = np.zeros(3, np.float32)
            normal[axis] = sign
            corners = []
            for ca, cb in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                p = np.zeros(3, np.float32)
                p[axis], p[a], p[b] = sign * half[axis], ca * half[a], cb * half[b]
                corners.append(p)
            base = len(vertices)
            for p in corners:
                vertices.append(center + p)
                uvs.append([(p[a] + half[a]) / tile_m, (p[b] + half[b]) / tile_m])
                normals.append(normal)
            # wind counter-clockwise seen from outside
            if np.dot(np.cross(corners[1] - corners[0], corners[2] - corners[0]), normal) > 0:
                triangles += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
            else:
                triangles += [[base, base + 2, base + 1], [base, base + 3, base + 2]]
    return Mesh(np.array(vertices, np.float32), np.array(triangles, np.int32), np.array(uvs, np.float32),
                np.array(normals, np.float32), texture, **material)


def _profile_normals(radius: np.ndarray, height: np.ndarray) -> np.ndarray:
    """Outward (r, z) normals [N, 2] of a profile going upward; repeated points make sharp corners."""
    points = np.stack([radius, height], axis=1)
    n = len(points)
    tangents = np.zeros_like(points)
    for i in range(n):
        prev_i, next_i = max(i - 1, 0), min(i + 1, n - 1)
        if next_i != i and np.allclose(points[next_i], points[i]):
            next_i = i
        if prev_i != i and np.allclose(points[prev_i], points[i]):
            prev_i = i
        tangents[i] = points[next_i] - points[prev_i]
    normals = np.stack([tangents[:, 1], -tangents[:, 0]], axis=1)
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-9)


def revolve(radius, height, texture: np.ndarray, segments: int = 48, **material) -> Mesh:
    """Surface of revolution about +z of the profile (radius [N], height [N]) listed bottom to top.

    u runs around (one texture width per turn), v along the profile's arc length (0 bottom, 1 top).
    """
    radius, height = np.asarray(radius, np.float32), np.asarray(height, np.float32)
    normals_rz = _profile_normals(radius, height)
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(radius), np.diff(height)))])
    v = (arc / max(arc[-1], 1e-9)).astype(np.float32)
    theta = np.linspace(0, 2 * np.pi, segments + 1, dtype=np.float32)
    c, s = np.cos(theta)[None, :], np.sin(theta)[None, :]
    vertices = np.stack([radius[:, None] * c, radius[:, None] * s, np.broadcast_to(height[:, None], (len(radius), segments + 1))], -1)
    normals = np.stack([normals_rz[:, :1] * c, normals_rz[:, :1] * s, np.broadcast_to(normals_rz[:, 1:], vertices.shape[:2])], -1)
    uvs = np.stack(np.broadcast_arrays(theta[None, :] / (2 * np.pi), 1.0 - v[:, None]), -1)
    rows, cols = len(radius), segments + 1
    i, j = np.meshgrid(np.arange(rows - 1), np.arange(segments), indexing="ij")
    a, b, cc, d = i * cols + j, i * cols + j + 1, (i + 1) * cols + j + 1, (i + 1) * cols + j
    triangles = np.concatenate([np.stack([a, b, cc], -1).reshape(-1, 3), np.stack([a, cc, d], -1).reshape(-1, 3)])
    return Mesh(vertices.reshape(-1, 3).astype(np.float32), triangles.astype(np.int32), uvs.reshape(-1, 2).astype(np.float32),
                normals.reshape(-1, 3).astype(np.float32), texture, **material)


def tube(path, radius: float, texture: np.ndarray, segments: int = 12, **material) -> Mesh:
    """A closed-ring tube of constant `radius` along `path` [N, 3] (handles, stems, table legs)."""
    path = np.asarray(path, np.float32)
    tangents = np.gradient(path, axis=0)
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    ref = np.array([0, 0, 1], np.float32) if abs(tangents[0, 2]) < 0.9 else np.array([1, 0, 0], np.float32)
    side = np.cross(tangents, ref)
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    up = np.cross(side, tangents)
    theta = np.linspace(0, 2 * np.pi, segments + 1, dtype=np.float32)
    normals = np.cos(theta)[None, :, None] * side[:, None] + np.sin(theta)[None, :, None] * up[:, None]
    vertices = path[:, None] + radius * normals
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
    uvs = np.stack(np.broadcast_arrays(theta[None, :] / (2 * np.pi), arc[:, None] / max(arc[-1], 1e-9)), -1)
    rows, cols = len(path), segments + 1
    i, j = np.meshgrid(np.arange(rows - 1), np.arange(segments), indexing="ij")
    a, b, c, d = i * cols + j, i * cols + j + 1, (i + 1) * cols + j + 1, (i + 1) * cols + j
    triangles = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    return Mesh(vertices.reshape(-1, 3).astype(np.float32), triangles.astype(np.int32), uvs.reshape(-1, 2).astype(np.float32),
                normals.reshape(-1, 3).astype(np.float32), texture, **material)


def ribbon(spine, widths, sides, texture: np.ndarray, **material) -> Mesh:
    """A two-sided strip (a leaf blade) along `spine` [N, 3] with half-widths [N] along `sides` [N, 3].

    u across the strip (0..1), v along it; normals are the strip's surface normals (the ray tracer
    shades both sides).
    """
    spine, sides = np.asarray(spine, np.float32), np.asarray(sides, np.float32)
    widths = np.asarray(widths, np.float32)[:, None]
    left, right = spine - widths * sides, spine + widths * sides
    vertices = np.stack([left, right], 1).reshape(-1, 3)
    tangents = np.gradient(spine, axis=0)
    normal = np.cross(sides, tangents)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-9)
    normals = np.repeat(normal, 2, axis=0)
    v = np.linspace(0, 1, len(spine), dtype=np.float32)
    uvs = np.stack([np.tile([0.0, 1.0], len(spine)), np.repeat(v, 2)], 1)
    k = np.arange(len(spine) - 1) * 2
    triangles = np.concatenate([np.stack([k, k + 1, k + 3], 1), np.stack([k, k + 3, k + 2], 1)])
    return Mesh(vertices.astype(np.float32), triangles.astype(np.int32), uvs.astype(np.float32),
                normals.astype(np.float32), texture, **material)


def sample_surface(meshes: list[Mesh], count: int, rng: np.random.Generator) -> np.ndarray:
    """Area-weighted random points [count, 3] float32 on the union of `meshes`."""
    corners = np.concatenate([m.vertices[m.triangles] for m in meshes])  # [F, 3, 3]
    areas = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    picks = rng.choice(len(corners), size=count, p=areas / areas.sum())
    r1, r2 = rng.uniform(size=(2, count, 1))
    s = np.sqrt(r1)
    tri = corners[picks]
    points = (1 - s) * tri[:, 0] + s * (1 - r2) * tri[:, 1] + s * r2 * tri[:, 2]
    return points.astype(np.float32)


def bounds(meshes: list[Mesh]) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds (min [3], max [3]) of `meshes`."""
    vertices = np.concatenate([m.vertices for m in meshes])
    return vertices.min(0), vertices.max(0)
