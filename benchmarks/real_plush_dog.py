"""Real capture end to end with the defaults: the plush dog's 84 photos -> frames -> sfm -> splat_train ->
extract, the real RGB-D photos (TUM, NYU, SUN) -> bg_depth -> planes, and compose on them.

    OMP_NUM_THREADS=1 taskset -c 1 python -m benchmarks.real_plush_dog --cache /tmp/real16/cache \
        --figures benchmarks/results/real_plush_dog

The graph is the one `python dag.py data=<folder config> run.until=compose` builds (object plush_dog,
0.25 m, video ../shared/real/plush_dog/images; backgrounds ../shared/real/rgbd), run by the engine with
the given cache (a cached node is not rerun). Prints and writes <figures>/summary.json: each stage's
seconds (from its manifest), SfM, splat and extract figures, the five IoUs against the hand-drawn boxes
(benchmarks/lib/cutout_boxes.py) and compose's stats; and the figures filtering.png, object_boxes.png (each
boxed photo with the drawn box in blue and the cut-out's alpha outline in red, beside the cut-out on green),
composed_preview.png (compose's preview of composed images, masks outlined) and composed.png (the first six
composed images as they are).
"""
from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import cv2
import numpy as np
import torch

from benchmarks.lib.cutout_boxes import BoxScore, alpha_mask, load_boxes, score_cutout, scores_json
from stages.app.pipeline import Graph
from stages.engine.cache_entry import Outcome, read_manifest
from stages.engine.graph import Node
from stages.engine.scheduler import Engine
from stages.lib.composition.preview import preview_grid
from stages.lib.gaussians.ply import read_ply
from stages.lib.gaussians.rasterize import render
from stages.records.cameras import CamerasRecord
from stages.records.sfm import SfmRecord
from tests.factories.configs import REAL
from tests.factories.runs import object_dirs, run_real_chain

log = logging.getLogger("benchmarks.real_plush_dog")


def node(graph: Graph, stage: str) -> Node:
    """The graph's first node of a stage."""
    return graph.nodes[stage][0]


def stage_seconds(engine: Engine, graph: Graph, stages: list[str]) -> dict[str, float]:
    """Seconds each stage took (summed over its items), from the manifests in the cache."""
    return {stage: round(sum(read_manifest(engine.output_dir(n))["seconds"]
                             for n in graph.nodes[stage]), 2) for stage in stages}


def small(bgr: np.ndarray, max_side: int) -> np.ndarray:
    """`bgr` [H, W, 3] with its long side at most `max_side`."""
    factor = min(1.0, max_side / max(bgr.shape[:2]))
    return cv2.resize(bgr, None, fx=factor, fy=factor, interpolation=cv2.INTER_AREA) if factor < 1 else bgr


def box_panel(scores: list[BoxScore], dirs: dict[str, Path]) -> np.ndarray:
    """Rows per boxed photo: undistorted SfM image with the drawn box (blue) and alpha outline (red), and the
    cut-out rendered on green: BGR uint8."""
    cameras = {frame.file: frame for frame in CamerasRecord.read(dirs["splat_train"]).frames}
    gaussians = read_ply(dirs["extract"] / "object.ply")
    rows = []
    for score in scores:
        frame = cameras[score.frame]
        photo = cv2.imread(str(SfmRecord.read(dirs["sfm"]).image(score.frame)))
        contours, _ = cv2.findContours(alpha_mask(gaussians, frame).astype(np.uint8), cv2.RETR_EXTERNAL,
                                       cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(photo, contours, -1, (0, 0, 255), 2)
        x0, y0, x1, y1 = (round(v) for v in score.drawn)
        cv2.rectangle(photo, (x0, y0), (x1, y1), (255, 0, 0), 2)
        cv2.putText(photo, f"{score.photo} IoU {score.iou:.3f}", (10, 30), cv2.FONT_HERSHEY_SIMPLEX, 0.8,
                    (0, 0, 255), 2)
        with torch.no_grad():
            out = render(gaussians, torch.as_tensor(frame.viewmat, dtype=torch.float32),
                         torch.as_tensor(frame.K, dtype=torch.float32), frame.width, frame.height,
                         background=torch.tensor([0.0, 0.6, 0.0]))
        rgb = (out.rgb.clamp(0, 1).numpy() * 255).round().astype(np.uint8)
        rows.append(np.concatenate([photo, rgb[:, :, ::-1]], axis=1))
    return np.concatenate(rows, axis=0)


def composed_grid(compose_dir: Path, count: int = 6) -> np.ndarray:
    """The first `count` composed images of a compose output in a grid (BGR uint8), without outlines."""
    names = [image["file_name"] for image in json.loads((compose_dir / "annotations.json").read_text())["images"]]
    return preview_grid([cv2.imread(str(compose_dir / "images" / name)) for name in names[:count]], tile_width=640)


def summary(engine: Engine, graph: Graph, outcomes: list[Outcome], scores: list[BoxScore]) -> dict:
    """The benchmark's figures (see the module doc)."""
    dirs = object_dirs(engine, graph)
    metrics = {stage: read_manifest(engine.output_dir(node(graph, stage)))["metrics"]
               for stage in ("frames", "sfm", "splat_train", "extract", "compose")}
    return {
        "status": {f"{r.stage}[{r.item}]": r.status for r in outcomes},
        "seconds": stage_seconds(engine, graph, ["frames", "sfm", "splat_train", "extract", "bg_depth", "planes",
                                                 "compose"]),
        "frames": {k: metrics["frames"][k] for k in ("frames", "input_frames", "dark", "blurred", "duplicates_dropped")},
        "sfm": {k: metrics["sfm"][k] for k in ("registered", "total", "mean_reprojection_error_px", "points",
                                               "attempts", "bit_reproducible")},
        "splat_train": {k: metrics["splat_train"][k] for k in ("final_psnr", "num_gaussians", "iterations_run")},
        "extract": {k: metrics["extract"][k] for k in ("plane_source", "kept", "total", "base_gap", "layer",
                                                       "cut_density", "removed_flat_contact", "removed_hanging")},
        "boxes": scores_json(scores),
        "ious": [round(s.iou, 3) for s in scores],
        "planes": [read_manifest(engine.output_dir(n))["metrics"]
                   for n in graph.nodes["planes"]],
        "compose": metrics["compose"],
        "cache": {stage: str(path) for stage, path in dirs.items()},
    }


def main() -> None:
    """Run the chain, score the cut-out and write the summary and figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cache", type=Path, default=Path("/tmp/real16/cache"))
    parser.add_argument("--figures", type=Path, default=Path("benchmarks/results/real_plush_dog"))
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    torch.set_num_threads(1)
    if not REAL.is_dir():
        raise SystemExit(f"{REAL} not present: the real captures live beside the repository")
    engine, graph, outcomes = run_real_chain(args.cache, "compose")
    failed = [r for r in outcomes if r.status == "failed"]
    if failed:
        raise SystemExit("\n".join(f"{r.stage}[{r.item}] failed: {r.error}" for r in failed))
    dirs = object_dirs(engine, graph)
    scores = score_cutout(load_boxes(REAL / "plush_dog" / "boxes.json"), dirs["frames"], dirs["sfm"],
                          dirs["splat_train"], dirs["extract"] / "object.ply")
    result = summary(engine, graph, outcomes, scores)
    args.figures.mkdir(parents=True, exist_ok=True)
    (args.figures / "summary.json").write_text(json.dumps(result, indent=1))
    cv2.imwrite(str(args.figures / "filtering.png"), small(cv2.imread(str(dirs["extract"] / "filtering.png")), 1200))
    cv2.imwrite(str(args.figures / "object_boxes.png"), small(box_panel(scores, dirs), 1000))
    compose_dir = engine.output_dir(node(graph, "compose"))
    png = [cv2.IMWRITE_PNG_COMPRESSION, 9]
    cv2.imwrite(str(args.figures / "composed_preview.png"), small(cv2.imread(str(compose_dir / "preview.png")), 960), png)
    cv2.imwrite(str(args.figures / "composed.png"), small(composed_grid(compose_dir), 1200), png)
    print(json.dumps({k: result[k] for k in ("seconds", "sfm", "splat_train", "extract", "ious")}, indent=1))


if __name__ == "__main__":
    main()
