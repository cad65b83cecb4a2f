"""The clustering steps of extract (stages/lib/objects/cut.py): the statistical filter and DBSCAN keeping the cluster
nearest the cameras' look-at point, the object's core of opaque Gaussians, and what the filters give back.

`removed_by` arrays [N] say why each Gaussian was removed: an index into STEPS, 0 = kept.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.contract.errors import StageError
from stages.lib.objects import pointcloud
from stages.lib.objects.cut_config import CutConfig

# Why a Gaussian was removed (index into STEPS); 0 = kept.
STEPS = ("kept", "plane", "stat", "cluster", "halo")


def pick_central_cluster(points: np.ndarray, labels: np.ndarray, centre: np.ndarray | None,
                         merge_distance: float = 0.0, rank: int = 0) -> np.ndarray:
    """Mask [N] of the DBSCAN cluster (labels [N], -1 = noise) whose points lie closest to `centre` [3]
    (None: the largest cluster), joined by every cluster that comes within `merge_distance` of it (repeatedly).
    `rank` > 0 takes the rank-th closest instead (the self-check's next candidate; an empty mask when there are
    not that many clusters).

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
        if rank >= len(cluster_ids):
            return np.zeros(len(points), dtype=bool)
        keep = labels == cluster_ids[int(np.argsort(medians, kind="stable")[rank])]
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


def central_spacing(points: np.ndarray, centre: np.ndarray | None, cfg: CutConfig) -> float:
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


@dataclass
class Core:
    """The object's core: the DBSCAN cluster of opaque Gaussians nearest the look-at point (or the largest)."""

    mask: np.ndarray  # [N] bool over all Gaussians
    spacing: float  # Gaussian spacing where it was measured (central_spacing), normalised
    eps: float  # the DBSCAN radius used (core_spacing_factor x spacing)


def object_core(points: np.ndarray, candidates: np.ndarray, look_at: np.ndarray | None, cfg: CutConfig) -> Core:
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
                 cfg: CutConfig, rank: int = 0, radius_scale: float = 1.0) -> tuple[float, int]:
    """The stat and cluster steps of a captured scene, in place on removed_by [N]: the statistical filter, then
    DBSCAN (its radius times radius_scale) keeping the cluster nearest `look_at` [3] (the rank-th nearest:
    pick_central_cluster); statistically removed Gaussians, DBSCAN noise and faint Gaussians (faint [N] bool, which
    sit out both) near the cluster come back. Returns (DBSCAN radius, Gaussians given back)."""
    alive = np.flatnonzero((removed_by == 0) & ~faint)
    kept = pointcloud.statistical_inliers(points[alive], cfg.stat_neighbours, cfg.stat_std_ratio)
    removed_by[alive[~kept]] = STEPS.index("stat")
    check_step(removed_by, "stat", cfg)

    alive = np.flatnonzero((removed_by == 0) & ~faint)
    eps = radius_scale * max(cfg.dbscan_eps, cfg.dbscan_spacing_factor * central_spacing(points[alive], look_at, cfg))
    labels = pointcloud.dbscan_labels(points[alive], eps, cfg.dbscan_min_points)
    kept = pick_central_cluster(points[alive], labels, look_at, cfg.cluster_merge_eps * eps, rank)
    if rank and not kept.any():
        raise StageError(f"extract: no cluster number {rank + 1} near the look-at point")
    removed_by[alive[~kept]] = STEPS.index("cluster")
    noise = np.zeros(len(points), dtype=bool)
    noise[alive[labels < 0]] = cfg.regrow_noise
    return eps, _faint_sit_out(points, faint, removed_by, noise, cfg.regrow_fraction * eps, cfg)


def filter_model(points: np.ndarray, faint: np.ndarray, removed_by: np.ndarray, eps: float,
                 cfg: CutConfig) -> tuple[float, int]:
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
    check_step(removed_by, "cluster", cfg)
    given_back = 0
    while True:
        regrown = regrow(points, removed_by, eps, outside & (removed_by == STEPS.index("cluster")))
        if len(regrown) == 0:
            return eps, given_back
        removed_by[regrown] = 0
        given_back += len(regrown)


def _faint_sit_out(points: np.ndarray, faint: np.ndarray, removed_by: np.ndarray, noise: np.ndarray, distance: float,
                   cfg: CutConfig) -> int:
    """Mark the faint Gaussians still in (faint [N]) as cluster-removed, check the step, then give back those
    and the `noise` [N] within `distance` of the kept ones (regrow); returns how many came back."""
    noise = noise | ((removed_by == 0) & faint)
    removed_by[(removed_by == 0) & faint] = STEPS.index("cluster")
    check_step(removed_by, "cluster", cfg)
    regrown = regrow(points, removed_by, distance, noise)
    removed_by[regrown] = 0
    return len(regrown)


def check_step(removed_by: np.ndarray, step: str, cfg: CutConfig) -> None:
    """Raise StageError if `step` removed more than `max_step_removed_fraction` of its input."""
    index = STEPS.index(step)
    step_input = int(((removed_by == 0) | (removed_by >= index)).sum())
    removed = int((removed_by == index).sum())
    if step_input == 0 or removed > cfg.max_step_removed_fraction * step_input:
        raise StageError(f"extract: the {step} step removed {removed} of {step_input} Gaussians (almost all); "
                         "the scene does not look like an object standing on a plane, or the step's thresholds "
                         "do not fit its scale")
