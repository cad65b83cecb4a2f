"""Stage `extract`: cut the object out of a trained Gaussian-splatting scene (paper: "Foreground
Object Extraction"), headless and automatic, and check the cut (the algorithm: stages/lib/objects/cut.py).

Reads `splat` (a splat_train folder: scene.ply + cameras.json) or `model` (a given .ply / .splat without
cameras: objects[].splat, whose up direction is `up_hint`, the data config's objects[].up); writes
object.ply, extract.json (stages/records/extract.py) and filtering.png (the paper's filtering figure).
"""
from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from stages.contract.errors import StageError
from stages.extract.spec import ExtractConfig
from stages.lib.gaussians.model import SH_C0, Gaussians
from stages.lib.gaussians.ply import read_gaussians, read_ply, write_ply
from stages.lib.objects.cut import STEPS, Extraction, cut_gaussians
from stages.records.cameras import CamerasRecord
from stages.records.extract import ExtractRecord

if TYPE_CHECKING:  # the engine's object; not part of the stage's cache key
    from stages.engine.context import Context


def draw_filtering(path: Path, means: np.ndarray, colors: np.ndarray | None, extraction: Extraction,
                   max_points: int = 30000, seed: int = 0) -> None:
    """Three panels like the paper's filtering figure (plane, statistical, cluster + halo filter), and the kept set
    with its self-check's figures (stages/lib/objects/self_check.py).

    Each panel shows the Gaussians entering that step seen obliquely from the side (the plane's
    normal is up), removed ones in red; the last one the kept Gaussians over the removed ones in grey. A blue
    cross marks the point the capture cameras look at. means [N, 3]; colors [N, 3] in [0, 1] or None (grey).
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
    shown_and_centre = np.concatenate([means[shown], extraction.centre[None]])  # [M + 1, 3]
    relative = (shown_and_centre - extraction.base_point) / extraction.scene_scale
    elevation = np.deg2rad(20.0)
    u = relative @ across  # [M + 1]: the shown Gaussians, then the normalisation centre
    v = (relative @ normal) * np.cos(elevation) - (relative @ depth_axis) * np.sin(elevation)
    (u, centre_u), (v, centre_v) = (u[:-1], u[-1]), (v[:-1], v[-1])
    base_colors = np.full((len(shown), 3), 0.5) if colors is None else np.clip(colors[shown], 0, 1)
    removed_by = extraction.removed_by[shown]
    panels = [("plane filter", [STEPS.index("plane")]), ("statistical filter", [STEPS.index("stat")]),
              ("cluster + halo filter", [STEPS.index("cluster"), STEPS.index("halo")])]
    figure, axes = plt.subplots(1, 4, figsize=(20, 5), dpi=100)
    for axis, (title, steps) in zip(axes, panels):
        entering = (removed_by == 0) | (removed_by >= steps[0])
        red = np.isin(removed_by, steps)
        axis.scatter(u[entering & ~red], v[entering & ~red], s=1, c=base_colors[entering & ~red], linewidths=0)
        axis.scatter(u[red], v[red], s=1, c="red", linewidths=0)
        axis.set_title(f"{title}: {int(red.sum())} of {int(entering.sum())} removed (shown)")
    kept = removed_by == 0
    axes[3].scatter(u[~kept], v[~kept], s=1, c="0.85", linewidths=0)
    axes[3].scatter(u[kept], v[kept], s=4, c="0.15", linewidths=0)  # a dark rim: a white object shows on white
    axes[3].scatter(u[kept], v[kept], s=2, c=base_colors[kept], linewidths=0)
    axes[3].set_title(self_check_title(extraction.checks), fontsize=9)
    if kept.any():  # zoomed on the kept set and the look-at point, a margin of half its size around
        low = np.minimum([u[kept].min(), v[kept].min()], [centre_u, centre_v])
        high = np.maximum([u[kept].max(), v[kept].max()], [centre_u, centre_v])
        margin = 0.5 * (high - low).max() + 1e-6
        axes[3].set_xlim(low[0] - margin, high[0] + margin)
        axes[3].set_ylim(low[1] - margin, high[1] + margin)
    if "look_at_gap" in extraction.checks:  # the normalisation centre is the cameras' look-at point
        for axis in axes:
            axis.plot([centre_u], [centre_v], marker="+", markersize=14, markeredgewidth=2, color="blue")
    for axis in axes:
        axis.set_aspect("equal")
        axis.set_xticks([])
        axis.set_yticks([])
    figure.tight_layout()
    figure.savefig(path)
    plt.close(figure)


def self_check_title(checks: dict) -> str:
    """The kept-set panel's title: the self-check's verdict and figures (those there are)."""
    verdict = ("refused" if "refused" in checks else
               f"kept cluster {checks['candidate'] + 1} (nearer ones fail the self-check)" if checks.get("candidate")
               else "kept")
    names = {"view_share": "in {:.0%} of views", "look_at_gap": "look-at gap {:.2f}", "footprint": "footprint {:.2f}",
             "wall_share": "{:.0%} on a wall", "kept_share": "{:.0%} of the scene"}
    return "\n".join([verdict, ", ".join(text.format(checks[name]) for name, text in names.items() if name in checks)])


def read_scene(ctx: Context) -> tuple[Gaussians, CamerasRecord | None, Path]:
    """The scene to cut and its cameras: `splat` (a splat_train folder: scene.ply + cameras.json) or `model`
    (a given .ply / .splat file, no cameras); and the file read."""
    if "model" in ctx.inputs:
        path = Path(ctx.inputs["model"])
        return read_gaussians(path), None, path
    splat = Path(ctx.inputs["splat"])
    path = splat / "scene.ply"
    if not path.exists():
        raise StageError(f"extract[{ctx.item}]: {path} not found; run splat_train first")
    if not CamerasRecord.exists(splat):
        raise StageError(f"extract[{ctx.item}]: {splat / CamerasRecord.JSON} not found; run splat_train first")
    return read_ply(path), CamerasRecord.read(splat), path


def run(ctx: Context) -> dict:
    """Cut the object out of `splat` (splat_train folder) or `model` (a given model file); write object.ply,
    extract.json and filtering.png."""
    cfg = ctx.typed(ExtractConfig)
    gaussians, cameras, scene_path = read_scene(ctx)
    means = gaussians.means.detach().cpu().numpy()  # [N, 3]
    try:
        extraction = cut_gaussians(gaussians, cfg, cameras, seed=ctx.seed)
    except StageError as error:
        raise StageError(f"extract[{ctx.item}] ({scene_path}): {error}") from error

    keep = np.flatnonzero(extraction.keep)
    write_ply(ctx.out / "object.ply", gaussians.subset(keep))
    ExtractRecord(extraction.normal, extraction.base_point, extraction.height, extraction.counts,
                  extraction.scene_scale, extraction.centre, extraction.plane_source, extraction.dbscan_eps,
                  asdict(cfg), extraction.checks).write(ctx.out)
    colors = 0.5 + SH_C0 * gaussians.sh[:, 0].detach().cpu().numpy()  # [N, 3]
    draw_filtering(ctx.out / "filtering.png", means, colors, extraction, seed=ctx.seed)
    ctx.log.info("extract[%s]: kept %d of %d Gaussians (plane: %s), height %.4g", ctx.item, len(keep),
                 len(means), extraction.plane_source, extraction.height)
    return {"kept": len(keep), "total": len(means), "height": extraction.height,
            "plane_source": extraction.plane_source, **extraction.counts, **extraction.checks}
