"""Cutting an object out of a Gaussian-splatting scene (paper: "Foreground Object Extraction"), on arrays.

Steps, all on the Gaussian means after normalising the scene scale (median camera distance to the
cameras' look-at point = 1, or the robust spread of the means when there are no cameras):
1. plane:  the support plane (stages/support.py: RANSAC, or the base of the object's core for plain
           sheets and tables), removing it, all floaters below it and the flat Gaussians lying on it;
2. stat:   Open3D statistical outlier filter;
3. cluster: DBSCAN on the opaque Gaussians, keeping the cluster closest to the look-at point (then
           statistically removed Gaussians, DBSCAN noise and faint Gaussians near the cluster come back);
4. halo:   semi-transparent Gaussians away from the opaque core, nearly invisible ones, and huge Gaussians.
Then the checks: the object's base touches the removed plane, the removed layer is thin against the object,
and the plane did not cut through it (else a StageError naming the step and the fix).

A model given without cameras takes its up direction from `up_hint` or from its largest plane, and may
already be cut out. The extract stage (stages/extract.py) reads and writes the files around `extract_object`.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from stages import pointcloud, support
from stages.errors import StageError
from stages.geometry import camera_centres, image_ups, look_at_point
from stages.specs.extract import ExtractConfig
from stages.support import GroundPlane

log = logging.getLogger(__name__)

# Why a Gaussian was removed (index into STEPS); 0 = kept.
STEPS = ("kept", "plane", "stat", "cluster", "halo")


@dataclass
class CameraRig:
    """The capture cameras in world coordinates (stages/geometry.py conventions)."""

    centres: np.ndarray  # [C, 3]
    ups: np.ndarray  # [C, 3] unit image-up directions
    look_at: np.ndarray | None  # [3] the point the optical axes meet; None for parallel axes

    @classmethod
    def from_viewmats(cls, viewmats: np.ndarray) -> "CameraRig":
        """Build from world-to-camera matrices [C, 4, 4]."""
        return cls(camera_centres(viewmats), image_ups(viewmats), look_at_point(viewmats))

    def up(self) -> np.ndarray | None:
        """Mean image-up direction [3] (unit); None if the cameras disagree too much to define one."""
        mean_up = self.ups.mean(axis=0)
        norm = np.linalg.norm(mean_up)
        return mean_up / norm if norm > 0.5 else None


@dataclass
class Extraction:
    """Result of `extract_object`, in the input (model) frame unless noted."""

    removed_by: np.ndarray  # [N] int index into STEPS, 0 = kept
    normal: np.ndarray  # [3] unit, from the plane towards the object
    base_point: np.ndarray  # [3] object centroid projected on the plane
    height: float  # object height along the normal, model units
    scene_scale: float  # model units per normalised unit
    centre: np.ndarray  # [3] normalisation centre (cameras' look-at point or robust centre)
    plane_source: str
    dbscan_eps: float  # DBSCAN radius used (normalised units)
    counts: dict = field(default_factory=dict)
    checks: dict = field(default_factory=dict)  # base_gap, layer (fractions of the height), cut_density

    @property
    def keep(self) -> np.ndarray:
        """Mask [N] of the object's Gaussians."""
        return self.removed_by == 0


def normalisation(means: np.ndarray, rig: CameraRig | None) -> tuple[np.ndarray, float]:
    """Scene centre [3] and scale so that (means - centre) / scale has median camera distance 1.

    Without cameras (or with parallel optical axes): the median of the means and their median
    distance to it.
    """
    centre = rig.look_at if rig is not None else None
    if centre is not None:
        scale = float(np.median(np.linalg.norm(rig.centres - centre, axis=1)))
    else:
        centre = np.median(means, axis=0)
        scale = float(np.median(np.linalg.norm(means - centre, axis=1)))
    if not np.isfinite(scale) or scale <= 0:
        raise StageError(f"extract: cannot normalise the scene scale (scale={scale}); are all Gaussians at one point?")
    return centre, scale


def pick_central_cluster(points: np.ndarray, labels: np.ndarray, centre: np.ndarray | None,
                         merge_distance: float = 0.0) -> np.ndarray:
    """Mask [N] of the DBSCAN cluster (labels [N], -1 = noise) whose points lie closest to `centre` [3]
    (None: the largest cluster), joined by every cluster that comes within `merge_distance` of it (repeatedly).

    Closeness is the median point distance, so a ring of halo around the object never beats the object.
    Joining keeps an object that the filters split into pieces whole: when a small fragment of its side
    happens to lie nearest the centre, the body next to it joins instead of being thrown away. Without a
    centre (a model without cameras, whose median point may lie between a plant's leaves) the model is the
    object and its largest cluster seeds it.
    """
    cluster_ids, sizes = np.unique(labels[labels >= 0], return_counts=True)
    if len(cluster_ids) == 0:
        return np.zeros(len(points), dtype=bool)
    if centre is None:
        keep = labels == cluster_ids[int(np.argmax(sizes))]
    else:
        distance = np.linalg.norm(points - centre, axis=1)  # [N]
        medians = [np.median(distance[labels == cluster_id]) for cluster_id in cluster_ids]
        keep = labels == cluster_ids[int(np.argmin(medians))]
    others = [c for c in cluster_ids if not keep[labels == c].any()]
    joined = True
    while joined and others and merge_distance > 0:
        joined = False
        for cluster_id in list(others):
            members = labels == cluster_id
            if pointcloud.nearest_distance(points[members], points[keep]).min() <= merge_distance:
                keep |= members
                others.remove(cluster_id)
                joined = True
    return keep


def central_spacing(points: np.ndarray, centre: np.ndarray | None, cfg: ExtractConfig) -> float:
    """Typical spacing of the Gaussians near `centre` [3] (points [N, 3] normalised): the median distance
    to the dbscan_min_points-th neighbour among those within cfg.spacing_radius (all when too few).

    Measured near the object, not over the whole scene: a densified background (walls, floaters) is
    sparse and would inflate DBSCAN's radius until the object merges with its surroundings. Without a
    centre (a model without cameras, which is the object) the cfg.model_spacing_percentile of all points:
    its sparse parts (a plant's pot of large Gaussians) must stay connected to the rest.
    """
    if centre is None:
        return pointcloud.neighbour_spacing(points, cfg.dbscan_min_points, cfg.model_spacing_percentile)
    near = points[np.linalg.norm(points - centre, axis=1) < cfg.spacing_radius] if cfg.spacing_radius > 0 else points
    return pointcloud.neighbour_spacing(near if len(near) > cfg.dbscan_min_points else points, cfg.dbscan_min_points)


def regrow(points: np.ndarray, removed_by: np.ndarray, eps: float, noise: np.ndarray | None = None) -> np.ndarray:
    """Indices of statistically removed Gaussians, and of DBSCAN noise (`noise` [N] bool, optional), within
    `eps` of a kept one (points [N, 3], removed_by [N]).

    The statistical filter and DBSCAN also drop sparse parts of the object itself (large, sparse
    Gaussians on and inside its body); once the object cluster is known, those touching it come back.
    Halo far from the object stays out.
    """
    sparse = removed_by == STEPS.index("stat")
    if noise is not None:
        sparse |= noise & (removed_by == STEPS.index("cluster"))
    candidates = np.flatnonzero(sparse)
    near = pointcloud.nearest_distance(points[candidates], points[removed_by == 0]) <= eps
    return candidates[near]


def halo_mask(points: np.ndarray, opacities: np.ndarray, max_scales: np.ndarray, object_height: float,
              distance: float, cfg: ExtractConfig) -> np.ndarray:
    """Mask [N] of halo Gaussians among the object's: semi-transparent ones farther than `distance`
    from the opaque core, nearly invisible ones (below cfg.invisible_opacity) and huge ones. points [N, 3] and
    max_scales [N] normalised; opacities [N] in [0, 1]."""
    opaque = opacities >= cfg.halo_opacity
    far = pointcloud.nearest_distance(points, points[opaque]) > distance  # [N]
    huge = max_scales > cfg.huge_scale_fraction * object_height
    return (~opaque & far) | huge | (opacities < cfg.invisible_opacity)


@dataclass
class Core:
    """The object's core: the DBSCAN cluster of opaque Gaussians nearest the look-at point (or the largest)."""

    mask: np.ndarray  # [N] bool over all Gaussians
    spacing: float  # Gaussian spacing where it was measured (central_spacing), normalised
    eps: float  # the DBSCAN radius used (core_spacing_factor x spacing)


def object_core(points: np.ndarray, candidates: np.ndarray, look_at: np.ndarray | None, cfg: ExtractConfig) -> Core:
    """The object's core among the `candidates` [N] bool (opaque Gaussians) of points [N, 3] (normalised):
    their DBSCAN cluster nearest `look_at` [3] (None: the largest). StageError when there is no cluster."""
    index = np.flatnonzero(candidates)
    spacing = central_spacing(points[index], look_at, cfg)
    eps = max(cfg.dbscan_eps, cfg.core_spacing_factor * spacing)
    labels = pointcloud.dbscan_labels(points[index], eps, cfg.dbscan_min_points)
    picked = pick_central_cluster(points[index], labels, look_at, cfg.cluster_merge_eps * eps)
    if not picked.any():
        raise StageError(f"extract: no cluster of {cfg.dbscan_min_points} opaque Gaussians near the centre; "
                         "is there an object where the cameras look?")
    mask = np.zeros(len(points), dtype=bool)
    mask[index[picked]] = True
    return Core(mask, spacing, eps)


def filter_scene(points: np.ndarray, faint: np.ndarray, removed_by: np.ndarray, look_at: np.ndarray,
                 cfg: ExtractConfig) -> tuple[float, int]:
    """The stat and cluster steps of a captured scene, in place on removed_by [N]: the statistical filter, then
    DBSCAN keeping the cluster nearest `look_at` [3]; statistically removed Gaussians, DBSCAN noise and
    faint Gaussians (faint [N] bool, which sit out both) near the cluster come back. Returns (DBSCAN radius,
    Gaussians given back)."""
    alive = np.flatnonzero((removed_by == 0) & ~faint)
    kept = pointcloud.statistical_inliers(points[alive], cfg.stat_neighbours, cfg.stat_std_ratio)
    removed_by[alive[~kept]] = STEPS.index("stat")
    _check_step(removed_by, "stat", cfg)

    alive = np.flatnonzero((removed_by == 0) & ~faint)
    eps = max(cfg.dbscan_eps, cfg.dbscan_spacing_factor * central_spacing(points[alive], look_at, cfg))
    labels = pointcloud.dbscan_labels(points[alive], eps, cfg.dbscan_min_points)
    kept = pick_central_cluster(points[alive], labels, look_at, cfg.cluster_merge_eps * eps)
    removed_by[alive[~kept]] = STEPS.index("cluster")
    noise = np.zeros(len(points), dtype=bool)
    noise[alive[labels < 0]] = cfg.regrow_noise
    return eps, _faint_sit_out(points, faint, removed_by, noise, cfg.regrow_fraction * eps, cfg)


def filter_model(points: np.ndarray, faint: np.ndarray, removed_by: np.ndarray, eps: float,
                 cfg: ExtractConfig) -> tuple[float, int]:
    """The cluster step of a model without cameras, in place on removed_by [N]: the model is the object, so
    no statistical filter (it would strip a plant pot's sparse, large Gaussians); its largest DBSCAN cluster
    at the core's radius `eps` stays, and of the rest (faint [N] bool ones included) only what no chain of
    Gaussians within `eps` links to it goes (floaters, support remnants). Returns (eps, Gaussians given back)."""
    alive = np.flatnonzero((removed_by == 0) & ~faint)
    labels = pointcloud.dbscan_labels(points[alive], eps, cfg.dbscan_min_points)
    kept = pick_central_cluster(points[alive], labels, None, cfg.cluster_merge_eps * eps)
    outside = removed_by == 0  # [N]
    outside[alive[kept]] = False
    removed_by[outside] = STEPS.index("cluster")
    _check_step(removed_by, "cluster", cfg)
    given_back = 0
    while True:
        regrown = regrow(points, removed_by, eps, outside & (removed_by == STEPS.index("cluster")))
        if len(regrown) == 0:
            return eps, given_back
        removed_by[regrown] = 0
        given_back += len(regrown)


def _faint_sit_out(points: np.ndarray, faint: np.ndarray, removed_by: np.ndarray, noise: np.ndarray, distance: float,
                   cfg: ExtractConfig) -> int:
    """Mark the faint Gaussians still in (faint [N]) as cluster-removed, check the step, then give back those
    and the `noise` [N] within `distance` of the kept ones (regrow); returns how many came back."""
    noise = noise | ((removed_by == 0) & faint)
    removed_by[(removed_by == 0) & faint] = STEPS.index("cluster")
    _check_step(removed_by, "cluster", cfg)
    regrown = regrow(points, removed_by, distance, noise)
    removed_by[regrown] = 0
    return len(regrown)


def extract_object(means: np.ndarray, opacities: np.ndarray, scales: np.ndarray, cfg: ExtractConfig,
                   viewmats: np.ndarray | None = None, seed: int = 0, rotations: np.ndarray | None = None,
                   enforce_checks: bool = True) -> Extraction:
    """Separate the object's Gaussians from the scene and check the cut.

    means [N, 3] model units; opacities [N] in [0, 1]; scales [N, 3] model units (not log); rotations
    [N, 3, 3] local-to-world (None: axis-aligned); viewmats [C, 4, 4] world-to-camera (OpenCV) or None (a
    model without cameras: up from cfg.up_hint or its largest plane; it is the object, may stand on its
    support or already be cut out). Raises StageError on degenerate input, when a step removes (almost)
    everything or, with cameras, (almost) nothing in all, and when the checks of stages/support.py fail
    (enforce_checks=False: their message goes into checks["refused"] instead, to look at a refused cut).
    """
    means = np.asarray(means, dtype=np.float64)
    opacities = np.asarray(opacities, dtype=np.float64)  # [N]
    total = len(means)
    if total < max(cfg.min_object_gaussians, cfg.stat_neighbours + 1):
        raise StageError(f"extract: only {total} Gaussians in the scene; need at least "
                         f"{max(cfg.min_object_gaussians, cfg.stat_neighbours + 1)}")
    if not np.isfinite(means).all():
        raise StageError("extract: the scene has non-finite Gaussian positions")
    rig = CameraRig.from_viewmats(np.asarray(viewmats, dtype=np.float64)) if viewmats is not None and len(viewmats) else None
    centre, scale = normalisation(means, rig)
    points = (means - centre) / scale  # [N, 3] normalised, look-at point at the origin
    scales = np.asarray(scales, dtype=np.float64) / scale  # [N, 3] normalised

    removed_by = np.zeros(total, dtype=np.int64)
    opaque = opacities >= cfg.plane_min_opacity  # [N]
    fit = opaque if opaque.sum() > cfg.stat_neighbours else np.ones(total, dtype=bool)
    planes = support.ransac_planes(points[fit], cfg, seed)
    up = rig.up() if rig is not None else _unit_or_none(cfg.up_hint)
    if up is None:
        up = support.estimated_up(planes, (rig.centres - centre) / scale if rig is not None else points[fit],
                                  cfg.plane_distance)
    look_at = np.zeros(3) if rig is not None and rig.look_at is not None else None
    core = object_core(points, fit, look_at, cfg)
    solid_core = core.mask & (opacities >= cfg.height_opacity)  # [N] the base is the solid body's: a plain
    base_set = solid_core if solid_core.sum() > cfg.dbscan_min_points else core.mask  # sheet's noise is fainter
    plane = support.choose_plane(support.ransac_support(planes, up, points[base_set], cfg), points[base_set], up, cfg)
    heights = plane.height(points)  # [N]
    along = support.normal_extents(plane.normal, scales, rotations)  # [N]
    on_plane, support_counts = support.support_mask(plane, heights, along, scales.max(axis=1), core.spacing, cfg)
    removed_by[on_plane] = STEPS.index("plane")
    _check_step(removed_by, "plane", cfg)

    faint = opacities < cfg.cluster_min_opacity  # [N] sit out the statistical filter and DBSCAN
    if look_at is not None:
        eps, given_back = filter_scene(points, faint, removed_by, look_at, cfg)
    else:
        eps, given_back = filter_model(points, faint, removed_by, core.eps, cfg)

    across = support.plane_coordinates(points, plane.normal)  # [N, 2]
    edge = support.beyond_footprint(across, heights, removed_by == 0, opaque, plane, core.spacing, cfg)
    removed_by[edge] = STEPS.index("plane")
    support_counts["removed_beyond_footprint"] = int(edge.sum())
    filtered = (removed_by == STEPS.index("stat")) | (removed_by == STEPS.index("cluster"))
    under = support.under_object(across, heights, filtered, removed_by == 0, opaque,
                                 support.layer_thickness(plane, core.spacing, cfg), eps, cfg)
    removed_by[under] = 0
    given_back += int(under.sum())

    alive = np.flatnonzero(removed_by == 0)
    object_height = float(heights[alive].max())
    halo = halo_mask(points[alive], opacities[alive], scales.max(axis=1)[alive], object_height, eps, cfg)
    removed_by[alive[halo]] = STEPS.index("halo")
    _check_step(removed_by, "halo", cfg)

    keep = removed_by == 0
    if keep.sum() < cfg.min_object_gaussians:
        raise StageError(f"extract: only {keep.sum()} object Gaussians left (need {cfg.min_object_gaussians}); "
                         "the filters are too aggressive for this scene (raise stat_std_ratio or dbscan_eps)")
    removed_fraction = 1.0 - keep.mean()
    if rig is not None and removed_fraction < cfg.min_total_removed_fraction:
        raise StageError(f"extract: removed only {removed_fraction:.2%} of the Gaussians (less than "
                         f"min_total_removed_fraction={cfg.min_total_removed_fraction}); no ground or background "
                         "was found to cut away. Is the scene already cut out? Then give it as objects[].splat")

    solid = keep & (opacities >= cfg.height_opacity)  # the height is the opaque body's:
    solid = solid if solid.any() else keep  # faint haze on top would make it taller
    kept_heights = heights[solid]
    base = support.footprint_base(across[solid], kept_heights - support.BOTTOM_SIGMAS * along[solid])
    checks = check_cut(across, heights, keep, removed_by == STEPS.index("plane"), opaque, kept_heights, base, plane,
                       core.spacing, cfg, enforce_checks)
    centroid = points[keep].mean(axis=0)
    base_point = centroid - plane.height(centroid[None])[0] * plane.normal
    counts = {"total": total, "given_back": given_back,  # statistically removed, DBSCAN noise and faint
              **{f"removed_{name}": int((removed_by == i).sum()) for i, name in enumerate(STEPS) if i},
              "removed_below_plane": int((heights < -plane.thickness).sum()), **support_counts,
              "kept": int(keep.sum())}
    return Extraction(removed_by=removed_by, normal=plane.normal, base_point=base_point * scale + centre,
                      height=float(kept_heights.max()) * scale, scene_scale=scale, centre=centre,
                      plane_source=plane.source, dbscan_eps=eps, counts=counts, checks=checks)


def check_cut(across: np.ndarray, heights: np.ndarray, keep: np.ndarray, support_removed: np.ndarray,
              opaque: np.ndarray, kept_heights: np.ndarray, base: float, plane: GroundPlane,
              spacing: float, cfg: ExtractConfig, enforce: bool = True) -> dict[str, float | str]:
    """The cut's checks (stages/support.py check_support; StageError when one fails) and their figures:
    base_gap and layer as fractions of the object's height, cut_density. across [N, 2] plane coordinates,
    heights [N] above the plane, keep / support_removed / opaque [N] bool, kept_heights [M] of the opaque kept
    ones, base: how low the object reaches (stages/support.py footprint_base)."""
    top = float(kept_heights.max())
    layer = support.layer_thickness(plane, spacing, cfg)
    density = support.cut_density(across, heights, keep, support_removed, opaque, cfg.max_layer * top,
                                  plane.thickness, spacing)
    checks = {"base_gap": float((base - layer) / top),
              "layer": layer / top, "cut_density": density}
    log.info("support plane %s: base gap %.3f, layer %.3f of the object's height, cut density %.2f", plane.source,
             checks["base_gap"], checks["layer"], density)
    try:
        support.check_support(plane, base, top, layer, density, cfg)
    except StageError as error:
        if enforce:
            raise
        checks["refused"] = str(error)
    return checks


def _unit_or_none(vector: list[float] | None) -> np.ndarray | None:
    """The direction [3] as a unit vector, or None."""
    if vector is None:
        return None
    direction = np.asarray(vector, dtype=np.float64)
    if direction.shape != (3,) or not np.linalg.norm(direction) > 0:
        raise StageError(f"extract: up_hint must be a non-zero 3-vector, got {vector!r}")
    return direction / np.linalg.norm(direction)


def _check_step(removed_by: np.ndarray, step: str, cfg: ExtractConfig) -> None:
    """Raise StageError if `step` removed more than `max_step_removed_fraction` of its input."""
    index = STEPS.index(step)
    step_input = int(((removed_by == 0) | (removed_by >= index)).sum())
    removed = int((removed_by == index).sum())
    if step_input == 0 or removed > cfg.max_step_removed_fraction * step_input:
        raise StageError(f"extract: the {step} step removed {removed} of {step_input} Gaussians (almost all); "
                         "the scene does not look like an object standing on a plane, or the step's thresholds "
                         "do not fit its scale")
