"""Point-cloud helpers on numpy arrays: plane RANSAC (seeded numpy), statistical filter and DBSCAN (Open3D).

All functions take float arrays of 3D points `[N, 3]` and return numpy arrays; none opens a window.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import Delaunay, QhullError, cKDTree


def _cloud(points: np.ndarray):
    """Wrap points [N, 3] in an Open3D point cloud (float64 copy); Open3D loads here, at first use (2 s)."""
    import open3d as o3d

    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64))
    return cloud


def ransac_plane(points: np.ndarray, distance: float, iterations: int, seed: int,
                 refine_steps: int = 5, chunk: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Largest plane through `points` [N, 3] by seeded RANSAC, then refit by least squares on its inliers
    until the inlier set is stable (a few steps at most).

    Deterministic for a given seed (Open3D's multi-threaded `segment_plane` returned different planes for
    the same input and seed, up to 6 degrees apart on a trained splat). Hypotheses are scored in chunks of
    `chunk` planes ([N, chunk] distances at a time); ties keep the first hypothesis.
    Returns (plane [4] as (a, b, c, d) with unit normal (a, b, c) and a*x + b*y + c*z + d = 0,
    inlier mask [N] bool: points within `distance` of the refitted plane).
    """
    points = np.asarray(points, dtype=np.float64)  # [N, 3]
    if len(points) < 3:
        raise ValueError(f"plane RANSAC needs at least 3 points, got {len(points)}")
    triples = points[np.random.default_rng(seed).integers(0, len(points), size=(max(1, iterations), 3))]  # [I, 3, 3]
    normals = np.cross(triples[:, 1] - triples[:, 0], triples[:, 2] - triples[:, 0])  # [I, 3]
    lengths = np.linalg.norm(normals, axis=1)  # [I]
    valid = lengths > 1e-12 * max(1.0, float(np.abs(points).max()) ** 2)
    if not valid.any():
        raise ValueError(f"plane RANSAC: all {len(points)} points are (nearly) collinear")
    normals = normals[valid] / lengths[valid, None]
    offsets = -np.einsum("ij,ij->i", normals, triples[valid, 0])  # [I]
    counts = np.concatenate([(np.abs(points @ normals[i:i + chunk].T + offsets[i:i + chunk]) < distance).sum(axis=0)
                             for i in range(0, len(normals), chunk)])  # [I]
    best = int(np.argmax(counts))
    normal, offset = normals[best], float(offsets[best])
    inliers = np.abs(points @ normal + offset) < distance  # [N]
    for _ in range(refine_steps):
        if inliers.sum() < 3:
            break
        refit, refit_offset = fit_plane_lstsq(points[inliers])
        if refit @ normal < 0:  # keep the hypothesis' orientation
            refit, refit_offset = -refit, -refit_offset
        normal, offset = refit, refit_offset
        refined = np.abs(points @ normal + offset) < distance
        if np.array_equal(refined, inliers):
            break
        inliers = refined
    return np.concatenate([normal, [offset]]), inliers


def fit_plane_lstsq(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Total-least-squares plane through points [N, 3]: (unit normal [3], offset d with n.x + d = 0)."""
    centroid = points.mean(axis=0)  # [3]
    _, _, vt = np.linalg.svd(points - centroid, full_matrices=False)
    normal = vt[-1] / np.linalg.norm(vt[-1])  # [3]
    return normal, float(-normal @ centroid)


def statistical_inliers(points: np.ndarray, neighbours: int, std_ratio: float) -> np.ndarray:
    """Mask [N] of points kept by Open3D's statistical outlier filter.

    A point is dropped when its mean distance to its `neighbours` nearest neighbours exceeds the
    cloud-wide mean of that quantity by more than `std_ratio` standard deviations.
    """
    keep = np.zeros(len(points), dtype=bool)
    if len(points) <= neighbours:
        return ~keep
    _, index = _cloud(points).remove_statistical_outlier(int(neighbours), float(std_ratio))
    keep[np.asarray(index, dtype=np.int64)] = True
    return keep


def dbscan_labels(points: np.ndarray, eps: float, min_points: int) -> np.ndarray:
    """DBSCAN cluster labels [N] int (Open3D `cluster_dbscan`); -1 marks noise."""
    if len(points) == 0:
        return np.zeros(0, dtype=np.int64)
    labels = _cloud(points).cluster_dbscan(float(eps), int(min_points), print_progress=False)
    return np.asarray(labels, dtype=np.int64)


def nearest_distance(queries: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Distance [M] from each query [M, 3] to its nearest point in `points` [N, 3] (inf if N == 0)."""
    if len(points) == 0:
        return np.full(len(queries), np.inf)
    distance, _ = cKDTree(points).query(queries, k=1)
    return np.asarray(distance, dtype=np.float64)


def neighbour_spacing(points: np.ndarray, neighbours: int, percentile: float = 50.0) -> float:
    """Distance from a point of `points` [N, 3] to its `neighbours`-th nearest neighbour, at `percentile` over
    the points (median by default; 0 if N <= k)."""
    if len(points) <= neighbours:
        return 0.0
    distance, _ = cKDTree(points).query(points, k=neighbours + 1)
    return float(np.percentile(distance[:, -1], percentile))


def inside_footprint(queries: np.ndarray, outline: np.ndarray, reach: float) -> np.ndarray:
    """Mask [Q] of 2-D points queries [Q, 2] inside the convex hull of outline [P, 2] or within `reach` of one of
    its points (a ring of points has its inside in the footprint, unlike a nearest-point test)."""
    near = nearest_distance(queries, outline) <= reach
    try:
        return near | (Delaunay(outline).find_simplex(queries) >= 0)
    except (QhullError, ValueError):  # fewer than 3 points, or all on a line: no area
        return near
