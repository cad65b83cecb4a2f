"""The settings of the plane search (stages/lib/planes/search.py), light: the planes stage's spec extends them
without loading OpenCV."""
from __future__ import annotations

from dataclasses import dataclass

from stages.contract.choices import choices

PointSampling = choices("PointSampling", ("pixel", "area"))  # planes.point_sampling


@dataclass
class PlaneSearchConfig:
    """Settings of the plane search; depth-relative, so relative depth works the same way."""

    max_points: int = 20000               # pixel grid subsampled to at most this many points
    max_grid_pixels: int = 80000       # member masks on a grid subsampled to at most this
    denoise_normal_noise_deg: float = 7.5  # depth smoothing when the pixel normals scatter more than this
    denoise_sigma_rel: float = 0.015      # depth smoothing: Gaussian sigma, a fraction of the image width
    denoise_edge_rel: float = 0.1         # depth smoothing: does not average across steps of about this * depth
    outlier_neighbors: int = 20           # statistical outlier removal
    outlier_std_ratio: float = 2.0
    normal_neighbors: int = 20            # normal estimation (KNN)
    patch_neighbors: int = 30             # detect_planar_patches KNN
    patch_normal_variance_deg: float = 45.0
    patch_coplanarity_deg: float = 75.0
    patch_outlier_ratio: float = 0.75
    max_tilt_deg: float = 65.0            # up axis must be within this of the camera's -y
    horizontal_tol_deg: float = 15.0      # plane normal within this of up = horizontal
    top_drop_fraction: float = 0.9        # drop planes above this fraction of the scene height
    top_keep_pixel_fraction: float = 0.1  # ... unless they cover this fraction of the photo (its main surface)
    plane_distance_rel: float = 0.02      # member: |distance to plane| < this * depth
    member_normal_tol_deg: float = 35.0  # member: local normal within this of the plane normal
    member_follow_steps: int = 2         # member: rounds of following the surface's smooth bend (0: a plane)
    member_smooth_rel: float = 0.05      # member: the bend smoothed over this fraction of the image width
    min_plane_pixel_fraction: float = 0.005
    colour_grow_steps: int = 3            # estimated depth: rounds of growing the members over its own colour
    colour_grow_distance_rel: float = 0.1  # ... over pixels whose ray meets the plane within this of their depth
    colour_grow_reach_rel: float = 0.02   # ... compared with the members' colour around (Gaussian, * width)
    colour_grow_tolerance: float = 2.0    # ... within this many standard deviations of it
    colour_grow_min_delta: float = 6.0    # ... or this CIELAB distance
    num_points: int = 1000                # placement points over all planes
    min_points_per_plane: int = 20        # every kept plane gets at least this many of them
    point_sampling: PointSampling = PointSampling.pixel  # pixel: uniform over its pixels (paper); area: over its surface
