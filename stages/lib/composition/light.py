"""The light of a background photo, and an object that takes it (issue 32; the paper keeps the capture's light).

`PhotoLight`, once per photo: its up axis (the placement planes' area-weighted normal), the horizontal direction
towards the brighter side of its planes (the least-squares gradient of log luminance over each plane's placement
points, which falls away from a lamp; kept where brightness changes by at least MIN_LOG_CHANGE across the plane),
its mean linear colour and a small linear copy for local means.
`SceneLight`, once per image: the direction towards the light (the photo's azimuth, jittered, or a random one;
an elevation drawn from a range) and the directional share of the light, which is how dark a shadow is.
An object takes the light in two ways: a per-channel gain from the background around it (`exposure_gain`:
exposure from its luminance against the photo's, white balance from grey world over it and over the photo),
and Lambert shading of each Gaussian by its normal (`shading_factors`), folded into its SH colour
(`relit`). Gains and shading are computed in linear light and returned as factors on the sRGB colours.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from stages.lib.gaussians.model import SH_C0, Gaussians
from stages.lib.planes.search import CAMERA_UP, project
from stages.records.planes import PlacementPlane

GAMMA = 2.2  # sRGB <-> linear light, as a power law
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709 weights of linear RGB
SMALL_SIDE = 64  # the small linear copy's longest side (local means)
MIN_LOG_CHANGE = 0.15  # a plane votes for a light azimuth when its log luminance changes this much across it
AZIMUTH_JITTER_DEG = 20.0  # std of the jitter around the photo's light azimuth
TRIM_SHARE = 0.2  # the brightness fit is redone without this share of its largest residuals (texture)
FLAT_RATIO = 0.5  # a Gaussian whose shortest axis is below this times its middle one is a surface patch
EPS = 1e-6


@dataclass
class PhotoLight:
    """What a photo says about its light (once per photo)."""

    up: np.ndarray  # [3] camera frame, unit
    towards_light: np.ndarray | None  # [3] unit, horizontal: towards the brighter side of its planes; None: unknown
    mean: np.ndarray  # [3] mean linear RGB of the photo
    small: np.ndarray  # [h, w, 3] float32 linear RGB, the photo at most SMALL_SIDE pixels on a side
    scale: float  # small pixels per photo pixel


@dataclass
class SceneLight:
    """The light of one composed image."""

    direction: np.ndarray  # [3] camera frame, unit, towards the light
    elevation: float  # radians above the horizontal
    strength: float  # the directional share: a lit plane's darkening in the shadow, in [0, 1)


def linear(srgb: np.ndarray) -> np.ndarray:
    """Linear light of sRGB values in [0, 1] (any shape)."""
    return np.power(np.clip(srgb, 0.0, 1.0), GAMMA)


def horizontal(vector: np.ndarray, up: np.ndarray) -> np.ndarray | None:
    """The unit component of `vector` [3] perpendicular to unit `up` [3]; None when there is none."""
    flat = vector - (vector @ up) * up
    norm = float(np.linalg.norm(flat))
    return flat / norm if norm > EPS else None


def plane_brightness_gradient(plane: PlacementPlane, log_luminance: np.ndarray, K: np.ndarray, scale: float,
                              up: np.ndarray) -> np.ndarray | None:
    """The horizontal vector [3] towards the brighter side of a plane, as long as the change of log luminance
    across it (twice the std of its placement points along the gradient); None when it is under MIN_LOG_CHANGE
    or there are too few points. log_luminance: [h, w] of the small copy (`scale` small pixels per pixel)."""
    points = np.asarray(plane.points, dtype=np.float64)
    if len(points) < 10:
        return None
    pixels = project(points, K) * scale
    h, w = log_luminance.shape
    rows, cols = np.clip(pixels[:, 1].astype(int), 0, h - 1), np.clip(pixels[:, 0].astype(int), 0, w - 1)
    values = log_luminance[rows, cols]
    axis_a = horizontal(np.eye(3)[int(np.argmin(np.abs(up)))], up)
    axis_b = np.cross(up, axis_a)
    centred = points - points.mean(0)
    design = np.stack([centred @ axis_a, centred @ axis_b, np.ones(len(points))], axis=1)
    keep = np.ones(len(points), bool)
    for _ in range(2):
        solution = np.linalg.lstsq(design[keep], values[keep], rcond=None)[0]
        residuals = np.abs(design @ solution - values)
        keep = residuals <= np.quantile(residuals, 1.0 - TRIM_SHARE)
    gradient = solution[0] * axis_a + solution[1] * axis_b
    norm = float(np.linalg.norm(gradient))
    if norm < EPS:
        return None
    change = 2.0 * float(np.std(centred @ (gradient / norm))) * norm
    return gradient / norm * change if change >= MIN_LOG_CHANGE else None


def photo_light(image: np.ndarray, K: np.ndarray, planes: list[PlacementPlane]) -> PhotoLight:
    """The light of a photo (image [H, W, 3] float32 sRGB in [0, 1], camera K [3, 3], its placement planes)."""
    height, width = image.shape[:2]
    scale = min(1.0, SMALL_SIDE / max(height, width))
    small = linear(cv2.resize(image, (max(1, round(width * scale)), max(1, round(height * scale))),
                              interpolation=cv2.INTER_AREA)).astype(np.float32)
    areas = np.array([max(plane.area, 0.0) for plane in planes])
    up = CAMERA_UP
    if planes and areas.sum() > 0:
        up = (areas[:, None] * np.stack([plane.normal for plane in planes])).sum(0)
        up /= np.linalg.norm(up)
    log_luminance = np.log(small @ LUMINANCE.astype(np.float32) + 1e-3)
    votes = [(area, vote) for plane, area in zip(planes, areas)
             if (vote := plane_brightness_gradient(plane, log_luminance, K, scale, up)) is not None]
    towards = None
    if votes:
        total = sum(area * vote for area, vote in votes)
        towards = horizontal(total, up)
    return PhotoLight(up, towards, small.reshape(-1, 3).mean(0).astype(np.float64), small, scale)


def sample_scene_light(photo: PhotoLight, from_photo: bool, elevation_deg: tuple[float, float],
                       strength: tuple[float, float], rng: np.random.Generator) -> SceneLight:
    """The light of one image: azimuth from the photo (`from_photo` and the photo has one; jittered by
    AZIMUTH_JITTER_DEG) or uniform, elevation and strength uniform in their ranges. Draws the same four numbers
    from `rng` whatever the choice, so the other draws of an image do not depend on it."""
    random_azimuth = rng.uniform(0.0, 2.0 * math.pi)
    jitter = math.radians(rng.normal(0.0, AZIMUTH_JITTER_DEG))
    elevation = math.radians(rng.uniform(*elevation_deg))
    share = float(rng.uniform(*strength))
    base = horizontal(np.eye(3)[int(np.argmin(np.abs(photo.up)))], photo.up)
    azimuth = random_azimuth
    if from_photo and photo.towards_light is not None:
        azimuth = math.atan2(float(np.cross(base, photo.towards_light) @ photo.up),
                             float(base @ photo.towards_light)) + jitter
    side = np.cross(photo.up, base)
    flat = math.cos(azimuth) * base + math.sin(azimuth) * side
    direction = math.cos(elevation) * flat + math.sin(elevation) * photo.up
    return SceneLight(direction / np.linalg.norm(direction), elevation, min(share, 0.99))


def exposure_gain(photo: PhotoLight, box: tuple[int, int, int, int], strength: float, max_gain: float) -> np.ndarray:
    """Per-channel factor [3] on an object's sRGB colour from the background in `box` (x0, y0, x1, y1, photo
    pixels): exposure (the box's luminance against the photo's) times white balance (the light colour by grey
    world, half over the box and half over the photo), in linear light, to the power `strength`, each channel
    clamped to [1 / max_gain, max_gain]."""
    s = photo.scale
    h, w = photo.small.shape[:2]
    x0, y0 = min(max(int(box[0] * s), 0), w - 1), min(max(int(box[1] * s), 0), h - 1)
    x1, y1 = max(x0 + 1, min(math.ceil(box[2] * s), w)), max(y0 + 1, min(math.ceil(box[3] * s), h))
    local = photo.small[y0:y1, x0:x1].reshape(-1, 3).mean(0).astype(np.float64) + EPS
    overall = photo.mean + EPS
    local_luminance, overall_luminance = float(local @ LUMINANCE), float(overall @ LUMINANCE)
    white_balance = np.sqrt(local / local_luminance * overall / overall_luminance)
    gain = np.clip((local_luminance / overall_luminance * white_balance) ** strength, 1.0 / max_gain, max_gain)
    return gain ** (1.0 / GAMMA)


def gaussian_normals(g: Gaussians, centre: np.ndarray) -> np.ndarray:
    """Outward unit normals [N, 3] of an object's Gaussians (model frame): the shortest axis of a flat one (a
    surface patch), turned away from `centre` [3], else the direction from `centre` to its mean."""
    with torch.no_grad():
        scales = g.scales.double().numpy()
        axes = g.rotation_matrices().double().numpy()  # [N, 3, 3] columns: local axes
    outward = g.means.double().numpy() - np.asarray(centre, dtype=np.float64)
    outward /= np.maximum(np.linalg.norm(outward, axis=1, keepdims=True), EPS)
    order = np.sort(scales, axis=1)
    shortest = axes[np.arange(len(scales)), :, np.argmin(scales, axis=1)]  # [N, 3]
    shortest *= np.where((shortest * outward).sum(1) < 0, -1.0, 1.0)[:, None]
    flat = order[:, 0] < FLAT_RATIO * order[:, 1]
    return np.where(flat[:, None], shortest, outward)


def shading_factors(normals: np.ndarray, opacities: np.ndarray, towards_light: np.ndarray, light: SceneLight,
                    amount: float) -> np.ndarray:
    """Factor [N] on each Gaussian's sRGB colour: its Lambert irradiance ambient + directional * max(0, n . l)
    (the directional part relative to the ambient from the light's strength, so that a lit plane is as much
    brighter than its shadow), over its opacity-weighted mean (the object's overall brightness stays), moved
    `amount` of the way from 1. normals [N, 3] and towards_light [3] in one frame; opacities [N]."""
    directional = light.strength / ((1.0 - light.strength) * max(math.sin(light.elevation), 0.1))
    irradiance = 1.0 + directional * np.clip(normals @ towards_light, 0.0, None)
    weights = np.asarray(opacities, dtype=np.float64)
    relative = irradiance / (float((weights * irradiance).sum()) / max(float(weights.sum()), EPS))
    return np.maximum(1.0 + amount * (relative - 1.0), 0.0) ** (1.0 / GAMMA)


def relit(g: Gaussians, factors: np.ndarray) -> Gaussians:
    """The Gaussians with every colour, clamp_min(0.5 + SH(d), 0), multiplied by its factor [N] (>= 0) for
    every view direction d: all SH bands scaled, and the DC term shifted by the scaled 0.5 offset."""
    factor = torch.as_tensor(factors, dtype=g.sh.dtype)[:, None, None]  # [N, 1, 1]
    sh = g.sh * factor
    sh[:, 0] += (factor[:, 0] - 1.0) * (0.5 / SH_C0)
    return Gaussians(g.means, g.log_scales, g.quats, g.opacity_logits, sh)
