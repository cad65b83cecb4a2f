"""Benchmark of bg_depth + planes: time per photo and where the placement points land.

Sample-layout backgrounds (``<id>.png`` + ``<id>.depth.png`` uint16 mm + ``<id>.support.png``
255 = horizontal support + ``<id>.json`` with "K"): fraction of placement points whose pixel is
true support, and for photos without any support whether no plane was found. Real RGB-D photos
(``../shared/real/rgbd``): time, planes, and for TUM the fraction of points on the desk top and the
floor (floor = lowest plane; desk = planes 0.6-0.85 m above it) and the fraction of points lying
on the surface the sensor measured at their pixel (|z - sensor z| < 5 %).

    python -m benchmarks.planes --backgrounds outputs/.../backgrounds --json /tmp/planes.json
"""
from __future__ import annotations

import argparse
import json
import logging
import shutil
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from stages.bg_depth import run as bg_depth
from stages.engine.context import Context
from stages.planes import run as planes
from stages.records.depth import DepthRecord
from stages.records.planes import PlacementPlane, PlanesRecord
from tests.factories.configs import REAL

REAL_RGBD = REAL / "rgbd"
KINECT_K = [[525.0, 0.0, 320.0], [0.0, 525.0, 240.0], [0.0, 0.0, 1.0]]
REAL_PHOTOS = {"TUM": ("TUM_color.png", "TUM_depth.png"), "NYU": ("NYU_color.ppm", "NYU_depth.pgm"),
               "SUN": ("SUN_color.jpg", "SUN_depth.png")}


def run_photo(image: Path, depth: Path, work: Path, depth_params: dict, repeat: int) -> tuple[PlanesRecord, float]:
    """bg_depth then planes (planes timed, best of repeat); returns (planes.json, seconds)."""
    depth_dir = work / "depth"
    depth_dir.mkdir(parents=True)
    bg_depth.run(Context("bg_depth", image.stem, depth_params, {"image": image, "depth": depth}, depth_dir))
    times = []
    for attempt in range(repeat):
        planes_dir = work / f"planes{attempt}"
        planes_dir.mkdir()
        started = time.perf_counter()
        planes.run(Context("planes", image.stem, {}, {"image": image, "depth": depth_dir}, planes_dir))
        times.append(time.perf_counter() - started)
    return PlanesRecord.read(work / "planes0"), min(times)


def placement_pixels(planes: list[PlacementPlane]) -> np.ndarray:
    """All placement pixels as integer (row, col) [N, 2]."""
    if not planes:
        return np.zeros((0, 2), int)
    uv = np.concatenate([p.pixels for p in planes])
    return np.stack([uv[:, 1], uv[:, 0]], axis=1).astype(int)


def bench_backgrounds(folder: Path, work: Path, repeat: int) -> dict:
    """Per-photo figures and totals on a sample-layout background folder."""
    rows = []
    for image in sorted(p for p in folder.glob("*.png") if p.stem.count(".") == 0):
        depth, support_path = folder / f"{image.stem}.depth.png", folder / f"{image.stem}.support.png"
        if not depth.is_file() or not support_path.is_file():
            continue
        record, seconds = run_photo(image, depth, work / image.stem, {}, repeat)
        support = cv2.imread(str(support_path), cv2.IMREAD_UNCHANGED) > 127
        pixels = placement_pixels(record.planes)
        on_support = float(support[pixels[:, 0], pixels[:, 1]].mean()) if len(pixels) else None
        rows.append({"id": image.stem, "has_support": bool(support.any()), "planes": len(record.planes),
                     "on_support": on_support, "seconds": seconds})
    with_support = [r for r in rows if r["has_support"]]
    without = [r for r in rows if not r["has_support"]]
    scored = [r["on_support"] for r in with_support if r["on_support"] is not None]
    return {
        "photos": len(rows),
        "with_support": len(with_support),
        "with_support_but_no_plane": sum(r["planes"] == 0 for r in with_support),
        "mean_on_support": float(np.mean(scored)) if scored else None,
        "min_on_support": float(np.min(scored)) if scored else None,
        "photos_on_support_at_least_90pct": sum(s >= 0.9 for s in scored),
        "without_support": len(without),
        "without_support_no_plane_fraction": float(np.mean([r["planes"] == 0 for r in without])) if without else None,
        "seconds_mean": float(np.mean([r["seconds"] for r in rows])) if rows else None,
        "seconds_max": float(np.max([r["seconds"] for r in rows])) if rows else None,
        "per_photo": rows,
    }


def tum_support_figures(record: PlanesRecord, sensor_depth: np.ndarray) -> dict:
    """Fraction of TUM placement points on the floor and the desk top, and on the measured surface."""
    up = record.up
    found = sorted(record.planes, key=lambda p: float(np.dot(p.center, up)))
    if not found:
        return {"desk_or_floor": 0.0, "on_measured_surface": 0.0}
    floor = found[0]
    desk = [p for p in found if 0.6 < np.dot(p.center - floor.center, up) < 0.85]
    total = sum(len(p.points) for p in found)
    points = np.concatenate([p.points for p in found])
    pixels = placement_pixels(found)
    measured = sensor_depth[pixels[:, 0], pixels[:, 1]]
    return {
        "floor_points": len(floor.points) / total,
        "desk_points": sum(len(p.points) for p in desk) / total,
        "desk_or_floor": (len(floor.points) + sum(len(p.points) for p in desk)) / total,
        "desk_height_m": [round(float(np.dot(p.center - floor.center, up)), 3) for p in desk],
        "on_measured_surface": float((np.abs(points[:, 2] - measured) < 0.05 * measured).mean()),
    }


def bench_real(folder: Path, work: Path, repeat: int, figures_dir: Path | None) -> dict:
    """Real RGB-D photos with the default 55 degree camera and (TUM) the Kinect intrinsics."""
    results = {}
    for name, (color, depth) in REAL_PHOTOS.items():
        if not (folder / color).is_file():
            continue
        settings = {"fov55": {}}
        if name == "TUM":
            settings["kinect_K"] = {"K": KINECT_K}
        for label, params in settings.items():
            record, seconds = run_photo(folder / color, folder / depth, work / f"{name}_{label}", params, repeat)
            entry = {"seconds": seconds, "planes": len(record.planes),
                     "areas_m2": [round(p.area, 3) for p in record.planes],
                     "points": [len(p.points) for p in record.planes]}
            if name == "TUM":
                sensor = DepthRecord.read(work / f"{name}_{label}" / "depth").depth
                entry.update(tum_support_figures(record, sensor))
            if figures_dir is not None:
                figures_dir.mkdir(parents=True, exist_ok=True)
                shutil.copy(work / f"{name}_{label}" / "planes0" / "placement.png",
                            figures_dir / f"placement_{name}_{label}.png")
            results[f"{name}_{label}"] = entry
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--backgrounds", type=Path, help="sample-layout background folder")
    parser.add_argument("--real", type=Path, default=REAL_RGBD, help="folder with the real RGB-D photos")
    parser.add_argument("--repeat", type=int, default=3, help="planes runs per photo (best time kept)")
    parser.add_argument("--figures", type=Path, help="copy the real photos' placement.png here")
    parser.add_argument("--json", type=Path, help="write the figures here as JSON")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    report: dict = {}
    with tempfile.TemporaryDirectory() as scratch:
        if args.backgrounds is not None:
            report["backgrounds"] = bench_backgrounds(args.backgrounds, Path(scratch) / "bg", args.repeat)
        if args.real.is_dir():
            report["real"] = bench_real(args.real, Path(scratch) / "real", args.repeat, args.figures)
    text = json.dumps(report, indent=2)
    if args.json is not None:
        args.json.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
