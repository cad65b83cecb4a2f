"""Cutting an object out of a Gaussian-splatting scene (paper: "Foreground Object Extraction"), on arrays.

Steps, all on the Gaussian means after normalising the scene scale (median camera distance to the
cameras' look-at point = 1, or the robust spread of the means when there are no cameras):
1. plane:  the support plane (stages/lib/objects/support.py: RANSAC, or the base of the object's core for plain
           sheets and tables), removing it, all floaters below it and the flat Gaussians lying on it;
2. stat:   Open3D statistical outlier filter;                          (2 and 3: stages/lib/objects/clusters.py)
3. cluster: DBSCAN on the opaque Gaussians, keeping the cluster closest to the look-at point (then
           statistically removed Gaussians, DBSCAN noise and faint Gaussians near the cluster come back);
4. halo:   semi-transparent Gaussians away from the opaque core, nearly invisible ones, huge Gaussians, and
           (given the cameras' intrinsics) background haze: Gaussians outside the solid body's silhouette in
           the capture views with the colour of the background there, and what lies outside the cut's visible
           footprint in many capture views (stages/lib/objects/silhouettes.py, footprint_carve.py).
Then the checks: the object's base touches the removed plane, the removed layer is thin against the object,
and the plane did not cut through it (else a StageError naming the step and the fix).

A model given without cameras takes its up direction from `up_hint` or from its largest plane, and may
already be cut out. The extract stage (stages/extract/run.py) reads and writes the files around `extract_object`.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import torch

from stages.contract.errors import StageError
from stages.lib.gaussians.model import SH_C0, Gaussians, quat_to_rotmat
from stages.lib.geometry import camera_centres, image_ups, look_at_point
from stages.lib.objects import pointcloud
from stages.lib.objects import self_check, support
from stages.lib.objects.clusters import STEPS, check_step, filter_model, filter_scene, object_core
from stages.lib.objects.cut_config import CutConfig
from stages.lib.objects.footprint_carve import carve_outside_footprint
from stages.lib.objects.silhouettes import GaussianArrays, Intrinsics, haze_scores
from stages.lib.objects.support import GroundPlane
from stages.records.cameras import CamerasRecord

log = logging.getLogger(__name__)

@dataclass
class CameraRig:
    """The capture cameras in world coordinates (stages/lib/geometry.py conventions)."""

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


def halo_mask(points: np.ndarray, opacities: np.ndarray, max_scales: np.ndarray, object_height: float,
              distance: float, cfg: CutConfig, base: np.ndarray | None = None) -> np.ndarray:
    """Mask [N] of halo Gaussians among the object's: semi-transparent ones farther than `distance`
    from the opaque core, except those of its base (base [N] bool, support.over_base; None: no base), nearly
    invisible ones (below cfg.invisible_opacity) and huge ones. points [N, 3] and max_scales [N] normalised;
    opacities [N] in [0, 1]."""
    opaque = opacities >= cfg.halo_opacity
    far = pointcloud.nearest_distance(points, points[opaque]) > distance  # [N]
    if base is not None:
        far &= ~base
    huge = max_scales > cfg.huge_scale_fraction * object_height
    return (~opaque & far) | huge | (opacities < cfg.invisible_opacity)


def background_haze(gaussians: GaussianArrays, points: np.ndarray, across: np.ndarray, heights: np.ndarray,
                    keep: np.ndarray, look_at: np.ndarray | None, viewmats: np.ndarray, intrinsics: Intrinsics,
                    scale: float, cfg: CutConfig) -> np.ndarray:
    """Mask [N] of kept Gaussians (keep [N]) that are background haze (stages/lib/objects/silhouettes.py): their centre
    lies more than cfg.silhouette_distance (normalised) outside the silhouette of the object's solid body in a capture
    view (viewmats [C, 4, 4], intrinsics rendered at cfg.silhouette_long_side), and there their colour differs
    from the background's (the Gaussians not kept) by at most cfg.background_colour_tolerance on average. The
    solid body: the DBSCAN core of the kept Gaussians at least cfg.height_opacity opaque nearest `look_at`, and
    the solid Gaussians within the core's radius of it. Gaussians over the body's footprint on the support plane
    and below its median height are its base (support.over_base), left to the support checks: a pot tapering to
    its base has semi-transparent bottom Gaussians outside the solid silhouette, coloured like a brown floor.
    gaussians in model units; points [N, 3] normalised by `scale` model units, across [N, 2] and heights [N] their
    plane coordinates and heights above the support plane (support.plane_coordinates, GroundPlane.height)."""
    solid = keep & (gaussians.opacities >= cfg.height_opacity)
    haze = np.zeros(len(points), dtype=bool)
    if solid.sum() <= cfg.dbscan_min_points:
        return haze
    try:
        core = object_core(points, solid, look_at, cfg)
    except StageError:  # no cluster of solid Gaussians: nothing to draw a silhouette with
        return haze
    body = np.zeros(len(points), dtype=bool)  # [N]
    body[solid] = pointcloud.nearest_distance(points[solid], points[core.mask]) <= core.eps
    candidates = np.flatnonzero(keep & ~body)
    candidates = candidates[~support.over_base(across, heights, candidates, np.flatnonzero(body))]
    if len(candidates) == 0:
        return haze
    scores = haze_scores(gaussians.means[candidates], gaussians.colors[candidates], gaussians.subset(body),
                         gaussians.subset(~keep), viewmats, intrinsics.scaled(cfg.silhouette_long_side),
                         cfg.silhouette_distance * scale)
    haze[candidates[scores.colour_difference <= cfg.background_colour_tolerance]] = True  # nan: never beyond
    return haze


def cut_gaussians(gaussians: Gaussians, cfg: CutConfig, cameras: CamerasRecord | None = None, seed: int = 0,
                  enforce_checks: bool = True) -> Extraction:
    """`extract_object` on a Gaussians model and the cameras it was trained with (None: a model without cameras)."""
    viewmats = intrinsics = colors = None
    if cameras is not None and cameras.frames:
        viewmats = cameras.viewmats
        colors = (0.5 + SH_C0 * gaussians.sh[:, 0].detach().cpu().numpy()).clip(0.0, 1.0)  # [N, 3]
        intrinsics = Intrinsics.of_cameras(cameras)
    means, opacities, scales, quats = (tensor.detach().cpu().numpy() for tensor in (
        gaussians.means, gaussians.opacities, gaussians.scales, gaussians.quats))
    return extract_object(means, opacities, scales, cfg, viewmats, seed=seed, quats=quats,
                          enforce_checks=enforce_checks, intrinsics=intrinsics, colors=colors)


def extract_object(means: np.ndarray, opacities: np.ndarray, scales: np.ndarray, cfg: CutConfig,
                   viewmats: np.ndarray | None = None, seed: int = 0, quats: np.ndarray | None = None,
                   enforce_checks: bool = True, intrinsics: Intrinsics | None = None,
                   colors: np.ndarray | None = None) -> Extraction:
    """Separate the object's Gaussians from the scene and check the cut.

    means [N, 3] model units; opacities [N] in [0, 1]; scales [N, 3] model units (not log); quats [N, 4]
    (w, x, y, z) local-to-world (None: axis-aligned); viewmats [C, 4, 4] world-to-camera (OpenCV) or None (a
    model without cameras: up from cfg.up_hint or its largest plane; it is the object, may stand on its
    support or already be cut out); intrinsics of those cameras and colors [N, 3] in [0, 1] of the Gaussians
    (either None: no background-haze test in the halo step). Raises StageError on degenerate input, when a
    step removes (almost) everything or, with cameras, (almost) nothing in all, and when the checks of
    stages/lib/objects/support.py fail (enforce_checks=False: their message goes into checks["refused"] instead, to look
    at a refused cut). With cameras, the cut must also pass its self-check (stages/lib/objects/self_check.py: seen
    by the capture views, aimed at, no wider than the orbit): when the cluster nearest the look-at point fails it,
    the next nearest clusters are tried (up to cfg.self_check_candidates), then the nearest at a DBSCAN radius
    cfg.self_check_tighter as wide (checks["candidate"] says which cluster was kept, checks["radius_scale"] at which
    radius, checks["passed_over"] why the first cut was not), and a cut none passes is refused.
    """
    arrays = (means, opacities, scales, cfg, viewmats, seed, quats, enforce_checks, intrinsics, colors)
    extraction = _cut(*arrays)
    failures = self_check.failed_checks(extraction.checks, cfg) if viewmats is not None else []
    others = [(rank, 1.0) for rank in range(1, cfg.self_check_candidates)] + \
        ([(0, cfg.self_check_tighter)] if cfg.self_check_tighter < 1.0 else [])
    for rank, radius_scale in others if failures else []:
        try:
            candidate = _cut(*arrays, rank=rank, radius_scale=radius_scale)
        except StageError:  # no such cluster, or it fails the support checks
            continue
        if not self_check.failed_checks(candidate.checks, cfg) and "refused" not in candidate.checks:
            log.info("extract: the cluster nearest the look-at point fails the self-check (%s); cluster %d at %.2fx "
                     "the DBSCAN radius passes", "; ".join(failures), rank + 1, radius_scale)
            candidate.checks.update(candidate=rank, passed_over="; ".join(failures),
                                    **({"radius_scale": radius_scale} if radius_scale < 1.0 else {}))
            return candidate
    extraction.checks["candidate"] = 0
    if failures:
        message = (f"extract: the cut fails its self-check, {'; '.join(failures)}. Extract cuts out an object standing "
                   "on a surface: film it there with free space around it, keeping it in the middle of every frame; or "
                   "give it already cut out as objects[].splat")
        if enforce_checks:
            raise StageError(message)
        extraction.checks.setdefault("refused", message)
    return extraction


def _cut(means: np.ndarray, opacities: np.ndarray, scales: np.ndarray, cfg: CutConfig, viewmats: np.ndarray | None,
         seed: int, quats: np.ndarray | None, enforce_checks: bool, intrinsics: Intrinsics | None,
         colors: np.ndarray | None, rank: int = 0, radius_scale: float = 1.0) -> Extraction:
    """One cut of extract_object (its arguments), keeping the rank-th DBSCAN cluster nearest the look-at point at
    radius_scale x its DBSCAN radius; its checks hold the self-check's figures when there are cameras."""
    means = np.asarray(means, dtype=np.float64)
    opacities = np.asarray(opacities, dtype=np.float64)  # [N]
    total = len(means)
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (total, 1)) if quats is None else np.asarray(quats, dtype=np.float64)
    rotations = quat_to_rotmat(torch.from_numpy(quats)).numpy()  # [N, 3, 3]
    if total < max(cfg.min_object_gaussians, cfg.stat_neighbours + 1):
        raise StageError(f"extract: only {total} Gaussians in the scene; need at least "
                         f"{max(cfg.min_object_gaussians, cfg.stat_neighbours + 1)}")
    if not np.isfinite(means).all():
        raise StageError("extract: the scene has non-finite Gaussian positions")
    viewmats = np.asarray(viewmats, dtype=np.float64) if viewmats is not None and len(viewmats) else None
    rig = CameraRig.from_viewmats(viewmats) if viewmats is not None else None
    centre, scale = normalisation(means, rig)
    points = (means - centre) / scale  # [N, 3] normalised, look-at point at the origin
    model_scales = np.asarray(scales, dtype=np.float64)  # [N, 3]
    scales = model_scales / scale  # [N, 3] normalised

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
    plane = support.choose_plane(support.ransac_support(planes, up, points[base_set], core.spacing, cfg),
                                 points[base_set], up, cfg)
    heights = plane.height(points)  # [N]
    along = support.normal_extents(plane.normal, scales, rotations)  # [N]
    on_plane, support_counts = support.support_mask(plane, heights, along, scales.max(axis=1), core.spacing, cfg)
    removed_by[on_plane] = STEPS.index("plane")
    check_step(removed_by, "plane", cfg)

    faint = opacities < cfg.cluster_min_opacity  # [N] sit out the statistical filter and DBSCAN
    if look_at is None and rank:
        raise StageError("extract: without a look-at point there is no next cluster to try")
    if look_at is not None:
        eps, given_back = filter_scene(points, faint, removed_by, look_at, cfg, rank, radius_scale)
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
    base = support.over_base(across, heights, alive, alive[opacities[alive] >= cfg.height_opacity])
    halo = halo_mask(points[alive], opacities[alive], scales.max(axis=1)[alive], object_height, eps, cfg, base)
    removed_by[alive[halo]] = STEPS.index("halo")
    haze, outside = np.zeros((2, total), dtype=bool)  # [N], [N]
    if rig is not None and intrinsics is not None and colors is not None and cfg.silhouette_distance > 0:
        gaussians = GaussianArrays(means, quats, model_scales, opacities, np.asarray(colors, dtype=np.float64))
        haze = background_haze(gaussians, points, across, heights, removed_by == 0, look_at, viewmats, intrinsics,
                               scale, cfg)
        removed_by[haze] = STEPS.index("halo")
        outside = carve_outside_footprint(gaussians, points, across, heights, removed_by == 0, viewmats, intrinsics,
                                          scale, cfg)
        removed_by[outside] = STEPS.index("halo")
    check_step(removed_by, "halo", cfg)

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
                       core.spacing, base_set, cfg, enforce_checks)
    if rig is not None:
        figures = self_check.cut_figures(points, solid, total, int(keep.sum()), plane.normal, float(kept_heights.max()),
                                         viewmats, None if intrinsics is None else intrinsics.Ks,
                                         None if intrinsics is None else intrinsics.sizes, look_at, scale, centre,
                                         cfg.wall_distance, seed)
        checks.update(figures, **self_check.margins(figures, cfg))
    centroid = points[keep].mean(axis=0)
    base_point = centroid - plane.height(centroid[None])[0] * plane.normal
    counts = {"total": total, "given_back": given_back,  # statistically removed, DBSCAN noise and faint
              **{f"removed_{name}": int((removed_by == i).sum()) for i, name in enumerate(STEPS) if i},
              "removed_below_plane": int((heights < -plane.thickness).sum()), **support_counts,
              "removed_background_haze": int(haze.sum()), "removed_outside_footprint": int(outside.sum()),
              "kept": int(keep.sum())}
    return Extraction(removed_by=removed_by, normal=plane.normal, base_point=base_point * scale + centre,
                      height=float(kept_heights.max()) * scale, scene_scale=scale, centre=centre,
                      plane_source=plane.source, dbscan_eps=eps, counts=counts, checks=checks)


def check_cut(across: np.ndarray, heights: np.ndarray, keep: np.ndarray, support_removed: np.ndarray,
              opaque: np.ndarray, kept_heights: np.ndarray, base: float, plane: GroundPlane,
              spacing: float, core: np.ndarray, cfg: CutConfig, enforce: bool = True) -> dict[str, float | str]:
    """The cut's checks (stages/lib/objects/support.py check_support; StageError when one fails) and their figures:
    base_gap and layer as fractions of the object's height, cut_density, core_below (how far the object's core
    reaches under the plane, as a fraction of its height: support.core_below, ransac_support's test), and the
    margin of each against its limit, margin_<name> = (limit - value) / limit (cut_density's on object-base planes
    only, where it is checked). across [N, 2] plane coordinates, heights [N] above the plane, keep /
    support_removed / opaque / core [N] bool (core: the Gaussians the plane was chosen by), kept_heights [M] of the
    opaque kept ones, base: how low the object reaches (stages/lib/objects/support.py footprint_base)."""
    top = float(kept_heights.max())
    layer = support.layer_thickness(plane, spacing, cfg)
    density = support.cut_density(across, heights, keep, support_removed, opaque, cfg.max_layer * top,
                                  plane.thickness, spacing)
    checks = {"base_gap": float((base - layer) / top), "layer": layer / top, "cut_density": density,
              "core_below": support.core_below(heights[core], across[core], spacing, cfg)}
    limits = {"base_gap": cfg.max_base_gap, "layer": cfg.max_layer, "core_below": plane.core_below_limit(cfg),
              **({"cut_density": cfg.max_cut_density} if plane.source == "object_base" else {})}
    checks.update({f"margin_{name}": (limit - checks[name]) / limit for name, limit in limits.items()})
    log.info("support plane %s: base gap %.3f, layer %.3f of the object's height, cut density %.2f, core below "
             "%.3f", plane.source, checks["base_gap"], checks["layer"], density, checks["core_below"])
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
