"""The sample's object classes: procedural, textured meshes scaled to a real height in metres.

Each object stands on z = 0 with its base centred on the origin and +z up. Its look (textures, small
shape variations) is a pure function of (seed, name), so the captured object and the one in the test
photos are the same physical object.
"""
from __future__ import annotations

import zlib

import numpy as np

from . import textures as tx
from .meshes import Mesh, bounds, revolve, ribbon, tube

OBJECT_CLASSES = ("bottle", "eyedrops", "plant", "soda_can", "vase")


def _bottle(rng: np.random.Generator) -> list[Mesh]:
    """A plastic water bottle with a wrap-around label and a screw cap (unit height)."""
    r = 0.14 * rng.uniform(0.9, 1.1)
    body = revolve([0, r * 0.9, r, r, r * 0.97, r, r, 0.45 * r, 0.42 * r],
                   [0, 0, 0.02, 0.3, 0.33, 0.62, 0.66, 0.8, 0.88], tx.product_label(rng), specular=0.35, shininess=40)
    cap_r = 0.46 * r
    cap = revolve([0.42 * r, cap_r, cap_r, cap_r * 0.95, 0], [0.87, 0.87, 0.985, 1.0, 1.0],
                  tx.solid(tx.random_colour(rng, (0.6, 1.0), (0.4, 0.9))), specular=0.3, shininess=30)
    return [body, cap]


def _eyedrops(rng: np.random.Generator) -> list[Mesh]:
    """A small dropper bottle: white body with a bold label, tapered nozzle cap (unit height)."""
    r = 0.2
    body = revolve([0, r * 0.95, r, r, r * 0.9, 0.55 * r], [0, 0, 0.02, 0.55, 0.6, 0.63],
                   tx.product_label(rng, 256, 128), specular=0.3, shininess=30)
    cap = revolve([0.5 * r, 0.62 * r, 0.62 * r, 0.45 * r, 0.15 * r, 0.1 * r, 0],
                  [0.62, 0.62, 0.78, 0.85, 0.97, 1.0, 1.0],
                  tx.solid(tx.random_colour(rng, (0.5, 1.0), (0.3, 0.8))), specular=0.4, shininess=40)
    return [body, cap]


def _soda_can(rng: np.random.Generator) -> list[Mesh]:
    """An aluminium drinks can: shiny printed wall, tapered neck, metal lid (unit height)."""
    r = 0.27
    wall = revolve([0.2, 0.22, r, r, 0.23, 0.22], [0.0, 0.0, 0.05, 0.9, 0.97, 1.0],
                   tx.product_label(rng), specular=0.6, shininess=60)
    metal = tx.solid([0.75, 0.76, 0.78])
    lid = revolve([0.22, 0.21, 0.21, 0.0], [1.0, 0.985, 0.985, 0.985], metal, specular=0.8, shininess=80)
    bottom = revolve([0.0, 0.2], [0.02, 0.0], metal, specular=0.5, shininess=40)
    return [wall, lid, bottom]


def _vase(rng: np.random.Generator) -> list[Mesh]:
    """A glazed, painted vase with an open mouth and a loop handle (unit height)."""
    bulge = rng.uniform(0.34, 0.4)
    glaze = tx.ceramic_pattern(rng)
    body = revolve([0, 0.2, 0.22, bulge, 0.3, 0.18, 0.2, 0.25, 0.22, 0.15, 0],
                   [0, 0, 0.02, 0.35, 0.58, 0.78, 0.9, 1.0, 0.98, 0.7, 0.7], glaze, specular=0.45, shininess=50)
    t = np.linspace(0, 1, 24)[:, None]
    ctrl = np.array([[0.17, 0, 0.8], [0.5, 0, 0.88], [0.62, 0, 0.45], [bulge - 0.02, 0, 0.36]])
    path = ((1 - t)**3 * ctrl[0] + 3 * (1 - t)**2 * t * ctrl[1] + 3 * (1 - t) * t**2 * ctrl[2] + t**3 * ctrl[3])
    handle = tube(path, 0.035, glaze, specular=0.45, shininess=50)
    return [body, handle]


def _plant(rng: np.random.Generator) -> list[Mesh]:
    """A potted plant: terracotta pot, soil, stems and a crown of broad leaves (unit height)."""
    pot = revolve([0, 0.2, 0.2, 0.27, 0.29, 0.29, 0.26, 0.25], [0, 0, 0.01, 0.31, 0.31, 0.36, 0.36, 0.31],
                  tx.terracotta(rng), specular=0.05, shininess=8)
    earth = revolve([0.255, 0], [0.31, 0.315], tx.soil(rng), specular=0.0, shininess=4)
    leaf_tex = tx.leaf(rng)
    stem_tex = tx.solid([0.25, 0.4, 0.15])
    parts = [pot, earth]
    count = int(rng.integers(7, 11))
    for k in range(count):
        azimuth = 2 * np.pi * (k + rng.uniform(-0.3, 0.3)) / count
        out = np.array([np.cos(azimuth), np.sin(azimuth), 0.0])
        side = np.array([-np.sin(azimuth), np.cos(azimuth), 0.0])
        reach, rise = rng.uniform(0.12, 0.3), rng.uniform(0.25, 0.55)
        base = np.array([0, 0, 0.31]) + 0.05 * out
        s = np.linspace(0, 1, 8)[:, None]
        stem = base + s * reach * 0.6 * out + (s * rise - 0.1 * s**2) * np.array([0, 0, 1.0])
        parts.append(tube(stem, 0.012, stem_tex, segments=6, specular=0.02))
        length = rng.uniform(0.3, 0.45)
        droop = rng.uniform(0.15, 0.35)
        s = np.linspace(0, 1, 12)[:, None]
        spine = stem[-1] + s * length * out + (0.35 * s - droop * s**2) * length * np.array([0, 0, 1.0])
        widths = 0.11 * np.sin(np.pi * np.clip(s[:, 0], 0.02, 1.0)) ** 0.8
        tilt = side * np.cos(0.3) + np.array([0, 0, np.sin(0.3)])
        parts.append(ribbon(spine, widths, np.repeat(tilt[None], len(s), 0), leaf_tex, specular=0.15, shininess=20))
    return parts


_BUILDERS = {"bottle": _bottle, "eyedrops": _eyedrops, "plant": _plant, "soda_can": _soda_can, "vase": _vase}


def object_seed(seed: int, name: str) -> np.random.Generator:
    """The Generator that fixes an object's look, from the sample seed and the class name."""
    return np.random.default_rng([seed, 7, zlib.crc32(name.encode())])


def build_object(name: str, height_m: float, seed: int, label: int = 1) -> list[Mesh]:
    """Meshes of object `name` standing on z = 0, base centred at the origin, exactly `height_m` tall."""
    if name not in _BUILDERS:
        raise ValueError(f"unknown sample object {name!r}; known: {sorted(_BUILDERS)}")
    if not height_m > 0:
        raise ValueError(f"object {name!r}: height_m must be positive, got {height_m}")
    parts = _BUILDERS[name](object_seed(seed, name))
    top = bounds(parts)[1][2]
    return [p.transformed(np.eye(3), [0, 0, 0], scale=height_m / top).with_material(label=label) for p in parts]


def footprint_radius(meshes: list[Mesh]) -> float:
    """Largest horizontal distance of the object's vertices from its vertical axis (metres)."""
    vertices = np.concatenate([m.vertices for m in meshes])
    return float(np.sqrt((vertices[:, :2]**2).sum(1)).max())
