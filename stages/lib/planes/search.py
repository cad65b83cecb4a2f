"""Horizontal surfaces of a depth map where an object can stand (the planes stage reads and writes around it).

The paper's "Object Placement": depth -> camera-frame points -> statistical outlier removal ->
Open3D detect_planar_patches (Araujo and Oliveira 2020) -> up axis -> keep roughly horizontal
patches seen from above, drop those near the top of the scene -> sample placement points, planes
weighted by area.

Steps as built here (all thresholds relative to depth, so relative depth works the same way; the pixel-level
work of steps 0, 3 and 4 is in stages/lib/planes/pixels.py):
0. Noisy depth is smoothed first. When the pixel normals (5x5 Sobel of the point map on the
   grid of step 4) scatter by more than ``denoise_normal_noise_deg`` (median angle to their 2-pixel
   average), log depth on that grid is smoothed by a bilateral filter (Gaussian of
   ``denoise_sigma_rel`` of the width, not across steps of about ``denoise_edge_rel`` of the depth). A
   monocular model's depth has correlated noise of about 1 % of the depth that turns its local normals
   by tens of degrees; measured depth (normals within a few degrees) is used as it is. The smoothed
   depth gives the points, patches, normals and candidate regions; the membership test's distances, the
   final plane fits and the scene's height range use the depth as given.
1. Points from a pixel grid subsampled to at most ``max_points`` (speed), outlier removal, normals,
   planar patches. Each patch normal is turned to face the camera.
2. Up axis. Two candidates: the paper's PCA of the convex hull (principal axis of the hull surface
   closest to the camera's -y) and a camera-gravity prior (the camera is roughly upright, so up is
   near -y but tilted by the camera pitch: of -y and the patch normals within ``max_tilt_deg`` of it,
   the one with the most horizontal pixels). Each candidate is first moved to the mean of the pixel
   normals within ``horizontal_tol_deg`` of it (mean shift, kept within that angle of the candidate):
   the pixels of the horizontal surfaces vote, not one patch's normal, which a warped surface tilts
   and which on blurred depth may belong to a patch that swallowed a floor with its wall. Score of a
   candidate = the fraction of pixel normals within ``horizontal_tol_deg`` of it; a candidate further
   than ``max_tilt_deg`` from -y scores -1 (that would call walls floors). The higher score wins
   (ties go to the paper's PCA).
3. Candidate planes: connected regions of pixels whose normal lies within ``horizontal_tol_deg`` of
   up (seen from above; ceilings face down), cut where the height along up jumps by more than
   ``plane_distance_rel * depth`` between neighbouring pixels, of at least
   ``min_plane_pixel_fraction`` of the image, each with its least-squares plane; those whose centre
   lies above ``top_drop_fraction`` of the scene's height range are dropped (the tops of tall furniture), unless
   they cover ``top_keep_pixel_fraction`` of the photo: then the photo shows that surface (a close-up of a table
   top, whose centre estimated depth moves across the threshold).
4. Member pixels, on a grid of at most ``max_grid_pixels``: pixels within ``plane_distance_rel * depth``
   of a candidate's plane, whose local normal is within ``member_normal_tol_deg`` of it, and that
   are connected in the image to the candidate's region or to a smaller region lying on its plane
   (one floor seen in pieces between objects), so the members are the visible surface, not the plane's
   extension into empty space. Estimated depth bends floors by slow warps of a few % of the depth, so
   for ``member_follow_steps`` rounds the distance is taken to the members' own smooth offset from
   the plane (Gaussian of ``member_smooth_rel`` of the width; 0 on a true plane) instead of the
   plane. Larger planes (by footprint area) claim pixels first; planes with fewer than
   ``min_plane_pixel_fraction`` of the image are dropped. Each plane is refit to its member pixels;
   its area is the sum of the pixel footprints z^3 / (fx fy |d|) (d = plane distance to the camera).
   On estimated depth (smoothed in step 0) each kept plane's members then grow over the pixels of its own
   colour in the photo (``colour_grow_*``; plane_pixels.colour_grown): depth blurred across a table's edge bends
   the front of its top away from the plane, but the photo still shows where the top ends.
5. ``num_points`` placement points over all planes, shared in proportion to plane area but at
   least ``min_points_per_plane`` each (compose draws a plane by its ``area``, then one of its
   points, so every plane needs points). On each plane a member pixel is drawn uniformly
   (``point_sampling: pixel``, the paper's random point of the depth point cloud: nearer parts, which
   cover more pixels, get more points) or with probability proportional to its footprint (``area``:
   uniform over the visible area, which favours far-away spots), a uniform position inside that pixel
   is taken and its ray is intersected with the plane.

planes.json (docs/stage_contracts.md): ``pixels`` are continuous pixel coordinates in the K
convention (top-left pixel centre at (0.5, 0.5)): the integer pixel index is floor(u), floor(v).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from stages.lib.planes.pixels import (colour_grown, denoise_depth, facing_normals, horizontal_regions, normal_noise_deg,
                                      refit_plane, member_labels)
from stages.lib.planes.search_config import PlaneSearchConfig

CAMERA_UP = np.array([0.0, -1.0, 0.0])   # OpenCV camera: y points down in the image


@dataclass
class Patch:
    """One planar patch. normal faces the camera; axes [3, 3] columns: in-plane a, b, normal."""

    normal: np.ndarray        # [3]
    center: np.ndarray        # [3]
    axes: np.ndarray          # [3, 3]
    extent: np.ndarray        # [3] (a, b, thickness)
    seed_points: np.ndarray   # [M, 3] the point-cloud points the patch was fitted to


def backproject(depth: np.ndarray, K: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Camera-frame points [..., 3] of pixels (rows, cols) (integer indices, centres at +0.5)."""
    z = depth[rows, cols]
    x = (cols + 0.5 - K[0, 2]) / K[0, 0] * z
    y = (rows + 0.5 - K[1, 2]) / K[1, 1] * z
    return np.stack([x, y, z], axis=-1)


def subsample_depth(depth: np.ndarray, K: np.ndarray, max_pixels: int) -> tuple[np.ndarray, np.ndarray]:
    """Every s-th pixel of depth [H, W] (s so that at most max_pixels remain) and the K [3, 3] of
    that grid: backproject(sub, K_sub, r, c) equals backproject(depth, K, r*s + s//2, c*s + s//2)."""
    height, width = depth.shape
    stride = max(1, math.ceil(math.sqrt(height * width / max_pixels)))
    offset = stride // 2 + 0.5
    K_sub = np.array(K, dtype=np.float64)
    K_sub[:2] /= stride
    K_sub[0, 2] = (K[0, 2] - offset) / stride + 0.5
    K_sub[1, 2] = (K[1, 2] - offset) / stride + 0.5
    return depth[stride // 2::stride, stride // 2::stride], K_sub


def project(points: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixel coordinates (u, v) [N, 2] of camera-frame points [N, 3] (K convention)."""
    homogeneous = points @ np.asarray(K).T
    return homogeneous[:, :2] / homogeneous[:, 2:3]


def grid_points(depth: np.ndarray, K: np.ndarray, max_points: int) -> np.ndarray:
    """Valid points [N, 3] of the depth map subsampled to at most max_points pixels."""
    sub_depth, sub_K = subsample_depth(depth, K, max_points)
    rows, cols = np.nonzero(sub_depth > 0)
    return backproject(sub_depth, sub_K, rows, cols)


def detect_patches(points: np.ndarray, cfg: PlaneSearchConfig) -> tuple[list[Patch], np.ndarray]:
    """Open3D planar patches of a point cloud [N, 3] -> (patches, inlier points [M, 3])."""
    import open3d as o3d  # here, at first use: 2 s to load

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    cloud, _ = cloud.remove_statistical_outlier(cfg.outlier_neighbors, cfg.outlier_std_ratio)
    if len(cloud.points) < max(cfg.patch_neighbors, 10):
        return [], np.asarray(cloud.points)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(cfg.normal_neighbors))
    boxes = cloud.detect_planar_patches(
        normal_variance_threshold_deg=cfg.patch_normal_variance_deg,
        coplanarity_deg=cfg.patch_coplanarity_deg, outlier_ratio=cfg.patch_outlier_ratio,
        min_plane_edge_length=0.0, min_num_points=0,
        search_param=o3d.geometry.KDTreeSearchParamKNN(cfg.patch_neighbors))
    inliers = np.asarray(cloud.points)                                     # [M, 3]
    patches = []
    for box in boxes:
        axes = np.asarray(box.R).copy()
        center = np.asarray(box.center).copy()
        extent = np.asarray(box.extent).copy()
        if axes[:, 2] @ center > 0:          # make the normal face the camera (at the origin)
            axes[:, 2] *= -1
            axes[:, 1] *= -1
        # The box's own points. Open3D's box centre can sit a few mm off the plane with a thinner
        # box than that offset, so take points within the in-plane extent and a depth-relative
        # distance, and move the centre onto their median plane offset.
        local = (inliers - center) @ axes                                  # [M, 3]
        tolerance = max(float(extent[2]), cfg.plane_distance_rel * float(np.linalg.norm(center)))
        inside = (np.abs(local[:, :2]) <= extent[:2] / 2 + tolerance).all(axis=1) & \
                 (np.abs(local[:, 2]) <= tolerance)
        if inside.any():
            center = center + np.median(local[inside, 2]) * axes[:, 2]
        patches.append(Patch(axes[:, 2], center, axes, extent, inliers[inside]))
    return patches, inliers


def hull_pca_up(points: np.ndarray) -> np.ndarray:
    """The paper's up axis: principal axis of the convex hull surface closest to the camera's -y.

    points [N, 3]. PCA over triangle centroids weighted by triangle area; sign towards -y.
    """
    import open3d as o3d  # here, at first use: 2 s to load

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    try:
        hull, _ = cloud.compute_convex_hull()
    except RuntimeError:                      # degenerate (e.g. all points on one plane)
        return CAMERA_UP.copy()
    vertices = np.asarray(hull.vertices)                       # [V, 3]
    triangles = vertices[np.asarray(hull.triangles)]           # [T, 3, 3]
    areas = 0.5 * np.linalg.norm(np.cross(triangles[:, 1] - triangles[:, 0],
                                          triangles[:, 2] - triangles[:, 0]), axis=1)   # [T]
    centroids = triangles.mean(axis=1)                         # [T, 3]
    weights = areas / max(areas.sum(), 1e-12)
    mean = weights @ centroids
    covariance = (centroids - mean).T @ ((centroids - mean) * weights[:, None])
    _, vectors = np.linalg.eigh(covariance)                    # columns: principal axes
    best = vectors[:, np.argmax(np.abs(vectors.T @ CAMERA_UP))]
    return best if best @ CAMERA_UP > 0 else -best


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle(s) in degrees between unit vector(s) a [..., 3] and unit vector b [3]."""
    return np.degrees(np.arccos(np.clip(a @ b, -1.0, 1.0)))


def up_score(candidate: np.ndarray, normals: np.ndarray, cfg: PlaneSearchConfig) -> float:
    """Fraction of the pixel normals [N, 3] horizontal w.r.t. candidate; -1 when candidate tilts past max_tilt."""
    if _angle_deg(candidate, CAMERA_UP) > cfg.max_tilt_deg:
        return -1.0
    if len(normals) == 0:
        return 0.0
    return float(np.mean(normals @ candidate > math.cos(math.radians(cfg.horizontal_tol_deg))))


def choose_up(patches: list[Patch], hull_up: np.ndarray, facing: np.ndarray, cfg: PlaneSearchConfig,
              max_normals: int = 20000) -> tuple[np.ndarray, str, dict[str, float]]:
    """Up axis [3] (camera frame), which candidate won ("pca_hull" | "camera_prior"), scores.

    Candidates: the hull's axis and the camera prior's (-y and the patch normals), each moved to the mean of
    the pixel normals [H, W, 3] around it (refine_up): a patch's own normal is tilted by a warped or noisy
    surface, and on blurred depth a patch can swallow a floor with its wall. A candidate that ends further
    than max_tilt_deg from -y scores -1.
    """
    normals = facing.reshape(-1, 3)
    normals = normals[np.any(normals != 0, axis=1)]
    normals = normals[:: max(1, len(normals) // max_normals)]                 # [N, 3]
    reach = cfg.max_tilt_deg + cfg.horizontal_tol_deg          # refine_up moves a candidate up to the tolerance
    patch_normals = [p.normal for p in patches if _angle_deg(p.normal, CAMERA_UP) <= reach]
    prior_candidates = [refine_up(c, normals, cfg) for c in [CAMERA_UP] + patch_normals]
    prior_scores = [up_score(c, normals, cfg) for c in prior_candidates]
    prior = prior_candidates[int(np.argmax(prior_scores))]
    hull_up = refine_up(hull_up, normals, cfg)
    scores = {"pca_hull": up_score(hull_up, normals, cfg), "camera_prior": max(prior_scores)}
    source = "pca_hull" if scores["pca_hull"] >= scores["camera_prior"] else "camera_prior"
    up = hull_up if source == "pca_hull" else prior
    if scores[source] < 0:                    # neither is plausible: trust the upright camera
        up, source = CAMERA_UP.copy(), "camera_prior"
    return up / np.linalg.norm(up), source, scores


def refine_up(up: np.ndarray, normals: np.ndarray, cfg: PlaneSearchConfig, iterations: int = 5) -> np.ndarray:
    """The up axis [3] moved to the mean of the pixel normals [N, 3] within horizontal_tol_deg of it (mean shift
    over the normals within that angle of the given axis).

    Every horizontal pixel votes, so the axis follows the horizontal surfaces themselves rather than the
    normal of one planar patch, which a warped or noisy surface tilts by several degrees.
    """
    min_cos = math.cos(math.radians(cfg.horizontal_tol_deg))
    flat = normals[normals @ up > min_cos]    # anchored: it cannot walk off along the bend of a blurred floor-wall edge
    for _ in range(iterations):
        near = flat[flat @ up > min_cos]
        if len(near) == 0:
            break
        mean = near.sum(axis=0)
        up = mean / np.linalg.norm(mean)
    return up


def allocate_points(areas: np.ndarray, total: int, minimum: int) -> np.ndarray:
    """Points per plane [P]: proportional to areas [P] (largest remainder), at least `minimum`
    each (taken from the planes above it), summing to total (when total >= P * minimum)."""
    minimum = min(minimum, total // max(len(areas), 1))
    share = areas / areas.sum() * total
    counts = np.floor(share).astype(int)
    counts[np.argsort(counts - share)[: total - counts.sum()]] += 1
    while (counts < minimum).any():
        short = int(np.argmin(counts))
        counts[int(np.argmax(counts))] -= minimum - counts[short]
        counts[short] = minimum
    return counts


def sample_on_planes(depth: np.ndarray, K: np.ndarray, labels: np.ndarray, normals: np.ndarray,
                     centers: np.ndarray, total: int, minimum: int, rng: np.random.Generator,
                     per_pixel: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Placement points over each plane's visible member pixels; points per plane in proportion to its area.

    depth/labels [H, W] (labels -1 = none), K [3, 3] of that pixel grid, normals/centers [P, 3].
    A member pixel is drawn with probability proportional to its footprint on the plane (uniform over
    the surface: far parts, which cover more area per pixel, get more points), or with `per_pixel`
    uniformly over the plane's pixels (a random point of the depth point cloud, as in the paper:
    nearer parts get more points), then a uniform position inside it, whose ray is intersected with
    the plane. Returns (points [total, 3], plane index [total], area per plane [P] in depth units squared).
    """
    rows, cols = np.nonzero(labels >= 0)
    plane_of = labels[rows, cols]                                        # [S]
    offsets = np.einsum("ij,ij->i", normals, centers)                    # [P] plane: n.x = d
    footprint = depth[rows, cols] ** 3 / (K[0, 0] * K[1, 1] * np.abs(offsets[plane_of]))   # [S]
    areas = np.bincount(plane_of, weights=footprint, minlength=len(normals))
    counts = allocate_points(areas, total, minimum)
    chosen = np.concatenate([
        rng.choice(np.flatnonzero(plane_of == index), size=count,
                   p=None if per_pixel else footprint[plane_of == index] / areas[index])
        for index, count in enumerate(counts)])
    u = cols[chosen] + rng.random(len(chosen))
    v = rows[chosen] + rng.random(len(chosen))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(len(chosen))], axis=1)
    plane = plane_of[chosen]
    t = offsets[plane] / np.einsum("ij,ij->i", rays, normals[plane])
    return rays * t[:, None], plane, areas


def find_placement_planes(depth: np.ndarray, K: np.ndarray, cfg: PlaneSearchConfig,
                          rng: np.random.Generator, photo: np.ndarray | None = None) -> dict:
    """Horizontal placement planes of one depth map (float32 [H, W], 0 = missing); photo [H', W', 3] uint8 RGB
    (any size, the same view) or None: on estimated depth the planes' member pixels grow over their colour in it.

    Returns {"up": [3], "planes": [{"normal", "center", "area", "points", "pixels"}] (contract
    layout, numpy arrays), "labels": [H, W] the plane index of each member pixel, "up_source", "up_scores",
    "patches": number of planar patches}.
    """
    measured_depth, grid_K = subsample_depth(depth, K, cfg.max_grid_pixels)
    rows, cols = np.mgrid[0:measured_depth.shape[0], 0:measured_depth.shape[1]]
    measured_points = backproject(measured_depth, grid_K, rows, cols).astype(np.float32)    # [h, w, 3]
    valid = measured_depth > 0                                         # smoothing keeps the missing pixels missing
    facing = facing_normals(measured_points, valid)                                     # [h, w, 3]
    noisy = normal_noise_deg(facing) > cfg.denoise_normal_noise_deg
    if noisy:
        grid_depth = denoise_depth(measured_depth, cfg)     # noisy (estimated) depth: see step 0
        point_map = backproject(grid_depth, grid_K, rows, cols).astype(np.float32)
        facing = facing_normals(point_map, valid)
        points = grid_points(grid_depth, grid_K, cfg.max_points)                  # [N, 3]
    else:
        grid_depth, point_map = measured_depth, measured_points
        points = grid_points(depth, K, cfg.max_points)                                  # [N, 3]
    patches, inliers = detect_patches(points, cfg)
    empty_labels = np.full(depth.shape, -1, np.int32)
    if len(inliers) < 4:
        return {"up": CAMERA_UP.copy(), "planes": [], "labels": empty_labels,
                "up_source": "camera_prior", "up_scores": {}, "patches": len(patches)}
    up, up_source, up_scores = choose_up(patches, hull_pca_up(inliers), facing, cfg)
    heights = measured_points[measured_depth > 0] @ up      # as given: smoothing flattens what stands on the top
    low, high = np.percentile(heights, [2, 98])
    candidates = [r for r in horizontal_regions(point_map, facing, valid, grid_K, up, cfg, rng)
                  if (r.center @ up - low) <= cfg.top_drop_fraction * max(high - low, 1e-9)
                  or r.mask.mean() >= cfg.top_keep_pixel_fraction]
    labels = member_labels(measured_points, facing, valid, candidates, cfg)

    min_pixels = cfg.min_plane_pixel_fraction * grid_depth.size
    kept_normals, kept_centers, kept_index = [], [], []
    for index, _ in enumerate(candidates):
        mine = labels == index
        if mine.sum() < min_pixels:
            continue
        normal, center = refit_plane(measured_points[mine].astype(np.float64), rng)
        if _angle_deg(normal, up) > cfg.horizontal_tol_deg:
            continue
        kept_normals.append(normal)
        kept_centers.append(center)
        kept_index.append(index)
    remap = np.full(len(candidates) + 1, -1, np.int32)
    remap[kept_index] = np.arange(len(kept_index), dtype=np.int32)
    labels = remap[labels]                                  # -1 stays -1 (last entry)
    normals, centers = np.array(kept_normals), np.array(kept_centers)                  # [P, 3] each
    if noisy and photo is not None and kept_index and cfg.colour_grow_steps > 0:
        colours = cv2.cvtColor(cv2.resize(photo, labels.shape[::-1], interpolation=cv2.INTER_AREA).astype(np.float32)
                               / 255.0, cv2.COLOR_RGB2Lab)
        labels = colour_grown(labels, colours, measured_points, np.any(facing != 0, axis=-1), normals, centers, cfg)
    full_labels = cv2.resize(labels, depth.shape[::-1], interpolation=cv2.INTER_NEAREST)
    result = {"up": up, "planes": [], "labels": full_labels, "up_source": up_source,
              "up_scores": up_scores, "patches": len(patches)}
    if not kept_index:
        return result
    samples, sample_plane, areas = sample_on_planes(
        grid_depth, grid_K, labels, normals, centers, cfg.num_points, cfg.min_points_per_plane, rng,
        cfg.point_sampling == "pixel")
    sample_pixels = project(samples, K)
    for index in range(len(kept_index)):
        mine = sample_plane == index
        result["planes"].append({"normal": normals[index], "center": centers[index],
                                 "area": float(areas[index]), "points": samples[mine],
                                 "pixels": sample_pixels[mine]})
    return result
