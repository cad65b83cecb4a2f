"""Benchmark of the `extract` stage: precision / recall of the kept Gaussians against a known object.

Modes (JSON figures on stdout, one object per scene):
  python -m benchmarks.extract synthetic [--seeds 5]
      procedural scenes (tests/factories/splats.py: textured or plain floor, optional walls, halo, floaters) under
      random similarity transforms;
  python -m benchmarks.extract trained --splat SPLAT_DIR --gt GT_DIR [--frames FRAMES_DIR]
      a splat_train folder against the sample's objects/<name>/ (gt.json + object_points.npy): the
      model frame is aligned to the world by the camera centres (Umeyama similarity); a Gaussian is
      "object" when it lies inside the GT object's volume or within --object-distance metres of a GT
      object point, and not below the support plane (`object_membership`; the plane is the top of what the
      object stands on, a rug's included: benchmarks/lib/truth_views.py); the older surface-only figures (within
      --object-distance, above the plane) are reported too, as *_surface; at the held-out capture views, the
      cut's mask IoU with the visible mask (pixels where clutter hides the object left out) and how many
      rows it runs below the true mask's bottom (mask_below_bottom_px, median over views), with the same for
      the ground truth's own cut (*_true_cut), and, in the worst view, the share of the missed pixels that the
      whole splat draws with Gaussians under the support plane (worst_view_missed_under_support);
  python -m benchmarks.extract ply --ply MODEL.ply --out DIR
      any Inria PLY without cameras (e.g. ../shared/real/plush_dog/inria_point_cloud.ply): report
      what is kept and write the panel PNG.
"""
from __future__ import annotations

import argparse
import json
import logging
import time
from dataclasses import asdict
from pathlib import Path

from benchmarks.lib.cut_scoring import bench_trained
from benchmarks.lib.evaluation import angle_deg, score
from benchmarks.lib.settings import add_set_option, changed_settings
from stages.extract.run import draw_filtering
from stages.extract.spec import ExtractConfig
from stages.lib.gaussians.model import SH_C0
from stages.lib.gaussians.ply import read_gaussians
from stages.lib.objects.cut import Extraction, cut_gaussians, extract_object
from tests.factories.splats import synthetic_scene


def bench_synthetic(seeds: int, cfg: ExtractConfig) -> list[dict]:
    """Scores over procedural scene variants and seeds."""
    variants = {"textured_floor": {}, "plain_floor": {"floor_points": 300}, "room_walls": {"wall_points": 20000},
                "no_floaters_dense_halo": {"floater_points": 0, "halo_points": 2000}}
    results = []
    for name, kwargs in variants.items():
        for seed in range(seeds):
            scene = synthetic_scene(seed, **kwargs)
            start = time.perf_counter()
            extraction = extract_object(scene.means, scene.opacities, scene.scales, cfg, scene.viewmats, seed=seed)
            results.append({"scene": name, "seed": seed, **score(extraction.keep, scene.is_object),
                            "normal_error_deg": angle_deg(extraction.normal, scene.normal),
                            "height_error_rel": abs(extraction.height - scene.height) / scene.height,
                            "plane_source": extraction.plane_source, "seconds": time.perf_counter() - start})
    return results


def bench_ply(ply: Path, out: Path, cfg: ExtractConfig) -> dict:
    """Run extract on a model without cameras (.ply or .splat); write filtering.png into `out`."""
    gaussians = read_gaussians(ply)
    means = gaussians.means.detach().cpu().numpy()
    start = time.perf_counter()
    extraction: Extraction = cut_gaussians(gaussians, cfg)
    seconds = time.perf_counter() - start
    out.mkdir(parents=True, exist_ok=True)
    colors = 0.5 + SH_C0 * gaussians.sh[:, 0].detach().cpu().numpy()
    draw_filtering(out / "filtering.png", means, colors, extraction)
    return {"scene": str(ply), "counts": extraction.counts, "plane_source": extraction.plane_source,
            "height": extraction.height, "normal": extraction.normal.tolist(), "seconds": seconds}


def main() -> None:
    """Command line: see the module docstring."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("mode", choices=["synthetic", "trained", "ply"])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--splat", type=Path)
    parser.add_argument("--gt", type=Path)
    parser.add_argument("--frames", type=Path)
    parser.add_argument("--object-distance", type=float, default=0.01, help="metres")
    parser.add_argument("--ply", type=Path)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/extract"))
    add_set_option(parser, "extract's settings (ExtractConfig)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO)
    cfg = ExtractConfig(**changed_settings(args.set, asdict(ExtractConfig())))
    if args.mode == "synthetic":
        results = bench_synthetic(args.seeds, cfg)
    elif args.mode == "trained":
        results = [bench_trained(args.splat, args.gt, args.frames, args.object_distance, cfg)]
    else:
        results = [bench_ply(args.ply, args.out, cfg)]
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
