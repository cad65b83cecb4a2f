"""Procedural, tileable textures (sRGB float32 [T, T, 3] in [0, 1]) for rooms and objects.

Every generator takes a numpy Generator so a texture is a pure function of its seed. Textures tile
(they wrap at the borders) because UVs on large surfaces repeat them.
"""
from __future__ import annotations

import numpy as np


def fractal_noise(rng: np.random.Generator, size: int, beta: float = 2.0, aspect: float = 1.0) -> np.ndarray:
    """Tileable 1/f^beta noise normalised to [0, 1] (2nd..98th percentile), shape [size, size].

    aspect > 1 stretches the features along the u axis (columns), e.g. for wood grain.
    """
    fy = np.fft.fftfreq(size)[:, None]
    fx = np.fft.fftfreq(size)[None, :] * aspect
    radius = np.sqrt(fx**2 + fy**2)
    radius[0, 0] = 1.0
    spectrum = np.fft.fft2(rng.standard_normal((size, size))) / radius**(beta / 2.0)
    spectrum[0, 0] = 0.0
    noise = np.real(np.fft.ifft2(spectrum))
    lo, hi = np.percentile(noise, [2, 98])
    return np.clip((noise - lo) / max(hi - lo, 1e-8), 0.0, 1.0).astype(np.float32)


def _lerp(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Blend colours a, b [3] by weights t [T, T] -> [T, T, 3]."""
    return (np.asarray(a, np.float32)[None, None] * (1 - t[..., None])
            + np.asarray(b, np.float32)[None, None] * t[..., None]).astype(np.float32)


def random_colour(rng: np.random.Generator, sat: tuple[float, float] = (0.3, 0.9),
                  val: tuple[float, float] = (0.3, 0.95)) -> np.ndarray:
    """A random sRGB colour [3] from hue/saturation/value ranges."""
    h, s, v = rng.uniform(0, 1), rng.uniform(*sat), rng.uniform(*val)
    k = (np.array([5.0, 3.0, 1.0]) + h * 6.0) % 6.0
    return (v - v * s * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)).astype(np.float32)


def plaster(rng: np.random.Generator, size: int = 256, colour=None) -> np.ndarray:
    """Painted wall: a pale colour with blotchy low-frequency and fine speckle variation."""
    base = random_colour(rng, (0.05, 0.35), (0.65, 0.92)) if colour is None else np.asarray(colour, np.float32)
    blotch = fractal_noise(rng, size, 2.6)
    speck = fractal_noise(rng, size, 0.8)
    shade = 0.82 + 0.22 * blotch + 0.10 * (speck - 0.5)
    return np.clip(base[None, None] * shade[..., None], 0, 1)


def wallpaper(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """Striped or dotted wallpaper with paper grain."""
    a, b = random_colour(rng, (0.1, 0.5), (0.6, 0.95)), random_colour(rng, (0.2, 0.7), (0.3, 0.8))
    u = np.arange(size, dtype=np.float32)[None, :] / size
    v = np.arange(size, dtype=np.float32)[:, None] / size
    periods = int(rng.integers(4, 12))
    if rng.uniform() < 0.5:
        pattern = (np.sin(2 * np.pi * periods * u) > rng.uniform(-0.3, 0.6)).astype(np.float32) * np.ones_like(v)
    else:
        cu, cv = (u * periods) % 1.0 - 0.5, (v * periods) % 1.0 - 0.5
        pattern = (cu**2 + cv**2 < rng.uniform(0.02, 0.09)).astype(np.float32)
    grain = fractal_noise(rng, size, 1.0)
    return np.clip(_lerp(a, b, pattern) * (0.9 + 0.2 * grain[..., None]), 0, 1)


def wood(rng: np.random.Generator, size: int = 256, planks: int = 0) -> np.ndarray:
    """Wood grain along u; with planks > 0, a plank floor of that many rows with staggered joints."""
    light = (np.array([0.78, 0.56, 0.34]) * rng.uniform(0.6, 1.15) * rng.uniform(0.9, 1.1, 3)).astype(np.float32)
    dark = light * rng.uniform(0.35, 0.6)
    warp = fractal_noise(rng, size, 2.5)
    v = np.arange(size, dtype=np.float32)[:, None] / size
    rings = 0.5 + 0.5 * np.sin(2 * np.pi * (rng.uniform(12, 30) * v + 3.0 * warp))
    streak = fractal_noise(rng, size, 1.5, aspect=6.0)
    t = np.clip(0.65 * rings + 0.45 * streak - 0.1, 0, 1)
    tex = _lerp(light, dark, t)
    if planks > 0:
        rows = (v[:, 0] * planks).astype(int)
        u = np.arange(size, dtype=np.float32)[None, :] / size
        offsets = rng.uniform(0, 1, planks).astype(np.float32)
        tint = rng.uniform(0.8, 1.15, planks).astype(np.float32)
        tex = tex * tint[rows][:, None, None]
        seam_v = np.abs((v * planks) % 1.0 - 0.5) > 0.47
        seam_u = np.abs(((u * 2 + offsets[rows][:, None]) % 1.0) - 0.5) > 0.49
        tex[np.broadcast_to(seam_v, (size, size)) | seam_u] *= 0.35
    return np.clip(tex, 0, 1)


def tiles(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """Square floor tiles with per-tile colour variation, marbling and dark grout lines."""
    count = int(rng.choice([2, 4, 8]))
    base = random_colour(rng, (0.05, 0.4), (0.45, 0.9))
    cells = (np.arange(size) * count // size)
    tile_id = cells[:, None] * count + cells[None, :]
    tint = rng.uniform(0.82, 1.12, count * count).astype(np.float32)[tile_id]
    marble = fractal_noise(rng, size, 1.8)
    tex = base[None, None] * (tint * (0.85 + 0.3 * marble))[..., None]
    phase = (np.arange(size) * count / size) % 1.0
    grout = (phase < 0.04)[:, None] | (phase < 0.04)[None, :]
    tex[grout] = base * 0.3
    return np.clip(tex, 0, 1)


def fabric(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """Carpet / upholstery: a colour with a woven micro pattern and mottling, sometimes a check."""
    a = random_colour(rng, (0.2, 0.8), (0.25, 0.8))
    weave = 0.5 + 0.25 * (np.sin(np.arange(size) * np.pi / 2)[:, None] * np.sin(np.arange(size) * np.pi / 2)[None, :])
    mottle = fractal_noise(rng, size, 1.2)
    tex = a[None, None] * (0.7 + 0.3 * weave + 0.35 * (mottle - 0.5))[..., None]
    if rng.uniform() < 0.4:
        n = int(rng.integers(2, 6))
        stripe = ((np.arange(size) * n // size) % 2).astype(np.float32)
        check = np.maximum(stripe[:, None], stripe[None, :])
        tex = tex * (1 - 0.35 * check[..., None]) + 0.35 * check[..., None] * random_colour(rng)[None, None]
    return np.clip(tex, 0, 1)


def painting(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """An abstract painting: smooth colour fields mapped through a random palette, with a frame."""
    palette = np.stack([random_colour(rng, (0.4, 1.0), (0.3, 1.0)) for _ in range(5)])
    field = fractal_noise(rng, size, 3.0) * 4.0
    low = np.floor(field).astype(int).clip(0, 3)
    tex = palette[low] * (1 - (field - low)[..., None]) + palette[low + 1] * (field - low)[..., None]
    tex *= (0.9 + 0.2 * fractal_noise(rng, size, 0.9))[..., None]
    border = max(2, size // 24)
    frame = random_colour(rng, (0.0, 0.4), (0.1, 0.5))
    tex[:border], tex[-border:], tex[:, :border], tex[:, -border:] = frame, frame, frame, frame
    return np.clip(tex, 0, 1).astype(np.float32)


def book_spines(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """Rows of coloured book spines with title bands (for shelves and book stacks)."""
    edges = np.sort(rng.uniform(0, 1, 14))
    idx = np.searchsorted(edges, np.arange(size) / size)
    colours = np.stack([random_colour(rng, (0.3, 0.9), (0.2, 0.8)) for _ in range(15)])
    tex = np.repeat(colours[idx][None], size, axis=0)
    v = np.arange(size) / size
    bands = (np.abs(v - 0.3) < 0.04) | (np.abs(v - 0.75) < 0.02)
    tex[bands] = tex[bands] * 0.4 + 0.55
    tex *= (0.85 + 0.3 * fractal_noise(rng, size, 1.0))[..., None]
    return np.clip(tex, 0, 1).astype(np.float32)


def product_label(rng: np.random.Generator, width: int = 512, height: int = 256) -> np.ndarray:
    """A busy product label [height, width, 3]: colour bands, a logo disc, text-like glyph rows, noise."""
    tex = np.empty((height, width, 3), np.float32)
    tex[:] = random_colour(rng, (0.5, 1.0), (0.5, 1.0))
    v = np.arange(height)[:, None] / height
    u = np.arange(width)[None, :] / width
    for _ in range(int(rng.integers(2, 5))):
        c, w = rng.uniform(0, 1), rng.uniform(0.03, 0.15)
        band = np.broadcast_to(np.abs(v - c) < w, (height, width))
        tex[band] = random_colour(rng)
    for _ in range(int(rng.integers(2, 4))):
        cu, cv, r = rng.uniform(0.1, 0.9), rng.uniform(0.25, 0.75), rng.uniform(0.05, 0.12)
        disc = ((u - cu) * width / height)**2 + (v - cv)**2 < r**2
        tex[disc] = random_colour(rng, (0.6, 1.0), (0.2, 1.0))
        ring = np.abs(np.sqrt(((u - cu) * width / height)**2 + (v - cv)**2) - r * 0.7) < 0.01
        tex[ring] = 1.0 - tex[ring]
    glyph_rows = rng.uniform(0.1, 0.9, int(rng.integers(3, 7)))
    glyphs = rng.uniform(size=(height // 8 + 1, width // 6 + 1)) < 0.55
    glyph_mask = np.repeat(np.repeat(glyphs, 8, 0), 6, 1)[:height, :width]
    for row in glyph_rows:
        line = np.broadcast_to(np.abs(v - row) < 0.025, (height, width)) & glyph_mask
        line &= np.broadcast_to((u * 7.3 + row * 3) % 1.0 < 0.8, (height, width))
        tex[line] = tex[line] * 0.15 + (0.85 if rng.uniform() < 0.3 else 0.0)
    tex *= (0.92 + 0.16 * fractal_noise(rng, max(width, height), 0.8)[:height, :width])[..., None]
    return np.clip(tex, 0, 1)


def leaf(rng: np.random.Generator, size: int = 128) -> np.ndarray:
    """A leaf: green blade with a light midrib along v, side veins and mottling."""
    green = np.array([0.18, 0.45, 0.12], np.float32) * rng.uniform(0.7, 1.3, 3).astype(np.float32)
    u = np.arange(size)[None, :] / size
    v = np.arange(size)[:, None] / size
    midrib = np.abs(u - 0.5) < 0.025
    veins = np.abs(((v - np.abs(u - 0.5) * 0.8) * 9) % 1.0 - 0.5) < 0.06
    mottle = fractal_noise(rng, size, 1.5)
    tex = green[None, None] * (0.75 + 0.5 * mottle[..., None])
    tex[np.broadcast_to(veins, (size, size))] *= 1.35
    tex[np.broadcast_to(midrib, (size, size))] = np.array([0.55, 0.75, 0.35])
    return np.clip(tex, 0, 1).astype(np.float32)


def ceramic_pattern(rng: np.random.Generator, width: int = 512, height: int = 256) -> np.ndarray:
    """A colourful painted vase glaze: bands, zig-zags and flowers on a glossy base colour."""
    tex = np.empty((height, width, 3), np.float32)
    tex[:] = random_colour(rng, (0.3, 0.9), (0.5, 0.95))
    v = np.arange(height)[:, None] / height
    u = np.arange(width)[None, :] / width
    for k in range(int(rng.integers(3, 6))):
        c = rng.uniform(0.1, 0.9)
        if k % 2 == 0:
            zig = np.abs(v - c - 0.04 * np.abs(((u * rng.integers(8, 20)) % 1.0) - 0.5)) < 0.02
        else:
            zig = np.broadcast_to(np.abs(v - c) < rng.uniform(0.01, 0.04), (height, width))
        tex[zig] = random_colour(rng, (0.6, 1.0), (0.2, 0.9))
    for _ in range(int(rng.integers(25, 40))):
        cu, cv, r = rng.uniform(0, 1), rng.uniform(0.05, 0.95), rng.uniform(0.04, 0.09)
        angle = np.arctan2(v - cv, (u - cu) * width / height)
        dist = np.sqrt(((u - cu) * width / height)**2 + (v - cv)**2)
        petals = dist < r * (0.6 + 0.4 * np.cos(5 * angle))
        tex[petals] = random_colour(rng, (0.6, 1.0), (0.5, 1.0))
        tex[dist < r * 0.25] = random_colour(rng, (0.6, 1.0), (0.6, 1.0))
    speckle = rng.uniform(size=(height, width)) < 0.02
    tex[speckle] *= 0.4
    tex *= (0.85 + 0.3 * fractal_noise(rng, width, 1.0)[:height, :width])[..., None]
    return np.clip(tex, 0, 1)


def terracotta(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """Clay pot surface: orange-brown with mottling and a few horizontal rings."""
    base = np.array([0.72, 0.38, 0.22], np.float32) * rng.uniform(0.85, 1.1)
    mottle = fractal_noise(rng, size, 1.4)
    tex = base[None, None] * (0.75 + 0.45 * mottle[..., None])
    v = np.arange(size) / size
    for c in rng.uniform(0.1, 0.9, 3):
        tex[np.abs(v - c) < 0.015] *= 0.6
    return np.clip(tex, 0, 1).astype(np.float32)


def soil(rng: np.random.Generator, size: int = 128) -> np.ndarray:
    """Dark soil with pebbles."""
    tex = np.array([0.22, 0.15, 0.1], np.float32)[None, None] * (0.5 + fractal_noise(rng, size, 0.7)[..., None])
    return np.clip(tex, 0, 1).astype(np.float32)


def solid(colour, size: int = 8) -> np.ndarray:
    """A flat colour texture."""
    return np.broadcast_to(np.asarray(colour, np.float32), (size, size, 3)).copy()


def srgb_to_linear(tex: np.ndarray) -> np.ndarray:
    """sRGB [..., 3] in [0, 1] -> linear (gamma 2.2 approximation)."""
    return np.power(np.clip(tex, 0, 1), 2.2).astype(np.float32)


def linear_to_srgb(img: np.ndarray) -> np.ndarray:
    """Linear [..., 3] -> sRGB in [0, 1] (gamma 2.2 approximation, clipped)."""
    return np.power(np.clip(img, 0, 1), 1 / 2.2).astype(np.float32)
