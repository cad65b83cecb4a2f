"""The surface a captured object stands on, in a splat's normalised frame (the cameras' look-at point, or the
robust centre of the Gaussians, at the origin; median camera distance 1): where it is, which Gaussians are
support, and whether the cut left the object whole.

The plane comes from one of two sources:
- "ransac": the highest roughly horizontal RANSAC plane under the origin that the object's base rests on
  (textured floors, tables and mats, as the paper does), skipping planes that cut through the object (another
  surface at the height of its middle), and smaller planes over the largest one that the object's base reaches
  under (a plane through a fuzzy floor's upper layer);
- "object_base": a plane across the up direction at the base of the object's core (the central cluster of
  opaque Gaussians), when RANSAC finds no such plane, or only one the object does not rest on. A plain white
  sheet or table gives few, scattered Gaussians that no thin plane holds (the real plush dog's case).

Support is every Gaussian below the plane's thickness. On an object-base plane, whose support Gaussians are
scattered around it, also the flat Gaussians lying on the plane in a thin contact layer above it (a sheet's
discs reach out from under the object's feet and would frame it), those whose extent reaches well under
the plane (they would hang below the object's base), and, once the object is known, what is left in the
contact layer beside its footprint (a sheet's edge running off from its feet). A RANSAC plane is crisp: its
layer is its thickness.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from stages.contract.errors import StageError
from stages.lib.objects import pointcloud

log = logging.getLogger(__name__)

GAP_PERCENTILE = 1.0  # the base of the object's body: this percentile of its opaque heights
BOTTOM_SIGMAS = 2.0  # a Gaussian's bottom: its centre less this many standard deviations along the normal
BASE_CELLS = 5  # how low the object reaches: the lowest bottom of this many cells of its footprint (not one stray)
FOOTPRINT_CELLS = 12  # ... cells this many times smaller than the footprint's width
ADVICE = ("film the object on a textured mat so that its support plane is found, or give its up direction "
          "(objects[].up in the data config, or extract.up_hint)")


@dataclass
class SupportConfig:
    """How the support plane is found and checked. Distances in normalised units (median camera distance 1)."""

    plane_distance: float = 0.005  # RANSAC inlier distance (authors' code: 0.05 raw COLMAP units)
    plane_iterations: int = 1000  # RANSAC iterations per candidate plane
    plane_candidates: int = 4  # planes tried (largest first) before the object-base plane
    plane_min_fraction: float = 0.05  # a candidate plane holds at least this fraction of the Gaussians
    plane_max_tilt_deg: float = 30.0  # max angle between a candidate's normal and the up direction
    plane_min_opacity: float = 0.2  # planes are fit to Gaussians at least this opaque (faint floaters and
    #                                 never-seen Gaussians under the floor would pull the plane down)
    base_percentile: float = 1.0  # the object's base: this percentile of the heights of its core's solid Gaussians
    core_spacing_factor: float = 3.0  # the core is clustered with this x the spacing near the centre: wider
    #                                   than the cluster step's, so that sparser parts (a plant's pot) join it
    contact_layer: float = 2.0  # flat Gaussians within this x the Gaussian spacing above the plane are support
    contact_flatness: float = 0.4  # ... flat: extent along the normal below this x their largest extent
    below_reach: float = 1.0  # Gaussians whose 2-sigma extent reaches more than this x the spacing under the
    #                           plane hang below the object's base (seen from eye level): support too
    footprint_reach: float = 1.5  # kept Gaussians in the contact layer farther than this x the spacing (across
    #                               the normal) from the object's body above it are the support's edge
    base_band: float = 0.25  # the object's lowest part, this fraction of its height above its kept base: what
    #                          the stat and cluster steps dropped under it, down to the removed layer, comes back
    max_base_gap: float = 0.05  # check: the object's base lies at most this x its height above the plane
    max_core_below: float = 0.25  # a RANSAC plane with the core's base more than this x its height under it cuts
    #                               through the object (core_below: what lies under the object's body; a thick
    #                               floor's slabs that join the core reach 2-12 % there)
    max_core_below_smaller: float = 0.08  # ... the limit for a plane other than the largest level one: a table or
    #                                       a mat holds the object's base (0-6.5 % on 75 captures), a plane through a
    #                                       fuzzy floor's upper layer, 0.7-5.5 cm over the floor, cuts it off (10-23 %)
    max_layer: float = 0.15  # check: the removed layer is at most this x the object's height thick
    max_cut_density: float = 0.5  # check (object-base planes): opaque Gaussians removed just under the object,
    #                               against those kept just above the plane (an object cut through continues
    #                               below it). A RANSAC plane is a surface the cameras saw; under it an
    #                               under-trained floor's noise reads as 0.8-2.7 (the smoke run's splats)


@dataclass
class GroundPlane:
    """Support plane in normalised coordinates: normal . x + offset = 0, normal towards the object."""

    normal: np.ndarray  # [3] unit
    offset: float
    source: str  # "ransac" or "object_base"
    thickness: float  # Gaussians lower than this above the plane are support
    smaller: bool = False  # a RANSAC plane other than the largest level one (ransac_support)

    def core_below_limit(self, cfg: SupportConfig) -> float:
        """How far the object's core may reach under this plane (SupportConfig.max_core_below and _smaller)."""
        return cfg.max_core_below_smaller if self.smaller else cfg.max_core_below

    def height(self, points: np.ndarray) -> np.ndarray:
        """Signed distance [N] of points [N, 3] above the plane."""
        return points @ self.normal + self.offset


def ransac_planes(points: np.ndarray, cfg: SupportConfig, seed: int) -> list[tuple[np.ndarray, float]]:
    """Up to cfg.plane_candidates planes (unit normal [3], offset), largest first, each holding at least
    cfg.plane_min_fraction of the points [N, 3]; each is fit to what the earlier ones left."""
    total, remaining, planes = len(points), np.arange(len(points)), []
    for attempt in range(cfg.plane_candidates):
        if len(remaining) < max(3, cfg.plane_min_fraction * total):
            break
        plane, inliers = pointcloud.ransac_plane(points[remaining], cfg.plane_distance, cfg.plane_iterations,
                                                 seed + attempt)
        if inliers.sum() < cfg.plane_min_fraction * total:
            break
        planes.append((plane[:3], float(plane[3])))
        remaining = remaining[~inliers]
    return planes


def core_base_and_top(heights: np.ndarray, cfg: SupportConfig) -> tuple[float, float]:
    """The base and top of the object's core from its heights [M] above a plane (cfg.base_percentile and its
    complement: a few stray Gaussians decide neither)."""
    base, top = np.percentile(heights, [cfg.base_percentile, 100 - cfg.base_percentile])
    return float(base), float(top)


def core_below(heights: np.ndarray, across: np.ndarray, spacing: float, cfg: SupportConfig) -> float:
    """How far the object's core reaches under a plane, as a fraction of its height (0 when it rests on it): the
    base and top (core_base_and_top) of its Gaussians on or above the plane and of those under it that lie within
    `spacing`, across the normal, of its body (the Gaussians higher than cfg.max_layer x its height). What lies
    under the body continues the object; a floor slab joining the core spreads around it instead (under-trained
    splats' fuzzy floors reach 15-30 % of the object's height under the plane, almost all of it outside the
    object's footprint). heights [M] above the plane and across [M, 2] plane coordinates (plane_coordinates) of
    the core's Gaussians."""
    above = heights >= 0
    if not above.any():
        return 1.0
    top = float(np.percentile(heights[above], 100 - cfg.base_percentile))
    body = heights > cfg.max_layer * top
    counted = above.copy()
    under = np.flatnonzero(~above)
    if len(under) and body.any():
        counted[under] = pointcloud.nearest_distance(across[under], across[body]) <= spacing
    base, top = core_base_and_top(heights[counted], cfg)
    return max(-base, 0.0) / max(top - base, 1e-12)


def ransac_support(planes: list[tuple[np.ndarray, float]], up: np.ndarray, core: np.ndarray, spacing: float,
                   cfg: SupportConfig) -> GroundPlane | None:
    """The highest plane of `planes` (largest first) within cfg.plane_max_tilt_deg of `up` [3] and below the origin
    (an object on a table beats the floor; walls are skipped) that does not cut through the object: its core [M, 3]
    reaches at most cfg.max_core_below of its height under the largest such plane, the surface the capture stands
    on, whose fuzz joins the core, and at most cfg.max_core_below_smaller under a smaller one (core_below, with the
    core's Gaussian spacing): a table or a mat holds the object's base, while a plane through a fuzzy floor's upper
    layer cuts the base off. None when none qualifies."""
    best, largest = None, True
    for normal, offset in planes:
        if normal @ up < 0:
            normal, offset = -normal, -offset
        tilted = normal @ up < np.cos(np.deg2rad(cfg.plane_max_tilt_deg))
        log.debug("plane candidate: tilt %.1f deg, origin height %.3f", np.rad2deg(np.arccos(min(1.0, normal @ up))),
                  offset)
        if tilted or offset <= cfg.plane_distance:
            continue
        plane = GroundPlane(normal, offset, "ransac", cfg.plane_distance, smaller=not largest)
        largest = False
        if best is not None and offset >= best.offset:
            continue
        below = core_below(core @ normal + offset, plane_coordinates(core, normal), spacing, cfg)
        if below > plane.core_below_limit(cfg):
            log.info("a RANSAC plane %.3f under the origin cuts through the object (%.0f %% of its core's height "
                     "below it): not its support", offset, 100 * below)
            continue
        best = plane
    return best


def estimated_up(planes: list[tuple[np.ndarray, float]], points: np.ndarray, distance: float) -> np.ndarray:
    """Up [3] from the largest plane of `planes`, pointing to the side holding most of the points [N, 3]
    farther than `distance` from it (the object standing on its support). StageError when there is no plane."""
    if not planes:
        raise StageError("extract: no up direction: the model has no cameras and RANSAC found no support plane "
                         f"holding a share of its Gaussians; {ADVICE}")
    normal, offset = planes[0]
    heights = points @ normal + offset  # [N]
    off = heights[np.abs(heights) > distance]
    return normal if len(off) == 0 or np.median(off) >= 0 else -normal


def object_base_plane(core: np.ndarray, normal: np.ndarray, cfg: SupportConfig) -> GroundPlane:
    """Plane across `normal` [3] at the base (cfg.base_percentile of the heights) of the object's core [M, 3]."""
    base = float(np.percentile(core @ normal, cfg.base_percentile))
    return GroundPlane(normal.copy(), -base, "object_base", cfg.plane_distance)


def choose_plane(ransac: GroundPlane | None, core: np.ndarray, up: np.ndarray, cfg: SupportConfig) -> GroundPlane:
    """The RANSAC plane when the object's core [M, 3] rests on it (base within cfg.max_base_gap of the core's
    height), else the object-base plane across `up` [3]."""
    if ransac is not None:
        base, top = core_base_and_top(ransac.height(core), cfg)
        if base <= cfg.max_base_gap * (top - base):
            return ransac
        log.info("the RANSAC plane lies %.3f under the object's base (%.0f %% of its height): not its support; "
                 "using the object's base", base, 100 * base / max(top - base, 1e-12))
    else:
        log.info("no RANSAC support plane under the object; using the object's base")
    return object_base_plane(core, up, cfg)


def normal_extents(normal: np.ndarray, scales: np.ndarray, rotations: np.ndarray | None) -> np.ndarray:
    """Standard deviation [N] of each Gaussian along `normal` [3]: scales [N, 3] (linear), rotations
    [N, 3, 3] local-to-world (None: axis-aligned)."""
    local = normal[None] if rotations is None else np.einsum("nji,j->ni", rotations, normal)  # [N, 3] R^T n
    return np.linalg.norm(local * scales, axis=1)


def contact_layer(heights: np.ndarray, along_normal: np.ndarray, largest: np.ndarray, plane: GroundPlane,
                  spacing: float, cfg: SupportConfig) -> np.ndarray:
    """Mask [N] of flat Gaussians lying on the plane: heights [N] within the contact layer above the plane's
    thickness, extent along the normal (along_normal [N]) below cfg.contact_flatness x their largest extent
    (largest [N])."""
    return (heights >= plane.thickness) & (heights < layer_thickness(plane, spacing, cfg)) & (
        along_normal < cfg.contact_flatness * largest)


def reaching_below(heights: np.ndarray, along_normal: np.ndarray, spacing: float, cfg: SupportConfig) -> np.ndarray:
    """Mask [N] of Gaussians whose 2-sigma extent along the normal (along_normal [N]) reaches more than
    cfg.below_reach x spacing under the plane (heights [N])."""
    return 2.0 * along_normal - heights > cfg.below_reach * spacing


def support_mask(plane: GroundPlane, heights: np.ndarray, along_normal: np.ndarray, largest: np.ndarray,
                 spacing: float, cfg: SupportConfig) -> tuple[np.ndarray, dict[str, int]]:
    """Mask [N] of support Gaussians (see the module doc) and how many each rule added: heights [N] above
    the plane, along_normal [N] and largest [N] the Gaussians' extents along the normal and overall."""
    below = heights < plane.thickness
    flat = hanging = np.zeros_like(below)
    if plane.source == "object_base":
        flat = contact_layer(heights, along_normal, largest, plane, spacing, cfg) & ~below
        hanging = reaching_below(heights, along_normal, spacing, cfg) & ~below & ~flat
    return below | flat | hanging, {"removed_flat_contact": int(flat.sum()), "removed_hanging": int(hanging.sum())}


def beyond_footprint(across: np.ndarray, heights: np.ndarray, kept: np.ndarray, opaque: np.ndarray,
                     plane: GroundPlane, spacing: float, cfg: SupportConfig) -> np.ndarray:
    """Mask [N] of kept Gaussians in the contact layer of an object-base plane lying farther than
    cfg.footprint_reach x spacing from the object's footprint: the kept opaque Gaussians above the layer,
    across the normal. across [N, 2] plane coordinates; heights [N]; kept, opaque [N] bool."""
    mask = np.zeros(len(heights), dtype=bool)
    top = layer_thickness(plane, spacing, cfg)
    low, body = kept & (heights < top), kept & opaque & (heights >= top)
    if plane.source != "object_base" or not low.any() or not body.any():
        return mask
    mask[low] = pointcloud.nearest_distance(across[low], across[body]) > cfg.footprint_reach * spacing
    return mask


def layer_thickness(plane: GroundPlane, spacing: float, cfg: SupportConfig) -> float:
    """How far above the plane support is removed: its thickness, and the contact layer on an object-base plane."""
    return plane.thickness + (cfg.contact_layer * spacing if plane.source == "object_base" else 0.0)


def plane_coordinates(points: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Coordinates [N, 2] of points [N, 3] in the plane across the unit `normal` [3]."""
    basis = np.linalg.svd(normal[None])[2][1:]  # [2, 3] orthonormal in-plane axes
    return points @ basis.T


def cut_density(across: np.ndarray, heights: np.ndarray, kept: np.ndarray, support: np.ndarray,
                opaque: np.ndarray, band: float, thickness: float, reach: float) -> float:
    """Opaque support Gaussians in the band `band` under the plane (below its own layer, `thickness`) and
    within `reach` across the normal of the object's bottom, per opaque object Gaussian in the band above the
    plane (its bottom). across [N, 2]: plane coordinates (plane_coordinates); heights [N]; kept, support,
    opaque [N] bool.

    A plane under the object has little below the object's bottom outline: a trained splat has no Gaussians
    where no camera sees, a plain sheet only scattered ones (well under 1). A plane through the object has the
    object's own surface continuing below it (about 1).
    """
    bottom = kept & opaque & (heights >= 0) & (heights < band)
    below = support & opaque & (heights < -thickness) & (heights >= -band)
    if not bottom.any() or not below.any():
        return 0.0
    under = pointcloud.nearest_distance(across[below], across[bottom]) <= reach
    return float(under.sum() / bottom.sum())


def under_object(across: np.ndarray, heights: np.ndarray, removed_by_filters: np.ndarray, kept: np.ndarray,
                 opaque: np.ndarray, layer: float, reach: float, cfg: SupportConfig) -> np.ndarray:
    """Mask [N] of the Gaussians the statistical filter or DBSCAN removed (removed_by_filters [N] bool) that lie
    between the removed layer (`layer` above the plane) and the top of the object's lowest part, inside that
    part's footprint across the normal (its outline, grown by `reach`): the object stands on the plane, so what
    lies under it belongs to it. A plant pot's or a vase's bottom is seen by few cameras and trained into few, large
    Gaussians, which the filters, made for the densely seen body, leave out (sample captures of other seeds: the pot's
    lowest 15 %). across [N, 2] plane coordinates; heights [N] above the plane; kept, opaque [N] bool."""
    body = kept & opaque & (heights >= layer)
    mask = np.zeros(len(heights), dtype=bool)
    if not body.any():
        return mask
    base = np.percentile(heights[body], GAP_PERCENTILE)
    lowest = body & (heights < base + cfg.base_band * (heights[body].max() - base))  # the object's lowest part
    candidates = np.flatnonzero(removed_by_filters & (heights >= layer) & (heights < heights[lowest].max()))
    if len(candidates):
        mask[candidates] = pointcloud.inside_footprint(across[candidates], across[lowest], reach)
    return mask


def over_base(across: np.ndarray, heights: np.ndarray, candidates: np.ndarray, body: np.ndarray) -> np.ndarray:
    """Mask [M] of the candidates (indices [M]) that lie over the footprint of the object's solid body (indices
    [B]) on the support plane and below the body's median height: its base. A pot tapering to its bottom, seen
    by few cameras at grazing angles, is trained into few large, semi-transparent Gaussians there, far from the
    solid ones and coloured like the floor beside it; the support-plane step has removed what lies under the
    object, so they belong to it. across [N, 2] plane coordinates (plane_coordinates), heights [N] above the
    plane."""
    if len(candidates) == 0 or len(body) == 0:
        return np.zeros(len(candidates), dtype=bool)
    return pointcloud.inside_footprint(across[candidates], across[body], 0.0) & (
        heights[candidates] < np.median(heights[body]))


def footprint_base(across: np.ndarray, bottoms: np.ndarray) -> float:
    """How low an object reaches over its footprint: across [M, 2] plane coordinates and bottoms [M] (heights
    less BOTTOM_SIGMAS standard deviations along the normal) of its opaque Gaussians, binned in square cells
    FOOTPRINT_CELLS times smaller than the footprint's width (its 1-99 % range across the normal); the height
    that BASE_CELLS cells reach down to (a single stray Gaussian does not set it). A
    measure of the object's shape, not of its Gaussians' density: a pot's bottom, seen by few cameras and trained
    into few large Gaussians, reaches the plane though almost all the Gaussians are leaves high above."""
    low, high = np.percentile(across, [1.0, 99.0], axis=0)  # [2], [2]
    cell = max(float((high - low).max()) / FOOTPRINT_CELLS, 1e-12)
    cells = np.floor(across / cell).astype(np.int64)  # [M, 2]
    _, index = np.unique(cells, axis=0, return_inverse=True)
    lowest = np.full(int(index.max()) + 1, np.inf)
    np.minimum.at(lowest, index.ravel(), bottoms)
    return float(np.sort(lowest)[min(BASE_CELLS, len(lowest)) - 1])


def check_support(plane: GroundPlane, base: float, top: float, layer: float, density: float,
                  cfg: SupportConfig) -> None:
    """StageError naming the step and the fix when the cut went wrong: the object floats above the removed
    layer, the removed layer is thick against the object, or an object-base plane cut through the object.
    base: how low the kept object reaches above the plane (footprint_base); top: the object's height; layer:
    the removed layer's thickness above the plane (layer_thickness)."""
    where = f"the support plane ({plane.source})"
    if base - layer > cfg.max_base_gap * top:
        raise StageError(f"extract: the object's base lies {(base - layer) / top:.0%} of its height above the layer "
                         f"removed with {where}: the plane is not what it stands on (more than "
                         f"extract.max_base_gap={cfg.max_base_gap}); {ADVICE}")
    if layer > cfg.max_layer * top:
        raise StageError(f"extract: the plane step removed a layer {layer / top:.0%} of the object's height thick "
                         f"above {where} (more than extract.max_layer={cfg.max_layer}): it would cut the object's "
                         f"base off; lower extract.contact_layer or extract.plane_distance, or {ADVICE}")
    if plane.source == "object_base" and density > cfg.max_cut_density:
        raise StageError(f"extract: the plane step cut into the object: under its base, {where} removed "
                         f"{density:.2f} opaque Gaussians per one kept just above it (more than "
                         f"extract.max_cut_density={cfg.max_cut_density}), so the object continues below the "
                         f"plane; {ADVICE}")
