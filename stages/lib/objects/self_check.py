"""The cut's self-check (issue 60): is what extract kept the thing the capture cameras filmed? No ground truth.

A capture orbits the object and keeps it in frame, so the object is
- **seen**: its Gaussians lie inside nearly every capture view (`view_share`: the median, over the kept opaque
  Gaussians, of the share of views whose image holds the Gaussian's centre);
- **aimed at**: the cameras' look-at point lies on or near it (`look_at_gap`: its distance to the nearest kept
  opaque Gaussian, in units of the object's size);
- **smaller than the orbit** (`footprint`: the radius that holds 90 % of the kept opaque Gaussians around their
  vertical axis, in units of the median camera distance to the look-at point).
A wrong cut (a patch of table, the wall an object hangs on, the whole scene) fails one of them. `kept_share` (kept
Gaussians over all) is reported, not checked: an object on a plain sheet is most of its scene's Gaussians.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.lib.objects import pointcloud
from stages.lib.objects.support import plane_coordinates


@dataclass
class SelfCheckConfig:
    """Limits of the cut's self-check (normalised units: median camera distance to the look-at point = 1)."""

    min_view_share: float = 0.7  # the kept object must lie inside at least this share of the capture views ...
    max_look_at_gap: float = 1.5  # ... the look-at point within this many object sizes of it ...
    max_footprint: float = 0.4  # ... and its footprint radius at most this x the camera distance
    self_check_candidates: int = 3  # clusters tried, nearest the look-at point first, before refusing

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_view_share <= 1.0:
            raise ValueError(f"min_view_share must be within [0, 1], got {self.min_view_share}")
        for name in ("max_look_at_gap", "max_footprint"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.self_check_candidates < 1:
            raise ValueError(f"self_check_candidates must be at least 1, got {self.self_check_candidates}")


def view_share(points: np.ndarray, viewmats: np.ndarray, Ks: np.ndarray, sizes: np.ndarray) -> float:
    """Median over points [M, 3] (world) of the share of cameras (viewmats [C, 4, 4] world-to-camera, OpenCV;
    Ks [C, 3, 3]; sizes [C, 2] width, height) whose image holds the point, in front of the camera."""
    homogeneous = np.concatenate([points, np.ones((len(points), 1))], axis=1)  # [M, 4]
    in_camera = np.einsum("cij,mj->cmi", viewmats[:, :3], homogeneous)  # [C, M, 3]
    depth = in_camera[..., 2]  # [C, M]
    pixels = np.einsum("cij,cmj->cmi", Ks, in_camera)  # [C, M, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = pixels[..., 0] / depth, pixels[..., 1] / depth
    inside = (depth > 0) & (u >= 0) & (v >= 0) & (u < sizes[:, None, 0]) & (v < sizes[:, None, 1])  # [C, M]
    return float(np.median(inside.mean(axis=0)))


def footprint_radius(points: np.ndarray, normal: np.ndarray) -> float:
    """Radius around the vertical axis (along `normal` [3]) through the median of points [M, 3] that holds 90 %
    of them."""
    across = plane_coordinates(points, normal)  # [M, 2]
    return float(np.percentile(np.linalg.norm(across - np.median(across, axis=0), axis=1), 90.0))


def cut_figures(points: np.ndarray, body: np.ndarray, total: int, kept: int, normal: np.ndarray, height: float,
                viewmats: np.ndarray | None, Ks: np.ndarray | None, sizes: np.ndarray | None,
                look_at: np.ndarray | None, scale: float, centre: np.ndarray) -> dict[str, float]:
    """The self-check's figures of a cut: points [N, 3] normalised (look-at point at `look_at`, None without
    cameras), body [N] bool: the kept opaque Gaussians; `total` and `kept` Gaussians; `normal` [3] up; `height`
    of the object (normalised). view_share needs the capture cameras (viewmats [C, 4, 4], Ks [C, 3, 3], sizes
    [C, 2]; world = points * scale + centre); the look-at gap and footprint need a look-at point."""
    figures = {"kept_share": kept / max(total, 1)}
    solid = points[body]
    if viewmats is not None and Ks is not None and sizes is not None:
        figures["view_share"] = view_share(solid * scale + centre, viewmats, Ks, sizes)
    if look_at is not None:
        radius = footprint_radius(solid, normal)
        size = max(radius, 0.5 * height, 1e-9)
        figures["footprint"] = radius
        figures["look_at_gap"] = float(pointcloud.nearest_distance(look_at[None], solid)[0]) / size
    return figures


SENTENCES = {"view_share": "the kept Gaussians lie inside {value:.0%} of the capture views (at least {limit:.0%} "
                            "expected): the cameras did not film it",
             "look_at_gap": "the cameras' look-at point lies {value:.2f} object sizes from it (at most {limit:.2f}): "
                            "the cameras aim elsewhere",
             "footprint": "its footprint radius is {value:.2f} camera distances (at most {limit:.2f}): wider than "
                          "what an orbit keeps in frame"}


def limits(cfg: SelfCheckConfig) -> dict[str, float]:
    """Each checked figure's limit: view_share's a minimum, the others' maxima."""
    return {"view_share": cfg.min_view_share, "look_at_gap": cfg.max_look_at_gap, "footprint": cfg.max_footprint}


def margins(figures: dict[str, float], cfg: SelfCheckConfig) -> dict[str, float]:
    """Each figure's margin to its limit, margin_<name> = (limit - value) / limit (for view_share, the minimum:
    (value - limit) / limit); negative when it fails."""
    return {f"margin_{name}": ((figures[name] - limit) if name == "view_share" else (limit - figures[name])) / limit
            for name, limit in limits(cfg).items() if name in figures and limit > 0}


def failed_checks(figures: dict[str, float], cfg: SelfCheckConfig) -> list[str]:
    """The self-check's failures, each a sentence naming the figure and its limit (empty: the cut passes)."""
    limit_of, margin_of = limits(cfg), margins(figures, cfg)
    return [f"{name}: " + sentence.format(value=figures[name], limit=limit_of[name])
            for name, sentence in SENTENCES.items() if margin_of.get(f"margin_{name}", 0.0) < 0]
