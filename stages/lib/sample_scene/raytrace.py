"""Ray tracing with Open3D's RaycastingScene and Blinn-Phong shading in numpy.

Camera convention: OpenCV (x right, y down, z forward), `viewmat` world-to-camera [4, 4], `K` [3, 3]
with the top-left pixel's centre at (0.5, 0.5): pixel index (u, v) is sampled at (u + 0.5, v + 0.5).
Ray directions are K^-1 [u, v, 1] rotated into the world, so a hit's ray parameter is its camera z.
Radiance is linear; `photo.py` turns it into an sRGB picture.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from .meshes import Mesh
from .textures import srgb_to_linear

SHADOW_OFFSET_M = 1e-3
RAY_THREADS = {"count": 0}  # Open3D ray-casting threads (0 = all cores); worker processes set 1
SUPPORT_COS = 0.95  # a support pixel's surface normal is within ~18 degrees of +z


@dataclass
class Light:
    """A point light; radiance at distance d is colour / d^2 (linear RGB)."""

    position: np.ndarray  # [3]
    colour: np.ndarray  # [3]
    casts_shadows: bool = True


@dataclass
class Lighting:
    """Lights plus a constant ambient term (linear RGB [3])."""

    lights: list[Light]
    ambient: np.ndarray


@dataclass
class Render:
    """One rendered view. radiance [H, W, 3] linear; depth [H, W] camera z in metres (0 = no hit);
    label [H, W] int32 (0 = scene, k = object instance k); support [H, W] bool; mesh [H, W] int32 (-1 = none)."""

    radiance: np.ndarray
    depth: np.ndarray
    label: np.ndarray
    support: np.ndarray
    mesh: np.ndarray


class TracedScene:
    """Meshes loaded into an Open3D RaycastingScene, with per-triangle attributes for shading."""

    def __init__(self, meshes: list[Mesh]):
        if not meshes:
            raise ValueError("a scene needs at least one mesh")
        self.meshes = meshes
        self.scene = o3d.t.geometry.RaycastingScene()
        for mesh in meshes:
            self.scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(mesh.vertices, np.float32)),
                                     o3d.core.Tensor(np.ascontiguousarray(mesh.triangles, np.uint32)))
        counts = np.array([len(m.triangles) for m in meshes])
        self.offsets = np.concatenate([[0], np.cumsum(counts)[:-1]])
        self.tri_uvs = np.concatenate([m.uvs[m.triangles] for m in meshes]).astype(np.float32)  # [F, 3, 2]
        self.tri_normals = np.concatenate([m.normals[m.triangles] for m in meshes]).astype(np.float32)  # [F, 3, 3]
        self.labels = np.array([m.label for m in meshes], np.int32)
        self.supports = np.array([m.support for m in meshes], bool)
        self.specular = np.array([m.specular for m in meshes], np.float32)
        self.shininess = np.array([m.shininess for m in meshes], np.float32)
        self._pack_textures(meshes)

    def _pack_textures(self, meshes: list[Mesh]) -> None:
        """All textures (linear) in one flat texel array [T, 3]; per mesh its offset, width and height."""
        texels, offsets, first_use = [], [], {}
        total = 0
        for mesh in meshes:
            key = id(mesh.texture)
            if key not in first_use:
                first_use[key] = total
                texels.append(srgb_to_linear(mesh.texture).reshape(-1, 3))
                total += len(texels[-1])
            offsets.append(first_use[key])
        self.texels = np.concatenate(texels)
        self.tex_offset = np.array(offsets, np.int32)
        self.tex_width = np.array([m.texture.shape[1] for m in meshes], np.int32)
        self.tex_height = np.array([m.texture.shape[0] for m in meshes], np.int32)

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> dict[str, np.ndarray]:
        """First hits of rays (origins, directions [N, 3]): t [N], mesh [N] (-1 = miss), triangle [N], bary [N, 2], face normal [N, 3]."""
        rays = np.concatenate([origins, directions], axis=1).astype(np.float32)
        hits = self.scene.cast_rays(o3d.core.Tensor(rays), nthreads=RAY_THREADS["count"])
        t = hits["t_hit"].numpy()
        mesh = hits["geometry_ids"].numpy().astype(np.int64)
        hit = np.isfinite(t)
        mesh[~hit] = -1
        triangle = np.where(hit, hits["primitive_ids"].numpy().astype(np.int64), 0)
        return {"t": np.where(hit, t, 0.0).astype(np.float32), "mesh": mesh, "triangle": triangle,
                "bary": hits["primitive_uvs"].numpy(), "face_normal": hits["primitive_normals"].numpy()}

    def occluded(self, origins: np.ndarray, targets: np.ndarray) -> np.ndarray:
        """Whether anything lies between origins [N, 3] and targets [N, 3] -> [N] bool."""
        rays = np.concatenate([origins, targets - origins], axis=1).astype(np.float32)
        return self.scene.test_occlusions(o3d.core.Tensor(rays), tnear=0.0, tfar=1.0,
                                            nthreads=RAY_THREADS["count"]).numpy().astype(bool)

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Unsigned distance [N] from points [N, 3] to the nearest surface."""
        return self.scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()


def camera_rays(K: np.ndarray, viewmat: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World rays through continuous pixel positions (u, v) [N]: origins [N, 3], directions [N, 3] with camera z = 1."""
    rotation, translation = viewmat[:3, :3], viewmat[:3, 3]
    centre = -rotation.T @ translation
    cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=1)
    directions = cam @ rotation  # rows of R^T @ d
    return np.broadcast_to(centre, directions.shape).astype(np.float32), directions.astype(np.float32)


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot products of [N, 3] arrays -> [N]."""
    return np.einsum("ij,ij->i", a, b)


def _normalised(a: np.ndarray) -> np.ndarray:
    """Rows of [N, 3] scaled to unit length."""
    return a / np.maximum(np.sqrt(_dot(a, a)), 1e-9)[:, None]


def _facing(face: np.ndarray, ray_dir: np.ndarray) -> np.ndarray:
    """Face normals [N, 3] flipped to point back along the rays [N, 3] (surfaces are two-sided)."""
    return face * np.where(_dot(face, ray_dir) > 0, -1.0, 1.0).astype(np.float32)[:, None]


def _sample_textures(scene: TracedScene, mesh: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear, wrapping texture lookup per hit: mesh [N], uv [N, 2] -> linear albedo [N, 3]."""
    tw, th, base = scene.tex_width[mesh], scene.tex_height[mesh], scene.tex_offset[mesh]
    x = (uv[:, 0] - np.floor(uv[:, 0])) * tw - 0.5  # in [-0.5, tw - 0.5)
    y = (uv[:, 1] - np.floor(uv[:, 1])) * th - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0).astype(np.float32)[:, None], (y - y0).astype(np.float32)[:, None]
    x0, y0 = x0.astype(np.int32), y0.astype(np.int32)
    x1 = np.where(x0 + 1 >= tw, 0, x0 + 1)
    y1 = np.where(y0 + 1 >= th, 0, y0 + 1)
    x0 = np.where(x0 < 0, tw - 1, x0)
    y0 = np.where(y0 < 0, th - 1, y0)
    row0, row1 = base + y0 * tw, base + y1 * tw
    t = scene.texels
    top = np.take(t, row0 + x0, axis=0) * (1 - fx) + np.take(t, row0 + x1, axis=0) * fx
    bottom = np.take(t, row1 + x0, axis=0) * (1 - fx) + np.take(t, row1 + x1, axis=0) * fx
    return top * (1 - fy) + bottom * fy


def shade(scene: TracedScene, lighting: Lighting, origins: np.ndarray, directions: np.ndarray) -> dict[str, np.ndarray]:
    """Trace and shade rays [N, 3]: radiance [N, 3] plus the hit record of `TracedScene.cast` and support [N]."""
    hits = scene.cast(origins, directions)
    radiance = np.zeros((len(origins), 3), np.float32)
    support = np.zeros(len(origins), bool)
    hit = np.nonzero(hits["mesh"] >= 0)[0]
    if len(hit) == 0:
        return {**hits, "radiance": radiance, "support": support}
    mesh = hits["mesh"][hit]
    tri = scene.offsets[mesh] + hits["triangle"][hit]
    b = hits["bary"][hit]
    weights = np.stack([1 - b[:, 0] - b[:, 1], b[:, 0], b[:, 1]], axis=1)  # [N, 3]
    uv = np.einsum("nk,nkc->nc", weights, scene.tri_uvs[tri])
    normal = _normalised(np.einsum("nk,nkc->nc", weights, scene.tri_normals[tri]))
    ray_dir = _normalised(directions[hit])
    face = _facing(hits["face_normal"][hit], ray_dir)
    normal *= np.where(_dot(normal, face) < 0, -1.0, 1.0).astype(np.float32)[:, None]
    support[hit] = scene.supports[mesh] & (face[:, 2] > SUPPORT_COS)
    points = origins[hit] + directions[hit] * hits["t"][hit, None]
    albedo = _sample_textures(scene, mesh, uv)
    diffuse = np.broadcast_to(lighting.ambient.astype(np.float32), albedo.shape).copy()
    specular = np.zeros_like(albedo)
    view = -ray_dir
    for light in lighting.lights:
        to_light = light.position[None].astype(np.float32) - points
        dist2 = _dot(to_light, to_light)
        l_dir = to_light / np.sqrt(dist2)[:, None]
        n_dot_l = _dot(normal, l_dir)
        lit = (n_dot_l > 0) & (_dot(face, l_dir) > 0)
        if light.casts_shadows:
            start = points + face * SHADOW_OFFSET_M
            lit[lit] &= ~scene.occluded(start[lit], np.broadcast_to(light.position, (int(lit.sum()), 3)).astype(np.float32))
        strength = np.where(lit, 1.0 / dist2, 0.0).astype(np.float32)
        n_dot_h = np.maximum(_dot(normal, _normalised(l_dir + view)), 0)
        glossy = scene.specular[mesh] * n_dot_h ** scene.shininess[mesh]
        colour = light.colour.astype(np.float32)[None]
        diffuse += (strength * np.maximum(n_dot_l, 0))[:, None] * colour
        specular += (strength * glossy)[:, None] * colour
    radiance[hit] = albedo * diffuse + specular
    return {**hits, "radiance": radiance, "support": support}


def _edge_pixels(mesh: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Pixels [H, W] bool whose 4-neighbourhood changes mesh or jumps in depth by more than 3 %."""
    edges = np.zeros(mesh.shape, bool)
    for axis in (0, 1):
        differs = np.diff(mesh, axis=axis) != 0
        a, b = np.take(depth, np.arange(depth.shape[axis] - 1), axis), np.take(depth, np.arange(1, depth.shape[axis]), axis)
        differs |= np.abs(a - b) > 0.03 * np.maximum(np.minimum(a, b), 1e-3)
        if axis == 0:
            edges[:-1] |= differs
            edges[1:] |= differs
        else:
            edges[:, :-1] |= differs
            edges[:, 1:] |= differs
    return edges


def render(scene: TracedScene, lighting: Lighting, K: np.ndarray, viewmat: np.ndarray, width: int, height: int,
           supersample: int = 2) -> Render:
    """Render a [height, width] view; pixels on geometry edges are re-shaded with supersample^2 sub-samples.

    Depth, labels, support and mesh ids are those of the pixel-centre ray (u + 0.5, v + 0.5).
    """
    K, viewmat = np.asarray(K, np.float64), np.asarray(viewmat, np.float64)
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    origins, directions = camera_rays(K, viewmat, u.ravel() + 0.5, v.ravel() + 0.5)
    centre = shade(scene, lighting, origins, directions)
    mesh = centre["mesh"].reshape(height, width).astype(np.int32)
    depth = centre["t"].reshape(height, width)
    radiance = centre["radiance"].reshape(height, width, 3)
    edge_v, edge_u = np.nonzero(_edge_pixels(mesh, depth))
    if supersample > 1 and len(edge_v):
        offsets = (np.arange(supersample) + 0.5) / supersample
        ou, ov = [g.ravel() for g in np.meshgrid(offsets, offsets)]
        su = (edge_u[:, None] + ou[None]).ravel()
        sv = (edge_v[:, None] + ov[None]).ravel()
        sub = shade(scene, lighting, *camera_rays(K, viewmat, su, sv))
        radiance[edge_v, edge_u] = sub["radiance"].reshape(len(edge_u), -1, 3).mean(1)
    label = np.where(mesh >= 0, scene.labels[np.maximum(mesh, 0)], 0).astype(np.int32)
    return Render(radiance=radiance, depth=depth, label=label,
                  support=centre["support"].reshape(height, width), mesh=mesh)


def probe(scene: TracedScene, K: np.ndarray, viewmat: np.ndarray, width: int, height: int, step: int = 1) -> Render:
    """Geometry only (no shading) at every `step`-th pixel centre: a [H/step, W/step] Render with zero radiance."""
    K, viewmat = np.asarray(K, np.float64), np.asarray(viewmat, np.float64)
    v, u = np.mgrid[0:height:step, 0:width:step].astype(np.float64)
    origins, directions = camera_rays(K, viewmat, u.ravel() + 0.5, v.ravel() + 0.5)
    hits = scene.cast(origins, directions)
    mesh = hits["mesh"].reshape(u.shape).astype(np.int32)
    face = _facing(hits["face_normal"], directions)
    support = (mesh.ravel() >= 0) & scene.supports[np.maximum(hits["mesh"], 0)] & (face[:, 2] > SUPPORT_COS)
    label = np.where(mesh >= 0, scene.labels[np.maximum(mesh, 0)], 0).astype(np.int32)
    return Render(radiance=np.zeros(u.shape + (3,), np.float32), depth=hits["t"].reshape(u.shape), label=label,
                  support=support.reshape(u.shape), mesh=mesh)
