"""Metric depth from relative (affine-invariant) disparity, per photo: the shift from the geometry of its planar
surfaces, the scale from a camera-height prior.

A relative depth model (Depth Anything's relative checkpoints, a relative ONNX export, or a `disparity` sidecar)
gives d = a / z + b with unknown a > 0 and b. Dividing by the median disparity removes a up to the global scale:
d_n = d / median(d) = 1 / (s z) + shift. Two unknowns remain, and they are fixed here:

1. The shift. Taking inverse depth as d_n - t for a wrong t maps the scene by X -> X / (alpha + beta z), a
   projective map of space that fixes the camera: planes stay planes (so the planarity of a surface cannot tell
   the shift, whatever t), but parallel planes at different distances stop being parallel and right angles stop
   being right (as t moves off, every plane turns towards facing the camera). So t is chosen where the dominant
   planar patches are best explained by a gravity-aligned room: the patches are found once (the planes stage's own
   search, stages/lib/planes/search.py, on the map with t = 0; which pixels form a plane does not depend on t), and
   for each t their normals are refitted and scored by the area-weighted squared angle by which each patch misses
   being horizontal or vertical, against the best "up" among the upward-facing patch normals (each miss clipped at
   CLIP_DEG, so clutter counts the same at any t). t is searched on a grid over SHIFT_RANGE (in median
   disparities), then refined. Floors and table tops must come out parallel, walls and cabinet fronts
   perpendicular to them. When the score does not depend on t (one surface alone, or nothing planar), no shift
   can be told and t = 0 is kept (the old assumption), and the record says so.
2. The scale, from two priors of an indoor photo. The lowest large horizontal surface is taken as the floor and
   the camera as `camera_height_m` above it (the paper's camera: 55 degree field of view, held at 1.2-1.6 m), and
   the median depth is taken as `median_depth_m`; the scale is the geometric mean of the two (on the embedded
   sample, whose cameras stand 0.4-1.8 m high, each alone is off by a median factor of 1.4, their mean by 1.26).
   Without a horizontal surface below the camera, or when the camera-height scale puts the median depth outside
   PLAUSIBLE_MEDIAN_M (a shelf just under the camera taken for the floor), the median-depth prior alone. A photo
   taken close over a table top, with no floor in view, is scaled as if the table were the floor.

A metric model needs neither: its metres are used as they are.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from stages.contract.errors import StageError
from stages.lib.depth.formats import PLAUSIBLE_MEDIAN_M
from stages.lib.planes.search import CAMERA_UP, detect_patches, grid_points, project
from stages.lib.planes.search_config import PlaneSearchConfig

SHIFT_RANGE = (-2.0, 0.95)  # shifts searched, in median disparities (the upper end also stays below the data's)
GRID_STEPS = 60
REFINE_STEPS = 30
CLIP_DEG = 20.0  # a patch missing horizontal and vertical by more than this is clutter
THICK_DEG = 8.0  # a patch thicker than this (atan of its smallest over its middle spread) is no plane: clutter
FLAT_DEG2 = 0.5  # score contrast over the searched shifts (squared degrees) below which the shift is not told
MAX_TILT_DEG = 65.0  # "up" within this of the camera's -y (as in the planes stage)
HORIZONTAL_TOL_DEG = 15.0
FLOOR_MIN_SHARE = 0.1  # a floor candidate holds at least this share of the largest horizontal patch's pixels
PATCH_PIXELS = 300  # pixels per patch used to refit its plane at each shift
STARTS = (-1.0, -0.5, 0.0, 0.5)  # shifts whose geometry the patches are searched in (capped below the data's)


@dataclass
class PatchPixels:
    """The pixels of one planar patch: their rays [M, 3] (z = 1) and normalised disparities [M]."""

    rays: np.ndarray
    disparity: np.ndarray

    def points(self, shift: float) -> np.ndarray:
        """Camera-frame points [M, 3] with inverse depth disparity - shift (up to the global scale)."""
        return self.rays / (self.disparity - shift)[:, None]


@dataclass
class Patches:
    """The planar patches found in one geometry: their pixels, weights [P] (pixels of the search grid, the same
    at any shift) and the grid's valid pixels (`total`: pixels outside every patch count as clutter)."""

    pixels: list[PatchPixels]
    weights: np.ndarray
    total: float

    def planes(self, shift: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Camera-facing unit normals [P, 3], centroids [P, 3] and thickness angles [P] (degrees: atan of the
        smallest over the middle spread of the points; near 0 for a plane) of the patches at `shift`."""
        normals, centroids, thickness = [], [], []
        for patch in self.pixels:
            points = patch.points(shift)
            centre = points.mean(axis=0)
            _, spreads, axes = np.linalg.svd(points - centre, full_matrices=False)
            normals.append(axes[2] if axes[2] @ centre < 0 else -axes[2])
            centroids.append(centre)
            thickness.append(math.degrees(math.atan2(spreads[2], max(spreads[1], 1e-12))))
        return np.asarray(normals).reshape(-1, 3), np.asarray(centroids).reshape(-1, 3), np.asarray(thickness)

    def score(self, shift: float) -> tuple[float, np.ndarray | None]:
        """(score in squared degrees, up [3]) at `shift`: the mean over the grid's pixels of the squared miss of
        their patch from horizontal or vertical w.r.t. the best up among the upward-facing normals (misses clipped
        at CLIP_DEG, which pixels outside every patch get, and so does a patch thicker than THICK_DEG: no plane,
        e.g. a floor and a wall merged); (inf, None) when no normal faces up within MAX_TILT_DEG of the camera's
        -y."""
        normals, _, thickness = self.planes(shift)
        tilt = np.degrees(np.arccos(np.clip(normals @ CAMERA_UP, -1.0, 1.0)))
        candidates = normals[tilt <= MAX_TILT_DEG]
        if len(candidates) == 0:
            return math.inf, None
        angles = np.degrees(np.arccos(np.clip(np.abs(normals @ candidates.T), 0.0, 1.0)))   # [P, C]
        misses = np.minimum(np.minimum(angles, 90.0 - angles), CLIP_DEG)
        misses[thickness > THICK_DEG] = CLIP_DEG
        clutter = (self.total - self.weights.sum()) * CLIP_DEG ** 2
        scores = ((self.weights[:, None] * misses ** 2).sum(axis=0) + clutter) / self.total   # [C]
        best = int(np.argmin(scores))
        return float(scores[best]), candidates[best]

    def floor_distance(self, shift: float) -> float | None:
        """Height of the camera over the lowest large horizontal patch at `shift` (scene units), or None."""
        _, up = self.score(shift)
        if up is None:
            return None
        normals, centroids, _ = self.planes(shift)
        horizontal = np.degrees(np.arccos(np.clip(np.abs(normals @ up), 0.0, 1.0))) <= HORIZONTAL_TOL_DEG
        if not horizontal.any():
            return None
        below = -(centroids @ up)                                               # [P] camera height over each
        floors = horizontal & (self.weights >= FLOOR_MIN_SHARE * self.weights[horizontal].max()) & (below > 0)
        return float(below[floors].max()) if floors.any() else None


@dataclass
class ShiftFit:
    """The shift found from one starting geometry, its score and whether the score told it."""

    shift: float
    score: float
    told: bool
    patches: Patches


@dataclass
class Recovered:
    """Metric depth from disparity and how it was obtained (depth.json's `recovery`)."""

    depth: np.ndarray  # [H, W] float32 metres, 0 = missing
    shift: float  # inverse depth is proportional to disparity / median - shift
    shift_from: str
    scale_m: float  # depth = scale_m / (disparity / median - shift)
    scale_from: str
    score_deg: float | None  # RMS miss from horizontal/vertical over the grid's pixels at `shift` (clutter =
    #                          CLIP_DEG); None without an upward-facing patch
    patches: int

    def record(self) -> dict:
        """The JSON of depth.json's `recovery`."""
        return {"shift": round(self.shift, 5), "shift_from": self.shift_from, "scale_m": round(self.scale_m, 5),
                "scale_from": self.scale_from, "score_deg": None if self.score_deg is None else round(self.score_deg, 3), "patches": self.patches}


def find_patches(normalised: np.ndarray, K: np.ndarray, start: float, max_depth_ratio: float,
                 rng: np.random.Generator, cfg: PlaneSearchConfig) -> Patches:
    """The planar patches of normalised disparity [H, W] found by the planes stage's search on the geometry of
    shift `start` (which pixels form a plane does not depend on the shift; how well they are found does)."""
    inverse = normalised - start
    valid = (normalised > 0) & (inverse > 0)
    depth = np.where(valid, 1.0 / np.where(valid, inverse, 1.0), 0.0)
    if valid.any():
        depth = np.where(depth <= max_depth_ratio * np.median(depth[valid]), depth, 0.0)
    points = grid_points(depth, K, cfg.max_points)
    try:
        found, _ = detect_patches(points, cfg)
    except RuntimeError:  # Qhull gives up on degenerate point sets; then this start finds nothing
        found = []
    height, width = normalised.shape
    pixels, weights = [], []
    for patch in found:
        if len(patch.seed_points) < 3:
            continue
        uv = project(patch.seed_points, K)                                     # [M, 2]
        cols = np.clip(np.floor(uv[:, 0]).astype(int), 0, width - 1)
        rows = np.clip(np.floor(uv[:, 1]).astype(int), 0, height - 1)
        keep = rng.permutation(len(rows))[:PATCH_PIXELS]
        rays = np.stack([(uv[keep, 0] - K[0, 2]) / K[0, 0], (uv[keep, 1] - K[1, 2]) / K[1, 1],
                         np.ones(len(keep))], axis=1)
        pixels.append(PatchPixels(rays, normalised[rows[keep], cols[keep]]))
        weights.append(len(rows))
    return Patches(pixels, np.asarray(weights, dtype=np.float64), float(max(len(points), sum(weights), 1)))


def find_shift(patches: Patches, upper: float) -> ShiftFit:
    """The shift over SHIFT_RANGE capped at `upper` with the best score: a grid, then golden section around the
    grid's best. Not told (shift 0) with fewer than two patches or when the score hardly varies."""
    if len(patches.pixels) < 2:
        return ShiftFit(0.0, patches.score(0.0)[0] if patches.pixels else math.inf, False, patches)
    grid = np.linspace(SHIFT_RANGE[0], min(SHIFT_RANGE[1], upper), GRID_STEPS)
    scores = np.array([patches.score(t)[0] for t in grid])
    finite = np.isfinite(scores)
    if finite.sum() < 2 or scores[finite].max() - scores[finite].min() < FLAT_DEG2:
        return ShiftFit(0.0, patches.score(0.0)[0], False, patches)
    best = int(np.argmin(np.where(finite, scores, np.inf)))
    a, b = grid[max(best - 1, 0)], grid[min(best + 1, len(grid) - 1)]
    golden = (math.sqrt(5) - 1) / 2
    c, d = b - golden * (b - a), a + golden * (b - a)
    fc, fd = patches.score(c)[0], patches.score(d)[0]
    for _ in range(REFINE_STEPS):
        if fc <= fd:
            b, d, fd = d, c, fc
            c = b - golden * (b - a)
            fc = patches.score(c)[0]
        else:
            a, c, fc = c, d, fd
            d = a + golden * (b - a)
            fd = patches.score(d)[0]
    shift, value = (c, fc) if fc <= fd else (d, fd)
    if value > scores[best]:
        shift, value = grid[best], scores[best]
    return ShiftFit(float(shift), float(value), True, patches)


def recover_metric_depth(disparity: np.ndarray, K: np.ndarray, camera_height_m: float, median_depth_m: float,
                         max_depth_ratio: float, rng: np.random.Generator,
                         cfg: PlaneSearchConfig | None = None) -> Recovered:
    """Metric depth [H, W] (float32 metres, 0 = missing) from affine-invariant disparity [H, W] (larger = nearer,
    <= 0 or non-finite = none) seen through K [3, 3] (module doc). The patches are searched from each of STARTS
    and once more from the best shift found; the fit with the best score wins. Pixels beyond max_depth_ratio x
    the median depth are dropped (sky, the far end of a wrong shift). StageError when no disparity is positive."""
    cfg = cfg or PlaneSearchConfig()
    valid = np.isfinite(disparity) & (disparity > 0)
    if not valid.any():
        raise StageError("relative depth: the disparity map has no positive value")
    normalised = np.where(valid, disparity / np.median(disparity[valid]), 0.0)          # [H, W]
    upper = 0.95 * float(np.percentile(normalised[valid], 2))
    fits = [find_shift(find_patches(normalised, K, min(start, upper), max_depth_ratio, rng, cfg), upper)
            for start in STARTS]
    best = min(fits, key=lambda fit: fit.score)
    if best.told:
        again = find_shift(find_patches(normalised, K, best.shift, max_depth_ratio, rng, cfg), upper)
        best = again if again.told and again.score < best.score else best
    shift = best.shift if best.told else 0.0
    inverse = normalised - shift
    kept = valid & (inverse > 0)
    relative = np.where(kept, 1.0 / np.where(kept, inverse, 1.0), 0.0)                 # [H, W]
    kept &= relative <= max_depth_ratio * np.median(relative[kept])
    median = float(np.median(relative[kept]))
    scale, scale_from = median_depth_m / median, f"median depth {median_depth_m:g} m"
    floor = best.patches.floor_distance(shift)
    if floor is None:
        scale_from += " (no horizontal surface below the camera)"
    elif not PLAUSIBLE_MEDIAN_M[0] <= camera_height_m / floor * median <= PLAUSIBLE_MEDIAN_M[1]:
        scale_from += f" (camera {camera_height_m:g} m above the lowest horizontal surface gives an implausible scale)"
    else:
        scale = math.sqrt(scale * camera_height_m / floor)
        scale_from = f"camera {camera_height_m:g} m above the lowest horizontal surface and " + scale_from
    count = len(best.patches.pixels)
    shift_from = (f"right angles of {count} planar patches" if best.told else
                  f"assumed 0: the {count} planar patches do not tell it")
    return Recovered(np.where(kept, scale * relative, 0.0).astype(np.float32), shift, shift_from, float(scale),
                     scale_from, math.sqrt(best.score) if math.isfinite(best.score) else None, count)
