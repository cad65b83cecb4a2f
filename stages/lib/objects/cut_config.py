"""The settings of the object cut (stages/lib/objects/cut.py, clusters.py), light: the extract stage's spec extends
them without loading torch."""
from __future__ import annotations

from dataclasses import dataclass

from stages.lib.objects.self_check import SelfCheckConfig
from stages.lib.objects.support import SupportConfig


@dataclass
class CutConfig(SupportConfig, SelfCheckConfig):
    """The cut's parameters (stages/lib/objects/cut.py; the support plane's in SupportConfig, the self-check's in
    SelfCheckConfig). Distances are in normalised units (median camera distance = 1)."""

    stat_neighbours: int = 50  # paper: 50
    stat_std_ratio: float = 1.0  # paper: 0.1; authors' code: 0.5 (lower = more aggressive)
    dbscan_eps: float = 0.03  # paper: 0.5 in raw COLMAP units; ours is normalised
    dbscan_min_points: int = 10  # paper: 100
    cluster_merge_eps: float = 2.0  # clusters within this many eps of the chosen one join it (object fragments)
    dbscan_spacing_factor: float = 2.0  # eps >= this x median distance to the min_points-th neighbour ...
    spacing_radius: float = 0.5  # ... among the Gaussians within this distance of the centre (0 = all)
    model_spacing_percentile: float = 90.0  # ... over all Gaussians, at this percentile, for a model without cameras
    regrow_fraction: float = 1.5  # give back statistically removed Gaussians within this x eps of the object
    regrow_noise: bool = True  # ... and DBSCAN noise points (sparse object interior) likewise
    cluster_min_opacity: float = 0.2  # fainter Gaussians sit out the statistical filter and DBSCAN (floaters
    #                                   would set the spacing and bridge clusters); offered back like noise
    halo_opacity: float = 0.2  # Gaussians below this opacity farther than the cluster eps from opaque ones
    invisible_opacity: float = 0.02  # ... and Gaussians below this opacity anywhere: they add nothing to a render
    #                                  (faint object seeds of splat_train, e.g. in the vase's mouth)
    height_opacity: float = 0.5  # the object's height is measured on kept Gaussians at least this opaque
    huge_scale_fraction: float = 0.25  # Gaussians whose largest scale exceeds this x object height
    silhouette_distance: float = 0.015  # ... and background haze: Gaussians whose centre lies farther than this
    #                                     outside the solid body's silhouette in capture views (0 = no such test) ...
    background_colour_tolerance: float = 0.15  # ... with the colour of the background there: on average over those
    #                                            views, no channel differs more than this (colours in [0, 1])
    silhouette_long_side: int = 256  # pixels: the capture views are rendered this size for that test
    max_outside_share: float = 0.15  # ... and Gaussians outside the kept set's visible footprint (by
    #                                  silhouette_distance) in more than this share of the views seeing them (1 = no
    #                                  such test; stages/lib/objects/footprint_carve.py) ...
    footprint_difference: float = 0.05  # ... the footprint: where the kept set changes a view by more than this ...
    footprint_clearance: float = 0.05  # ... over the Gaussians farther than this from it
    max_step_removed_fraction: float = 0.995  # a step removing more of its input than this fails
    min_total_removed_fraction: float = 0.1  # removing less than this in all fails (already cut out?)
    min_object_gaussians: int = 50  # fewer kept Gaussians than this fails
    up_hint: list[float] | None = None  # world up of a model without cameras (COLMAP frames: often [0, -1, 0]);
    #                                     None: the up of its largest plane

    def __post_init__(self) -> None:
        super().__post_init__()
        if not 0.0 < self.max_outside_share <= 1.0:
            raise ValueError(f"max_outside_share must be within (0, 1] (1: no such test), got {self.max_outside_share}")
        for name in ("footprint_difference", "footprint_clearance"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
