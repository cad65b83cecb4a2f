"""Benchmark: how much extract's cut of one splat moves with the run's seed (its RANSAC draws), on cached captures.

The extract node's seed derives from the run seed (`run.seed`, the ablation's seeds 0-2), so two runs of one capture
can cut its splat differently. For each row of an earlier captures.json whose splat is in --cache, the cut with the
extract seed of each run seed, scored as the capture benchmark scores it (benchmarks/lib/cut_scoring.py): precision,
recall, worst held-out mask IoU, the support plane's tilt against the truth, and whether it is within the targets.

    python -m benchmarks.extract_seeds --rows ROWS.json --cache /work/cache_po [--run-seeds 0 1 2 3 4] \
        [--out benchmarks/results/captures/extract_seeds.json]
"""
from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

from benchmarks.lib.cut_scoring import SplatTruth, splat_chain, within_targets
from benchmarks.lib.evaluation import angle_deg, score
from stages.engine.cache_keys import derive_seed
from stages.extract.spec import ExtractConfig
from stages.lib.objects.cut import cut_gaussians

RESULTS = Path(__file__).resolve().parent / "results"


def cuts_over_seeds(row: dict, cache: Path, run_seeds: list[int]) -> dict:
    """One capture's cut with each run seed's extract seed: its figures per run seed."""
    splat, _, frames, gt_dir = splat_chain(cache, row["splat"])
    scene = SplatTruth.read(splat, gt_dir, frames, 0.01)
    cuts = []
    for run_seed in run_seeds:
        extraction = cut_gaussians(scene.gaussians, ExtractConfig(), scene.cameras,
                                   seed=derive_seed(run_seed, "extract", row["object"]), enforce_checks=False)
        figures = score(extraction.keep, scene.membership["is_object"])
        ious = scene.ious(extraction.keep)[0]
        cuts.append({"run_seed": run_seed, "precision": round(figures["precision"], 4),
                     "recall": round(figures["recall"], 4), "mask_iou_min": round(min(ious, default=0.0), 4),
                     "plane_tilt_deg": round(angle_deg(scene.rotation @ extraction.normal, scene.gt.ground_normal), 3),
                     "plane_source": extraction.plane_source, "refused": extraction.checks.get("refused")})
    within = [within_targets(cut) for cut in cuts]
    spread = max(cut["mask_iou_min"] for cut in cuts) - min(cut["mask_iou_min"] for cut in cuts)
    return {"seed": row["seed"], "object": row["object"], "splat": row["splat"], "cuts": cuts,
            "within": within, "iou_spread": round(spread, 4)}


def main() -> None:
    """Command line: see the module docstring."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rows", type=Path, required=True, help="an earlier captures.json (its seed/object/splat)")
    parser.add_argument("--cache", type=Path, required=True)
    parser.add_argument("--run-seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--out", type=Path, default=RESULTS / "captures" / "extract_seeds.json")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s][%(name)s][%(levelname)s] - %(message)s")
    results = [cuts_over_seeds(row, args.cache, args.run_seeds)
               for row in json.loads(args.rows.read_text()) if "splat" in row]
    args.out.write_text(json.dumps(results, indent=1))
    spreads = np.array([result["iou_spread"] for result in results])
    flips = [f"seed {r['seed']} {r['object']}" for r in results if len(set(r["within"])) > 1]
    moved = [f"seed {r['seed']} {r['object']} ({r['iou_spread']})" for r in results if r["iou_spread"] > 0.005]
    print(f"{len(results)} captures x run seeds {args.run_seeds}: worst-IoU spread median {np.median(spreads):.4f}, "
          f"max {spreads.max():.4f}; over 0.005: {', '.join(moved) or 'none'}; within the targets for some run seeds "
          f"only: {', '.join(flips) or 'none'}")


if __name__ == "__main__":
    main()
