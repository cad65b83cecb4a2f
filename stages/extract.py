"""Stage `extract`: cut the object out of a trained Gaussian-splatting scene (paper: "Foreground
Object Extraction"), headless and automatic.

Steps, all on the Gaussian means after normalising the scene scale (median camera distance to the
cameras' look-at point = 1, or the robust spread of the means when there are no cameras):
1. plane:  RANSAC ground plane (the largest roughly horizontal plane under the look-at point; a
           camera-up "lowest dense layer" fallback for plain floors), removing the plane and all
           floaters below it;
2. stat:   Open3D statistical outlier filter;
3. cluster: DBSCAN on the opaque Gaussians, keeping the cluster closest to the look-at point (then
           statistically removed Gaussians, DBSCAN noise and faint Gaussians near the cluster come back);
4. halo:   semi-transparent Gaussians away from the opaque core, nearly invisible ones, and huge Gaussians.
"""
from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from stages import pointcloud
from stages.context import Context, StageError
from stages.gaussians.model import SH_C0
from stages.gaussians.ply import read_ply, write_ply
from stages.geometry import camera_centres, image_ups, look_at_point
from stages.records.cameras import CamerasRecord
from stages.records.extract import ExtractRecord

log = logging.getLogger(__name__)

# Why a Gaussian was removed (index into STEPS); 0 = kept.
STEPS = ("kept", "plane", "stat", "cluster", "halo")


@dataclass
class ExtractConfig:
    """Extraction parameters. Distances are in normalised units (median camera distance = 1)."""

    plane_distance: float = 0.005  # RANSAC inlier distance (authors' code: 0.05 raw COLMAP units)
    plane_iterations: int = 1000  # RANSAC iterations per candidate plane
    plane_candidates: int = 4  # planes tried (largest first) before the camera-up fallback
    plane_min_fraction: float = 0.05  # a candidate plane holds at least this fraction of the Gaussians
    plane_max_tilt_deg: float = 30.0  # max angle between a candidate's normal and the cameras' up
    plane_min_opacity: float = 0.2  # the plane is fit to Gaussians at least this opaque (faint floaters and
    #                                 never-seen Gaussians under the floor would pull the fallback layer down)
    layer_bins: int = 64  # fallback (no RANSAC plane): height bins along up over the scene's extent ...
    layer_peak_fraction: float = 0.1  # ... the lowest bin with this fraction of the fullest bin's count
    stat_neighbours: int = 50  # paper: 50
    stat_std_ratio: float = 1.0  # paper: 0.1; authors' code: 0.5 (lower = more aggressive)
    dbscan_eps: float = 0.03  # paper: 0.5 in raw COLMAP units; ours is normalised
    dbscan_min_points: int = 10  # paper: 100
    cluster_merge_eps: float = 2.0  # clusters within this many eps of the chosen one join it (object fragments)
    dbscan_spacing_factor: float = 2.0  # eps >= this x median distance to the min_points-th neighbour ...
    spacing_radius: float = 0.5  # ... among the Gaussians within this distance of the centre (0 = all)
    regrow_fraction: float = 1.5  # give back statistically removed Gaussians within this x eps of the object
    regrow_noise: bool = True  # ... and DBSCAN noise points (sparse object interior) likewise
    cluster_min_opacity: float = 0.2  # fainter Gaussians sit out the statistical filter and DBSCAN (floaters
    #                                   would set the spacing and bridge clusters); offered back like noise
    halo_opacity: float = 0.2  # Gaussians below this opacity farther than the cluster eps from opaque ones
    invisible_opacity: float = 0.02  # ... and Gaussians below this opacity anywhere: they add nothing to a render
    #                                  (faint object seeds of splat_train, e.g. in the vase's mouth)
    height_opacity: float = 0.5  # the object's height is measured on kept Gaussians at least this opaque
    huge_scale_fraction: float = 0.25  # Gaussians whose largest scale exceeds this x object height
    max_step_removed_fraction: float = 0.995  # a step removing more of its input than this fails
    min_total_removed_fraction: float = 0.1  # removing less than this in all fails (already cut out?)
    min_object_gaussians: int = 50  # fewer kept Gaussians than this fails
    up_hint: list[float] | None = None  # world up when there are no cameras (COLMAP frames: often [0, -1, 0])


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
class GroundPlane:
    """Ground plane in normalised coordinates: normal . x + offset = 0, normal towards the object."""

    normal: np.ndarray  # [3] unit
    offset: float
    source: str  # "ransac" or "camera_up_layer"
    thickness: float  # the ground layer: Gaussians lower than this above the plane are ground

    def height(self, points: np.ndarray) -> np.ndarray:
        """Signed distance [N] of points [N, 3] above the plane."""
        return points @ self.normal + self.offset


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


def find_ground_plane(points: np.ndarray, up: np.ndarray | None, cfg: ExtractConfig, seed: int,
                      cameras: np.ndarray | None = None) -> GroundPlane:
    """Ground plane of normalised points [N, 3] (look-at point at the origin), normal towards the object.

    With a camera up [3]: among the `plane_candidates` largest RANSAC planes, the roughly horizontal
    ones below the origin qualify and the highest qualifying one wins (an object on a table beats the
    floor); walls are skipped. No qualifying plane: the lowest height layer (along up) holding
    layer of points (see `_lowest_layer`). Without up: the largest plane, oriented towards the cameras
    [C, 3] (or the side holding most points).
    """
    total = len(points)
    remaining = np.arange(total)
    max_tilt = np.cos(np.deg2rad(cfg.plane_max_tilt_deg))
    best: GroundPlane | None = None
    for attempt in range(cfg.plane_candidates):
        if len(remaining) < max(3, cfg.plane_min_fraction * total):
            break
        plane, inliers = pointcloud.ransac_plane(points[remaining], cfg.plane_distance, cfg.plane_iterations,
                                                 seed + attempt)
        if inliers.sum() < cfg.plane_min_fraction * total:
            break
        normal, offset = plane[:3], float(plane[3])
        if up is None:
            side = _towards(points, normal, offset, cameras)
            return GroundPlane(normal * side, offset * side, "ransac", cfg.plane_distance)
        if normal @ up < 0:
            normal, offset = -normal, -offset
        log.debug("plane candidate %d: %d inliers, tilt %.1f deg, origin height %.3f", attempt, inliers.sum(),
                  np.rad2deg(np.arccos(min(1.0, normal @ up))), offset)
        if normal @ up >= max_tilt and offset > cfg.plane_distance and (best is None or offset < best.offset):
            best = GroundPlane(normal, offset, "ransac", cfg.plane_distance)
        remaining = remaining[~inliers]
    if best is not None or up is None:
        if best is None:
            raise StageError("extract: no ground plane found (RANSAC found no plane holding "
                             f"{cfg.plane_min_fraction:.0%} of the Gaussians and there are no cameras to fall back on)")
        return best
    return _lowest_layer(points, up, cfg)


def _towards(points: np.ndarray, normal: np.ndarray, offset: float, cameras: np.ndarray | None) -> float:
    """+1 or -1: the plane side holding the cameras [C, 3], else the side holding most points [N, 3]."""
    reference = cameras if cameras is not None and len(cameras) else points
    return 1.0 if np.median(reference @ normal + offset) >= 0 else -1.0


def _lowest_layer(points: np.ndarray, up: np.ndarray, cfg: ExtractConfig) -> GroundPlane:
    """Horizontal plane (normal = up) at the bottom of the lowest dense height layer of points [N, 3].

    Heights along up between their 0.1 and 99.9 percentiles go into `layer_bins` bins; the lowest bin
    holding at least `layer_peak_fraction` of the fullest bin's count is the layer (scale-free, and
    sparse floaters below the floor never qualify).
    """
    heights = points @ up  # [N]
    low, high = np.percentile(heights, [0.1, 99.9])
    counts, edges = np.histogram(heights, bins=cfg.layer_bins, range=(low, high))
    dense = np.flatnonzero(counts >= cfg.layer_peak_fraction * counts.max())
    if high <= low or len(dense) == 0:
        raise StageError("extract: no ground plane: RANSAC found no horizontal plane under the object and the "
                         "Gaussians have no height extent along the up direction for the camera-up fallback")
    log.info("no RANSAC ground plane; falling back to the lowest dense layer along the up direction")
    bin_width = float(edges[1] - edges[0])  # the layer is one bin thick: all of it is ground
    return GroundPlane(up.copy(), -float(edges[dense[0]]), "camera_up_layer", max(cfg.plane_distance, bin_width))


def pick_central_cluster(points: np.ndarray, labels: np.ndarray, centre: np.ndarray,
                         merge_distance: float = 0.0) -> np.ndarray:
    """Mask [N] of the DBSCAN cluster (labels [N], -1 = noise) whose points lie closest to `centre` [3],
    joined by every cluster that comes within `merge_distance` of it (repeatedly).

    Closeness is the median point distance, so a ring of halo around the object never beats the object.
    Joining keeps an object that the filters split into pieces whole: when a small fragment of its side
    happens to lie nearest the centre, the body next to it joins instead of being thrown away.
    """
    cluster_ids = np.unique(labels[labels >= 0])
    if len(cluster_ids) == 0:
        return np.zeros(len(points), dtype=bool)
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


def central_spacing(points: np.ndarray, centre: np.ndarray, cfg: ExtractConfig) -> float:
    """Typical spacing of the Gaussians near `centre` [3] (points [N, 3] normalised): the median distance
    to the dbscan_min_points-th neighbour among those within cfg.spacing_radius (all when too few).

    Measured near the object, not over the whole scene: a densified background (walls, floaters) is
    sparse and would inflate DBSCAN's radius until the object merges with its surroundings.
    """
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


def extract_object(means: np.ndarray, opacities: np.ndarray, scales: np.ndarray, cfg: ExtractConfig,
                   viewmats: np.ndarray | None = None, seed: int = 0) -> Extraction:
    """Separate the object's Gaussians from the scene.

    means [N, 3] model units; opacities [N] in [0, 1]; scales [N, 3] model units (not log);
    viewmats [C, 4, 4] world-to-camera (OpenCV) or None. Raises StageError on degenerate input or
    when a step removes (almost) everything or, in all, (almost) nothing.
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
    cameras = (rig.centres - centre) / scale if rig is not None else None
    up = rig.up() if rig is not None else _unit_or_none(cfg.up_hint)

    removed_by = np.zeros(total, dtype=np.int64)
    opaque = opacities >= cfg.plane_min_opacity  # [N]
    plane = find_ground_plane(points[opaque] if opaque.sum() > cfg.stat_neighbours else points, up, cfg, seed, cameras)
    heights = plane.height(points)  # [N]
    removed_by[heights < plane.thickness] = STEPS.index("plane")
    _check_step(removed_by, "plane", cfg)

    faint = opacities < cfg.cluster_min_opacity  # [N] sit out the statistical filter and DBSCAN
    alive = np.flatnonzero((removed_by == 0) & ~faint)
    kept = pointcloud.statistical_inliers(points[alive], cfg.stat_neighbours, cfg.stat_std_ratio)
    removed_by[alive[~kept]] = STEPS.index("stat")
    _check_step(removed_by, "stat", cfg)

    alive = np.flatnonzero((removed_by == 0) & ~faint)
    cluster_centre = np.zeros(3) if rig is not None and rig.look_at is not None else points[alive].mean(axis=0)
    eps = max(cfg.dbscan_eps, cfg.dbscan_spacing_factor * central_spacing(points[alive], cluster_centre, cfg))
    labels = pointcloud.dbscan_labels(points[alive], eps, cfg.dbscan_min_points)
    kept = pick_central_cluster(points[alive], labels, cluster_centre, cfg.cluster_merge_eps * eps)
    removed_by[alive[~kept]] = STEPS.index("cluster")
    noise = np.zeros(total, dtype=bool)
    noise[alive[labels < 0]] = cfg.regrow_noise
    noise |= (removed_by == 0) & faint  # faint Gaussians near the object come back below, like noise
    removed_by[(removed_by == 0) & faint] = STEPS.index("cluster")
    _check_step(removed_by, "cluster", cfg)
    regrown = regrow(points, removed_by, cfg.regrow_fraction * eps, noise)
    removed_by[regrown] = 0
    max_scales = np.asarray(scales, dtype=np.float64).max(axis=1) / scale  # [N] normalised

    alive = np.flatnonzero(removed_by == 0)
    object_height = float(heights[alive].max())
    halo = halo_mask(points[alive], opacities[alive], max_scales[alive], object_height, eps, cfg)
    removed_by[alive[halo]] = STEPS.index("halo")
    _check_step(removed_by, "halo", cfg)

    keep = removed_by == 0
    if keep.sum() < cfg.min_object_gaussians:
        raise StageError(f"extract: only {keep.sum()} object Gaussians left (need {cfg.min_object_gaussians}); "
                         "the filters are too aggressive for this scene (raise stat_std_ratio or dbscan_eps)")
    removed_fraction = 1.0 - keep.mean()
    if removed_fraction < cfg.min_total_removed_fraction:
        raise StageError(f"extract: removed only {removed_fraction:.2%} of the Gaussians (less than "
                         f"min_total_removed_fraction={cfg.min_total_removed_fraction}); no ground or background "
                         "was found to cut away. Is the scene already cut out?")

    normal_model = plane.normal  # scaling and translating leave directions unchanged
    solid = keep & (opacities >= cfg.height_opacity)  # the height is the opaque body's:
    kept_heights = heights[solid if solid.any() else keep]  # faint haze on top would make it taller
    centroid = points[keep].mean(axis=0)
    base_point = centroid - plane.height(centroid[None])[0] * plane.normal
    counts = {"total": total, "given_back": len(regrown),  # statistically removed, DBSCAN noise and faint
              **{f"removed_{name}": int((removed_by == i).sum()) for i, name in enumerate(STEPS) if i},
              "removed_below_plane": int((heights < -plane.thickness).sum()), "kept": int(keep.sum())}
    return Extraction(removed_by=removed_by, normal=normal_model, base_point=base_point * scale + centre,
                      height=float(kept_heights.max()) * scale, scene_scale=scale, centre=centre,
                      plane_source=plane.source, dbscan_eps=eps, counts=counts)


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


def draw_filtering(path: Path, means: np.ndarray, colors: np.ndarray | None, extraction: Extraction,
                   max_points: int = 30000, seed: int = 0) -> None:
    """Three panels like the paper's filtering figure (plane, statistical, cluster + halo filter).

    Each panel shows the Gaussians entering that step seen obliquely from the side (the plane's
    normal is up), removed ones in red. means [N, 3]; colors [N, 3] in [0, 1] or None (grey).
    Headless (matplotlib Agg).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rng = np.random.default_rng(seed)
    shown = np.sort(rng.permutation(len(means))[:max_points])
    normal = extraction.normal
    across = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    across /= np.linalg.norm(across)
    depth_axis = np.cross(normal, across)
    relative = (means[shown] - extraction.base_point) / extraction.scene_scale  # [M, 3]
    elevation = np.deg2rad(20.0)
    u = relative @ across
    v = (relative @ normal) * np.cos(elevation) - (relative @ depth_axis) * np.sin(elevation)
    base_colors = np.full((len(shown), 3), 0.5) if colors is None else np.clip(colors[shown], 0, 1)
    removed_by = extraction.removed_by[shown]
    panels = [("plane filter", [STEPS.index("plane")]), ("statistical filter", [STEPS.index("stat")]),
              ("cluster + halo filter", [STEPS.index("cluster"), STEPS.index("halo")])]
    figure, axes = plt.subplots(1, 3, figsize=(15, 5), dpi=100)
    for axis, (title, steps) in zip(axes, panels):
        entering = (removed_by == 0) | (removed_by >= steps[0])
        red = np.isin(removed_by, steps)
        axis.scatter(u[entering & ~red], v[entering & ~red], s=1, c=base_colors[entering & ~red], linewidths=0)
        axis.scatter(u[red], v[red], s=1, c="red", linewidths=0)
        axis.set_title(f"{title}: {int(red.sum())} of {int(entering.sum())} removed (shown)")
        axis.set_aspect("equal")
        axis.set_xticks([])
        axis.set_yticks([])
    figure.tight_layout()
    figure.savefig(path)
    plt.close(figure)


def run(ctx: Context) -> dict:
    """Read `splat`/scene.ply (+ cameras.json), write object.ply, extract.json and filtering.png."""
    cfg = ExtractConfig(**ctx.params)
    splat = Path(ctx.inputs["splat"])
    scene_path = splat / "scene.ply"
    if not scene_path.exists():
        raise StageError(f"extract[{ctx.item}]: {scene_path} not found; run splat_train first")
    gaussians = read_ply(scene_path)
    means = gaussians.means.detach().cpu().numpy()  # [N, 3]
    opacities = gaussians.opacities.detach().cpu().numpy()  # [N]
    scales = gaussians.scales.detach().cpu().numpy()  # [N, 3]
    viewmats = CamerasRecord.read(splat).viewmats if CamerasRecord.exists(splat) else None
    if viewmats is None:
        ctx.log.warning("extract[%s]: no cameras.json in %s; normalising by the spread of the means", ctx.item, splat)
    try:
        extraction = extract_object(means, opacities, scales, cfg, viewmats, seed=ctx.seed)
    except StageError as error:
        raise StageError(f"extract[{ctx.item}] ({scene_path}): {error}") from error

    keep = np.flatnonzero(extraction.keep)
    write_ply(ctx.out / "object.ply", gaussians.subset(keep))
    ExtractRecord(extraction.normal, extraction.base_point, extraction.height, extraction.counts,
                  extraction.scene_scale, extraction.centre, extraction.plane_source, extraction.dbscan_eps,
                  asdict(cfg)).write(ctx.out)
    colors = 0.5 + SH_C0 * gaussians.sh[:, 0].detach().cpu().numpy()  # [N, 3]
    draw_filtering(ctx.out / "filtering.png", means, colors, extraction, seed=ctx.seed)
    ctx.log.info("extract[%s]: kept %d of %d Gaussians (plane: %s), height %.4g", ctx.item, len(keep),
                 len(means), extraction.plane_source, extraction.height)
    return {"kept": len(keep), "total": len(means), "height": extraction.height,
            "plane_source": extraction.plane_source, **{k: v for k, v in extraction.counts.items()}}
