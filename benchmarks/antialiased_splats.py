"""Benchmark (issue 60's splat-limited misses): the captures' splats retrained with antialiased rasterization.

Our rasterizer, as 3DGS, adds a 0.3 px^2 low-pass to every projected Gaussian and keeps its opacity, so a part thinner
than a pixel of the 320 px training frames (a plant's stems) is learnt as a faint blur; rendered at the capture's
640 px it stays faint and drops out of the alpha > 0.5 mask. The antialiased mode (Mip-Splatting's 2D filter,
gsplat's `rasterize_mode="antialiased"`) scales each Gaussian's opacity by sqrt(det(cov2d) / det(cov2d + 0.3 I)),
so that what a thin part's Gaussians learn at 320 px is not a faint blur made for the low-pass.

For each cached splat named (the rows of an earlier captures.json whose `splat` key is in --cache), this retrains it
with the antialiased mode (the entry's own settings and seed, `--work` folder), then scores extract's cut of both
(benchmarks/lib/cut_scoring.py, the capture benchmark's scoring; each splat rendered in the mode it was trained in):

    python -m benchmarks.antialiased_splats --rows ROWS.json --cache /work/cache_po --work /tmp/aa \
        [--objects plant ...] [--out benchmarks/results/captures/antialiased.json]

The mode is applied here by wrapping the rasterizer (`antialiased`): the stages do not have it (yet).
"""
from __future__ import annotations

import argparse
import contextlib
import json
import logging
from pathlib import Path

import torch

from benchmarks.lib.cut_scoring import bench_trained, splat_chain, within_targets
from benchmarks.lib.splat_runs import train_timed
from stages.engine.cache_entry import read_manifest
from stages.engine.cache_keys import derive_seed
from stages.extract.spec import ExtractConfig
from stages.lib.gaussians import rasterize
from stages.lib.gaussians.native import project_gaussians_cpp
from stages.lib.gaussians.projection import project_gaussians
from stages.lib.gaussians.rasterize_gsplat import EPS2D as LOW_PASS  # px^2: the rasterizer's low-pass

RESULTS = Path(__file__).resolve().parent / "results"
FIGURES = ("precision", "recall", "mask_iou_mean", "mask_iou_min", "mask_iou_min_true_cut")


def compensation(conics: torch.Tensor) -> torch.Tensor:
    """Antialiased opacity factor [N] sqrt(det(cov2d) / det(cov2d + LOW_PASS I)) from the conics [N, 3] (a, b, c) of
    the low-passed 2D covariances (their inverses); in (0, 1], differentiable."""
    a, b, c = conics.unbind(-1)
    det_conic = (a * c - b * b).clamp_min(1e-12)
    xx, xy, yy = c / det_conic, -b / det_conic, a / det_conic  # the low-passed covariance
    unfiltered = (xx - LOW_PASS) * (yy - LOW_PASS) - xy * xy
    return torch.sqrt(unfiltered.clamp_min(1e-12) / (xx * yy - xy * xy).clamp_min(1e-12))


@contextlib.contextmanager
def antialiased():
    """Within: our rasterizer (every backend but gsplat's) scales each Gaussian's opacity by `compensation` (the
    Gaussians are projected twice, once here for the factor: a benchmark's wrapper, not a stage's path)."""
    plain = rasterize._rasterize_tiles

    def tiles(chosen, means, quats, scales, opacities, colors, viewmat, K, width, height):
        project = project_gaussians_cpp if chosen == "cpp" and means.dtype == torch.float32 else project_gaussians
        proj = project(means, quats, scales, opacities, viewmat, K, width, height)
        drawn = (proj.radii > 0)[:, None]  # [N, 1]: the culled ones' conics are not covariances (and no gradient)
        conics = torch.where(drawn, proj.conics, torch.tensor([1.0, 0.0, 1.0], dtype=proj.conics.dtype))  # [N, 3]
        return plain(chosen, means, quats, scales, opacities * compensation(conics), colors, viewmat, K, width, height)

    rasterize._rasterize_tiles = tiles
    try:
        yield
    finally:
        rasterize._rasterize_tiles = plain


def scored(splat: Path, frames: Path, gt_dir: Path, name: str) -> dict:
    """The capture benchmark's figures of extract's cut of `splat` (the extract node's seed of run seed 0)."""
    scores = bench_trained(splat, gt_dir, frames, 0.01, ExtractConfig(), derive_seed(0, "extract", name),
                           enforce_checks=False)
    return {key: round(scores[key], 4) for key in FIGURES} | {"refused": scores["checks"].get("refused")}


def compare(row: dict, cache: Path, work: Path) -> dict:
    """Row of one capture: its cached splat's figures and those of its antialiased retraining."""
    splat, sfm, frames, gt_dir = splat_chain(cache, row["splat"])
    manifest = read_manifest(splat)
    out = work / row["splat"]
    with antialiased():
        training = train_timed(sfm, out, manifest["params"], manifest["seed"], "cpu")
        retrained = scored(out, frames, gt_dir, row["object"])
    return {"seed": row["seed"], "object": row["object"], "splat": row["splat"],
            "psnr": [round(manifest["metrics"]["final_psnr"], 3), round(training["held_out_psnr"], 3)],
            "plain": scored(splat, frames, gt_dir, row["object"]), "antialiased": retrained}


def main() -> None:
    """Command line: see the module docstring."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rows", type=Path, required=True, help="an earlier captures.json (its seed/object/splat)")
    parser.add_argument("--cache", type=Path, required=True)
    parser.add_argument("--work", type=Path, required=True, help="new folder for the retrained splats")
    parser.add_argument("--objects", nargs="*", default=None, help="only these objects (default: every row)")
    parser.add_argument("--out", type=Path, default=RESULTS / "captures" / "antialiased.json")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s][%(name)s][%(levelname)s] - %(message)s")
    rows = [row for row in json.loads(args.rows.read_text())
            if "splat" in row and (args.objects is None or row["object"] in args.objects)]
    results = []
    for row in rows:  # written after each capture: a run stopped early keeps what it measured
        results.append(compare(row, args.cache, args.work))
        args.out.write_text(json.dumps(results, indent=1))
    for result in results:
        print(f"seed {result['seed']} {result['object']}: PSNR {result['psnr'][0]} -> {result['psnr'][1]} dB; "
              f"P / R / worst IoU / own cut's {[result['plain'][k] for k in FIGURES[:2] + FIGURES[3:]]} -> "
              f"{[result['antialiased'][k] for k in FIGURES[:2] + FIGURES[3:]]}")
    print(f"within the targets: {sum(within_targets(r['plain']) for r in results)} of {len(results)} plain, "
          f"{sum(within_targets(r['antialiased']) for r in results)} antialiased")


if __name__ == "__main__":
    main()
