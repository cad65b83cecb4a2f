"""Cast shadows: a placed object darkens the plane it stands on (issue 32; the paper has none).

The object's opaque Gaussians, as points drawn inside each (`ShadowCaster`), are projected onto its support
plane twice: along the light direction (the directional shadow) and straight down, weighted towards the base
(the contact shadow, an ambient occlusion under it). Each projection is splatted into a small grid in the plane's own
coordinates, as opacity (1 - exp(-sum of -log(1 - opacity)) per cell), and blurred: the directional shadow in
height bands, each with the penumbra of a light of angular radius `softness` at that height (sharp at the
contact, soft at the tip). The grid goes into the image through the plane's homography. A background pixel
takes the shadow only where its depth lies on the plane (`on_plane`): a surface in front of the plane (an
occluder, a wall nearer than the shadow) or behind it (past the plane's edge) stays lit. Shadows darken the
background before the objects are composited over it, so they never enter an object's mask or box.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from stages.lib.composition.placement import MODEL_OPACITY, NEAR_DEPTH, ObjectFrame, Pose
from stages.lib.gaussians.model import Gaussians

CASTER_POINTS = 4000  # points a shadow is made of, drawn inside the object's opaque Gaussians
CASTER_SPREAD = 0.8  # ... at this many standard deviations of each Gaussian's own shape (where it is opaque)
CELLS_PER_HEIGHT = 32  # grid cells per object height, at most ...
MIN_CELL_PIXELS = 0.7  # ... and at least this many image pixels where the plane is seen most obliquely (aliasing)
MAX_GRID_CELLS = 160  # the grid's longest side; longer shadows get coarser cells
HEIGHT_BANDS = 3  # directional shadow: height bands blurred separately
CONTACT_HEIGHT = 0.1  # contact shadow: a Gaussian's weight falls by e every this fraction of the object height
CONTACT_BLUR = 0.12  # contact shadow: blur sigma, fraction of the object height
MIN_BLUR_CELLS = 0.8  # every blur is at least this (fills the gaps between the splatted points)
MIN_DARKNESS = 1e-3  # a shadow darker than this nowhere is dropped
MAX_OPTICAL_DEPTH = 5.0  # one Gaussian's -log(1 - opacity) is capped here (opacity 0.993)


@dataclass
class ShadowCaster:
    """What an object's shadow is made of (model frame, computed once per object)."""

    points: np.ndarray  # [M, 3] points inside its opaque Gaussians
    optical_depth: np.ndarray  # [M] -log(1 - opacity) of the Gaussian of each


@dataclass
class Shadow:
    """A shadow in its window of the image (window pixel (r, c) = image (y0 + r, x0 + c))."""

    x0: int
    y0: int
    darkness: np.ndarray  # [h, w] float32 in [0, 1]: the background there is multiplied by 1 - darkness


@dataclass
class ShadowLook:
    """How dark and soft a shadow is (the image's light and the settings)."""

    light: np.ndarray  # [3] unit, camera frame, towards the light (above the support plane)
    strength: float  # darkness of the directional shadow's core, in [0, 1]
    contact: float  # darkness of the contact shadow's core, in [0, 1]
    softness: float  # penumbra width per unit of distance from the contact (the light's angular radius, rad)


def shadow_caster(g: Gaussians, max_points: int = CASTER_POINTS) -> ShadowCaster:
    """The caster of an object (model frame): its Gaussians at least MODEL_OPACITY opaque (all when none is),
    evenly subsampled to `max_points` in their stored order, each giving max_points // their count points drawn
    from its own shape shrunk to CASTER_SPREAD (a few large Gaussians cover their whole extent, not a point),
    with its optical depth. Deterministic (a fixed seed)."""
    with torch.no_grad():
        means, opacities = g.means.double().numpy(), g.opacities.double().numpy()
        chosen = np.flatnonzero(opacities >= MODEL_OPACITY)
        chosen = chosen if len(chosen) else np.arange(len(opacities))
        if len(chosen) > max_points:
            chosen = chosen[np.linspace(0, len(chosen) - 1, max_points).round().astype(int)]
        shapes = (g.rotation_matrices()[chosen] * g.scales[chosen][:, None, :]).double().numpy()  # [K, 3, 3] R S
    each = max(1, max_points // len(chosen))
    offsets = np.random.default_rng(0).normal(size=(len(chosen), each, 3)) * CASTER_SPREAD  # [K, each, 3]
    points = means[chosen][:, None, :] + np.einsum("kij,kej->kei", shapes, offsets)
    depth = -np.log(np.clip(1.0 - opacities[chosen], math.exp(-MAX_OPTICAL_DEPTH), 1.0))
    return ShadowCaster(points.reshape(-1, 3), np.repeat(depth, each))


def plane_axes(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors [3] spanning the plane of unit `normal` [3] (with the normal, a right-handed frame)."""
    helper = np.eye(3)[int(np.argmin(np.abs(normal)))]
    first = np.cross(normal, helper)
    first /= np.linalg.norm(first)
    return first, np.cross(normal, first)


def splat(coords: np.ndarray, depth: np.ndarray, origin: np.ndarray, cell: float, shape: tuple[int, int]) -> np.ndarray:
    """Opacity [rows, cols] float32 of points at plane coordinates coords [M, 2] with optical depths [M]: cell
    (i, j) is centred at origin + cell * (j, i) and holds 1 - exp(-sum of the depths of its points)."""
    rows, cols = shape
    index = np.rint((coords - origin) / cell).astype(np.int64)  # [M, 2] (col, row)
    inside = (index[:, 0] >= 0) & (index[:, 0] < cols) & (index[:, 1] >= 0) & (index[:, 1] < rows)
    flat = index[inside, 1] * cols + index[inside, 0]
    total = np.bincount(flat, weights=depth[inside], minlength=rows * cols)
    return (1.0 - np.exp(-total)).reshape(rows, cols).astype(np.float32)


def blurred(opacity: np.ndarray, sigma: float) -> np.ndarray:
    """opacity [rows, cols] blurred with a Gaussian of `sigma` cells (at least MIN_BLUR_CELLS)."""
    return cv2.GaussianBlur(opacity, (0, 0), max(float(sigma), MIN_BLUR_CELLS), borderType=cv2.BORDER_CONSTANT)


def pixel_footprint(point: np.ndarray, normal: np.ndarray, K: np.ndarray) -> float:
    """The length on a plane (unit `normal` [3]) at camera-frame `point` [3] that one image pixel covers along
    the direction in which the plane is seen most obliquely (camera K [3, 3])."""
    distance = float(np.linalg.norm(point))
    facing = abs(float(normal @ point)) / max(distance, 1e-12)  # cosine between the view ray and the normal
    return distance / (0.5 * float(K[0, 0] + K[1, 1]) * max(facing, 0.05))


def plane_shadow(caster: ShadowCaster, pose: Pose, frame: ObjectFrame, look: ShadowLook,
                 K: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float] | None:
    """The shadow of a posed object on its support plane, in plane coordinates (cells no smaller than
    MIN_CELL_PIXELS image pixels of camera K [3, 3]).

    Returns (darkness [rows, cols] float32, origin [3], plane axes e1 [3] and e2 [3], cell size): cell (i, j)
    is centred at the plane point origin + cell * (j e1 + i e2). None when the light is not above the plane.
    """
    normal = pose.rotation @ frame.normal
    contact = pose.apply(frame.base_point[None])[0]
    light = np.asarray(look.light, dtype=np.float64)
    rise = float(light @ normal)  # sine of the light's elevation above the plane
    if rise <= 1e-3:
        return None
    height = pose.scale * frame.height
    e1, e2 = plane_axes(normal)
    points = pose.apply(caster.points) - contact  # [M, 3]
    heights = np.clip(points @ normal, 0.0, None)  # [M]
    cast = points - (heights / rise)[:, None] * light  # [M, 3] on the plane, along the light
    along_light = np.stack([cast @ e1, cast @ e2], axis=1)  # [M, 2]
    straight_down = np.stack([points @ e1, points @ e2], axis=1)  # [M, 2]
    band_sigma = [look.softness * (band + 0.5) / HEIGHT_BANDS * height / rise for band in range(HEIGHT_BANDS)]
    margin = 3.0 * max(band_sigma + [CONTACT_BLUR * height])
    low = np.minimum(along_light.min(0), straight_down.min(0)) - margin
    high = np.maximum(along_light.max(0), straight_down.max(0)) + margin
    cell = max(height / CELLS_PER_HEIGHT, float((high - low).max()) / MAX_GRID_CELLS,
               MIN_CELL_PIXELS * pixel_footprint(contact, normal, K))
    cols, rows = (np.ceil((high - low) / cell).astype(int) + 1).tolist()
    shape = (rows, cols)
    light_lit = np.ones(shape, np.float32)  # the share of the directional light that reaches each cell
    bands = np.minimum((heights / max(height, 1e-12) * HEIGHT_BANDS).astype(int), HEIGHT_BANDS - 1)
    for band in range(HEIGHT_BANDS):
        members = bands == band
        if members.any():
            light_lit *= 1.0 - blurred(splat(along_light[members], caster.optical_depth[members], low, cell, shape),
                                       band_sigma[band] / cell)
    contact_weight = np.exp(-heights / (CONTACT_HEIGHT * max(height, 1e-12)))
    contact_opacity = blurred(splat(straight_down, caster.optical_depth * contact_weight, low, cell, shape),
                              CONTACT_BLUR * height / cell)
    darkness = 1.0 - (1.0 - look.strength * (1.0 - light_lit)) * (1.0 - look.contact * contact_opacity)
    origin = contact + low[0] * e1 + low[1] * e2
    return darkness.astype(np.float32), origin, e1, e2, cell


def plane_depth(normal: np.ndarray, point: np.ndarray, K: np.ndarray, x0: int, y0: int, width: int,
                height: int) -> np.ndarray:
    """Camera z [height, width] where the rays of the window's pixels (centres at +0.5 in K's frame, window
    origin (x0, y0)) meet the plane through `point` [3] with `normal` [3]; +inf where they do not (in front)."""
    u = np.arange(x0, x0 + width, dtype=np.float64)[None, :] + 0.5
    v = np.arange(y0, y0 + height, dtype=np.float64)[:, None] + 0.5
    inverse = np.linalg.inv(K)  # ray of pixel (u, v): K^-1 (u, v, 1)
    facing = (normal @ inverse[:, 0]) * u + (normal @ inverse[:, 1]) * v + normal @ inverse[:, 2]  # normal . ray
    ray_z = inverse[2, 0] * u + inverse[2, 1] * v + inverse[2, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = float(normal @ point) / facing * ray_z
    return np.where(np.isfinite(depth) & (depth > NEAR_DEPTH), depth, np.inf)


def cast_shadow(caster: ShadowCaster, pose: Pose, frame: ObjectFrame, K: np.ndarray, background_depth: np.ndarray,
                look: ShadowLook, depth_tolerance: float, depth_tolerance_abs: float) -> Shadow | None:
    """The shadow a plane-posed object (pose, its frame) casts into a photo (K [3, 3], filtered depth [H, W],
    +inf = none): darkness on the pixels whose depth is within depth_tolerance * plane depth +
    depth_tolerance_abs of its support plane's. None when it darkens no pixel."""
    found = plane_shadow(caster, pose, frame, look, K)
    if found is None:
        return None
    darkness, origin, e1, e2, cell = found
    image_height, image_width = background_depth.shape
    rows, cols = darkness.shape
    grid_to_camera = np.stack([cell * e1, cell * e2, origin], axis=1)  # [3, 3]: (j, i, 1) -> camera point
    corners = grid_to_camera @ np.array([[-0.5, -0.5, 1], [cols - 0.5, -0.5, 1], [-0.5, rows - 0.5, 1],
                                         [cols - 0.5, rows - 0.5, 1]], dtype=np.float64).T  # [3, 4]
    x0, y0, x1, y1 = 0, 0, image_width, image_height
    if (corners[2] > NEAR_DEPTH).all():  # else the grid reaches behind the camera: the whole image
        pixels = (K @ corners)[:2] / (K @ corners)[2]
        x0, y0 = max(0, math.floor(pixels[0].min())), max(0, math.floor(pixels[1].min()))
        x1, y1 = min(image_width, math.ceil(pixels[0].max())), min(image_height, math.ceil(pixels[1].max()))
    if x1 <= x0 or y1 <= y0:
        return None
    to_window = np.array([[1.0, 0.0, -0.5 - x0], [0.0, 1.0, -0.5 - y0], [0.0, 0.0, 1.0]])
    homography = to_window @ K @ grid_to_camera
    window = cv2.warpPerspective(darkness, homography, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    normal = pose.rotation @ frame.normal
    expected = plane_depth(normal, origin, K, x0, y0, x1 - x0, y1 - y0)
    surface = background_depth[y0:y1, x0:x1]
    with np.errstate(invalid="ignore"):  # inf - inf where neither the plane nor the photo has depth
        on_plane = np.isfinite(expected) & (np.abs(surface - expected) <= depth_tolerance * expected
                                            + depth_tolerance_abs)
    window = np.where(on_plane, window, 0.0).astype(np.float32)
    if window.max(initial=0.0) < MIN_DARKNESS:
        return None
    return Shadow(x0, y0, window)


def apply_shadows(image: np.ndarray, shadows: list[Shadow]) -> np.ndarray:
    """The image [H, W, 3] float32 darkened by the shadows (a copy; the image itself when there are none): where
    several overlap, the darkest (one light)."""
    if not shadows:
        return image
    y0, x0 = min(s.y0 for s in shadows), min(s.x0 for s in shadows)
    y1 = max(s.y0 + s.darkness.shape[0] for s in shadows)
    x1 = max(s.x0 + s.darkness.shape[1] for s in shadows)
    darkness = np.zeros((y1 - y0, x1 - x0), np.float32)  # over the union of the shadows' windows
    for shadow in shadows:
        h, w = shadow.darkness.shape
        region = darkness[shadow.y0 - y0:shadow.y0 - y0 + h, shadow.x0 - x0:shadow.x0 - x0 + w]
        np.maximum(region, shadow.darkness, out=region)
    out = image.copy()
    out[y0:y1, x0:x1] *= (1.0 - darkness)[..., None]
    return out
