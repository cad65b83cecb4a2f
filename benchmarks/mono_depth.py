"""Placement from monocular depth, without model weights: bg_depth + planes fed the true depth degraded the way
monocular models degrade it, scored against the planes the true depth gives.

    python -m benchmarks.mono_depth [--cache outputs/cache] [--photos 40] [--speed]
    python -m benchmarks.mono_depth --write-backgrounds outputs/mono_depth    # then: python dag.py +experiment=mono_depth

Photos: the embedded sample's generic backgrounds (the default data config's `sample` node, taken from the cache
or rendered into it) with their true depth and support masks, and the real RGB-D photos of ../shared/real/rgbd
(their measured depth). Each depth is degraded at several levels, written as the sidecar a user would have, run
through the bg_depth stage and the planes search (stages/lib/planes/search.py), and compared with the same on the
true (measured) depth:

- relative (what relative-small and any relative model give): the inverse depth warped by a smooth random field
  (multiplicative, a sum of four low-frequency waves), blurred (soft object edges), with spatially correlated
  noise, then turned into affine disparity with a random scale (x0.1-10) and shift (-0.2 to +0.5 median
  disparities; values <= 0 are lost, as a model's clipped output), saved as `<id>.depth.disparity.npy`: bg_depth
  recovers the shift and the scale (stages/lib/depth/recovery.py).
- metric (what the default metric-indoor-small gives): the depth times a random global factor (log-normal), warped,
  blurred and noisy the same way, saved as `<id>.depth.npy` metres.
A knob k scales warp amplitude, edge blur and noise together, and the edge blur has its own multiple. At the
published level of each family both are set on the sample's photos: for each blur multiple tried the k whose
mean AbsRel is the published one (bisection), and of those the blur whose delta1 is nearest the published delta1
(blur makes the large errors at object edges that delta1 counts; benchmarks/lib/depth_degradation.py). The other levels keep
that blur and scale the AbsRel. Errors are measured the way the figures were: relative depth after the least-squares
scale-and-shift fit in disparity, metric depth as it is. Depth Anything V2 (Yang et al. 2024, arXiv 2406.09414) reports
for ViT-S on NYU-D: zero-shot relative depth AbsRel 0.053, delta1 0.973 (Table 2); metric depth fine-tuned on NYU-D
AbsRel 0.073, delta1 0.961. The metric checkpoint used here is fine-tuned on Hypersim, so on real photos it is zero-shot
and likely worse: the 2x levels stand for that.

Scores, per level, against the planes found on the true depth ("true placement planes"):
- plane recall: true planes (>= 0.5 % of the photo) overlapped by a plane of the degraded depth (overlap of their
  support pixels >= half the smaller one); for the sample also the recall of its true support surfaces;
- normal error: angle between each found true plane's normal and its degraded match's;
- object-size error: at every placement point of the degraded planes, |z_true / z_point - 1| (an object stood at
  the point is drawn that much too large or small); for relative depth also with the photo's true scale, which
  separates the camera-height prior from the rest;
- on support (sample): placement points whose pixel is a true support surface; false planes: planes in photos
  whose true depth has none;
- up wrong: photos (of those with true planes) whose up axis, as the planes search chooses it, lies more than
  15 degrees from the one it chooses on the true depth: their horizontal surfaces are then missed whole
  (scores: benchmarks/lib/plane_matching.py).
Sensitivity rows (metric, the default model's kind): the same published AbsRel with less edge blur and more warp
(delta1 then misses the published one); the calibrated level searched with a looser plane support
(planes.plane_distance_rel 0.04 instead of 0.02) and without growing the support over the photo's colours; and
the calibrated level drawn with two other degradation seeds (stability).

--speed: seconds per 640x480 photo of a full-size randomly initialised DepthAnything of the default checkpoint's
architecture (24.8 M parameters) through bg_depth, on 1 and 2 CPU threads, against the planes stage on the same
photo. Writes benchmarks/results/mono_depth.md and mono_depth/mono_depth.json.
"""
from __future__ import annotations

import argparse
import json
import logging
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from benchmarks.lib.depth_degradation import PUBLISHED, calibrate, degrade, depth_errors, knob_for
from benchmarks.lib.plane_matching import per_photo, score, summarise
from stages.app.pipeline import build_graph
from stages.bg_depth import run as bg_depth
from stages.engine.context import Context
from stages.engine.scheduler import Engine
from stages.lib.depth.formats import read_sidecar_depth
from stages.lib.geometry import fov_intrinsics
from stages.lib.imageio import load_photo
from stages.lib.planes.search import find_placement_planes
from stages.lib.planes.search_config import PlaneSearchConfig
from stages.records import sample_layout
from stages.records.depth import DepthRecord
from tests.factories.configs import REAL, ROOT, compose_cfg

log = logging.getLogger("benchmarks.mono_depth")
RESULTS = Path(__file__).resolve().parent / "results"
REAL_RGBD = {"TUM": ("TUM_color.png", "TUM_depth.png"), "NYU": ("NYU_color.ppm", "NYU_depth.pgm"),
             "SUN": ("SUN_color.jpg", "SUN_depth.png")}
LEVELS = [("relative", "affine only", 0.0), ("relative", "realistic", 1.0), ("relative", "2x", 2.0),
          ("metric", "realistic", 1.0), ("metric", "2x", 2.0)]  # (family, level, multiple of the published AbsRel)
TARGETS = {"recall": 0.90, "normal_deg": 5.0, "size": 0.15}


@dataclass
class Photo:
    """A photo with its true (measured) depth [H, W] metres, K [3, 3] and, for the sample, its support [H, W]."""

    name: str
    image: Path
    depth: np.ndarray
    K: np.ndarray
    support: np.ndarray | None = None


# ------------------------------------------------------------------------------------------ scoring

def sidecar_name(family: str) -> str:
    """The sidecar file name suffix bg_depth reads a degraded map of `family` from."""
    return ".depth.disparity.npy" if family == "relative" else ".depth.npy"


def planes_from(photo: Photo, values: np.ndarray, suffix: str, work: Path,
                search: PlaneSearchConfig = PlaneSearchConfig()) -> tuple[DepthRecord, dict]:
    """bg_depth (the stage, on `values` saved as the sidecar `<name><suffix>` beside a copy of the photo) and the
    planes search with `search`; (its depth record, the search's result with support labels)."""
    work.mkdir(parents=True)
    image = work / f"{photo.name}.png"
    rgb = load_photo(photo.image)                                       # [H, W, 3] uint8
    cv2.imwrite(str(image), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    sidecar = work / f"{photo.name}{suffix}"
    np.save(sidecar, values.astype(np.float32))
    out = work / "bg_depth"
    out.mkdir()
    bg_depth.run(Context("bg_depth", photo.name, {"K": photo.K.tolist()}, {"image": image, "depth": sidecar}, out))
    record = DepthRecord.read(out)
    return record, find_placement_planes(record.depth, record.K, search, np.random.default_rng(0), rgb)


def run_level(photos: list[Photo], truths: dict, level: dict, seed: int, work: Path) -> list[dict]:
    """Every photo degraded at the level's (k, edge blur), through bg_depth and the level's planes search, scored;
    a row each."""
    rows, family = [], level["family"]
    for index, photo in enumerate(photos):
        values, draws = degrade(photo.depth, family, level["k"], level["edge_blur"], np.random.default_rng([seed, index]))
        record, found = planes_from(photo, values, sidecar_name(family), work / photo.name, level["search"])
        row = score(photo.depth, photo.support, truths[photo.name], found, record.depth)
        row["abs_rel"], row["delta1"] = depth_errors(values, photo.depth, family)
        valid = (photo.depth > 0) & (record.depth > 0)
        row["scale_ratio"] = float(np.median(record.depth[valid] / photo.depth[valid]))
        if record.recovery is not None:
            row["shift_error"] = abs(record.recovery["shift"] - draws["shift"] / (1 + draws["shift"]))
        rows.append(row)
        shutil.rmtree(work / photo.name)
    return rows


# ------------------------------------------------------------------------------------------ photos

def sample_photos(cache: Path, limit: int) -> list[Photo]:
    """The default data config's sample generic backgrounds (rendered into `cache` unless there)."""
    graph = build_graph(compose_cfg(["run.until=sample"]), ROOT)
    engine = Engine(cache)
    node = graph.nodes["sample"][0]
    if not engine.is_cached(node):
        log.warning("rendering the embedded sample into %s (a few minutes, once)", cache)
        engine.run([node])
    folder = engine.output_dir(node)
    cfg = compose_cfg([])
    photos = []
    for photo_id in sample_layout.background_ids(cfg.sample, "generic")[:limit or None]:
        depth = read_sidecar_depth(folder / sample_layout.depth("generic", photo_id))
        support = cv2.imread(str(folder / sample_layout.support("generic", photo_id)), cv2.IMREAD_UNCHANGED) > 127
        K = np.asarray(json.loads((folder / sample_layout.intrinsics("generic", photo_id)).read_text())["K"])
        photos.append(Photo(photo_id, folder / sample_layout.photo("generic", photo_id), depth, K, support))
    return photos


def real_photos(folder: Path) -> list[Photo]:
    """The real RGB-D photos with their measured depth, seen through the default 55 degree camera."""
    photos = []
    for name, (color, depth) in REAL_RGBD.items():
        if (folder / color).is_file():
            measured = read_sidecar_depth(folder / depth)
            photos.append(Photo(name, folder / color, measured, fov_intrinsics(measured.shape[1], measured.shape[0])))
    return photos


def true_planes(photos: list[Photo], work: Path) -> dict[str, dict]:
    """The planes search on each photo's true depth (through bg_depth as a metric sidecar)."""
    truths = {}
    for photo in photos:
        _, truths[photo.name] = planes_from(photo, photo.depth, ".depth.npy", work / photo.name)
        shutil.rmtree(work / photo.name)
    return truths


# ------------------------------------------------------------------------------------------ speed

def speed(work: Path, repeat: int = 3) -> dict:
    """Seconds per 640x480 photo of a full-size random DepthAnything (the default checkpoint's architecture)
    through bg_depth on 1 and 2 threads, and of the relative recovery, against the planes stage on the photo."""
    import torch

    from stages.planes import run as planes
    from tests.factories.depth_models import full_size_config, save_model
    from tests.factories.rooms import affine_disparity, room_depth

    folder = save_model(work / "full_size_metric", full_size_config("metric"))
    depth, _, _ = room_depth(640, 480)
    image = work / "room.png"
    cv2.imwrite(str(image), np.random.default_rng(0).integers(0, 255, (480, 640, 3), dtype=np.uint8))
    np.save(work / "room.depth.disparity.npy", affine_disparity(depth, 3.0, 0.2))
    figures: dict = {"parameters_m": 24.8}
    before = torch.get_num_threads()

    def timed(label: str, params: dict, inputs: dict, stage=bg_depth) -> None:
        times = []
        for attempt in range(repeat):
            out = work / f"{label}_{attempt}"
            out.mkdir()
            started = time.perf_counter()
            stage.run(Context(stage.__name__.rpartition(".")[2], "room", params, inputs, out))
            times.append(time.perf_counter() - started)
        figures[label] = {"best_s": round(min(times), 3), "runs_s": [round(t, 3) for t in times]}

    for threads in (1, 2):
        torch.set_num_threads(threads)
        timed(f"model_{threads}_threads", {"provider": "model", "model": str(folder)}, {"image": image})
    torch.set_num_threads(before)
    timed("relative_recovery", {}, {"image": image, "depth": work / "room.depth.disparity.npy"})
    timed("planes", {}, {"image": image, "depth": work / "relative_recovery_0"}, planes)
    figures["model_over_planes"] = round(figures["model_1_threads"]["best_s"] / figures["planes"]["best_s"], 2)
    return figures


# ------------------------------------------------------------------------------------------ report

def fmt(value, digits: int = 3, percent: bool = False) -> str:
    if value is None:
        return "-"
    return f"{100 * value:.1f} %" if percent else f"{value:.{digits}f}"


def table(title: str, levels: list[dict], sample: bool) -> list[str]:
    """A markdown table of the levels' figures."""
    lines = [f"### {title}", "", "| depth | k, edge blur | AbsRel / delta1 (published) | plane recall | " +
             ("support recall | " if sample else "") + "normal err. median / p90 | size err. median | "
             "size err., true scale | " + ("on support | false planes | " if sample else "") +
             "up wrong | scale (median, range) | shift err. |",
             "|---|---|---|---|" + ("---|" if sample else "") + "---|---|---|" + ("---|---|" if sample else "") +
             "---|---|---|"]
    for level in levels:
        s = level["scores"]
        published = PUBLISHED.get(level["family"], {}) if level["multiple"] else {}
        target = f" ({level['multiple'] * published['abs_rel']:.3f} / {published['delta1']:.3f})" if published else ""
        lines.append(
            f"| {level['label']} | {level['k']:.2f} x{level['edge_blur']:g} | {s['abs_rel']:.3f} / {s['delta1']:.3f}{target} | "
            f"{fmt(s['recall'], percent=True)} ({s['true_planes']}) | "
            + (f"{fmt(s['support_recall'], percent=True)} | " if sample else "")
            + f"{fmt(s['normal_deg_median'], 1)} / {fmt(s['normal_deg_p90'], 1)} deg | {fmt(s['size_median'], percent=True)} | "
            f"{fmt(s['size_true_scale_median'], percent=True)} | "
            + (f"{fmt(s['on_support'], percent=True)} | {s['false_planes']} | " if sample else "")
            + f"{s['up_wrong']} / {s['photos_with_planes']} | {s['scale_ratio_median']:.2f} ({s['scale_ratio_range'][0]:.2f}-{s['scale_ratio_range'][1]:.2f}) | "
            f"{fmt(s['shift_error'])} |")
    return lines


def met(scores: dict) -> str:
    """Which of TARGETS a level's scores meet."""
    checks = [("recall >= 90 %", scores["recall"] is not None and scores["recall"] >= TARGETS["recall"]),
              ("normal error <= 5 deg", scores["normal_deg_median"] is not None
               and scores["normal_deg_median"] <= TARGETS["normal_deg"]),
              ("size error <= 15 %", scores["size_median"] is not None and scores["size_median"] <= TARGETS["size"])]
    return ", ".join(f"{name}: {'met' if ok else 'NOT met'}" for name, ok in checks)


def report(results: dict, command: str) -> str:
    """mono_depth.md."""
    lines = ["# Placement from monocular depth (degraded true depth, no weights)", "", f"`{command}`", "",
             f"{results['date']}, {results['seconds']:.0f} s. Method, levels and scores: the docstring of "
             "benchmarks/mono_depth.py. Planes of the degraded depth against those of the true depth (k: the "
             "degradation knob found so that AbsRel matches the published figure times the level's multiple; "
             "scale: median recovered / true depth per photo).", ""]
    for part, title in (("sample", "The sample's generic backgrounds"), ("real", "The real RGB-D photos (TUM, NYU, SUN)")):
        if part in results:
            lines += table(title, results[part], part == "sample") + [""]
            for level in results[part]:
                if level["multiple"] == 1.0 and not level["sensitivity"]:
                    lines.append(f"- {level['label']}: {met(level['scores'])}")
            lines.append("")
    if "speed" in results:
        s = results["speed"]
        lines += ["### CPU seconds per photo (640x480, fed at 518x686)", "",
                  "| | best of 3 |", "|---|---|",
                  f"| full-size DepthAnything (random weights, 24.8 M), 1 thread | {s['model_1_threads']['best_s']:.2f} s |",
                  f"| the same, 2 threads | {s['model_2_threads']['best_s']:.2f} s |",
                  f"| recovery of relative depth (disparity sidecar) | {s['relative_recovery']['best_s']:.2f} s |",
                  f"| planes stage on the same photo (reference) | {s['planes']['best_s']:.2f} s |", "",
                  f"The model on one thread takes {s['model_over_planes']}x the planes stage.", ""]
    return "\n".join(lines)


def write_backgrounds(photos: list[Photo], root: Path, knobs: dict, seed: int) -> None:
    """The sample's generic backgrounds with their depth degraded at each family's published level, for
    +experiment=mono_depth: root/metric/<id>.png + <id>.depth.npy (metres) and root/relative/<id>.png +
    <id>.depth.disparity.npy, the same draws as the benchmark's; no intrinsics file (a user's photo has none; the
    55 degree default is the sample's camera)."""
    for family in ("metric", "relative"):
        folder = root / family
        folder.mkdir(parents=True, exist_ok=True)
        k, blur = knobs[family]
        for index, photo in enumerate(photos):
            shutil.copy(photo.image, folder / f"{photo.name}.png")
            values, _ = degrade(photo.depth, family, k, blur, np.random.default_rng([seed, index]))
            np.save(folder / f"{photo.name}{sidecar_name(family)}", values)
        (folder / "degradation.json").write_text(json.dumps(
            {"family": family, "k": k, "edge_blur": blur, "seed": seed, "photos": len(photos),
             "published": PUBLISHED[family]}, indent=2))
        log.info("wrote %d %s backgrounds into %s (k %.3f, edge blur x%g)", len(photos), family, folder, k, blur)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cache", type=Path, default=ROOT / "outputs" / "cache", help="the DAG's cache (the sample)")
    parser.add_argument("--photos", type=int, default=0, help="sample backgrounds to use (0 = all)")
    parser.add_argument("--real", type=Path, default=REAL / "rgbd")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--speed", action="store_true", help="also time a full-size random model (writes 100 MB)")
    parser.add_argument("--write-backgrounds", type=Path,
                        help="only write the sample's backgrounds with realistic metric and relative depth here")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    logging.getLogger("stages").setLevel(logging.ERROR)
    started = time.time()
    photos = sample_photos(args.cache, args.photos)
    depths = [photo.depth for photo in photos]
    fits = {family: calibrate(depths, family, args.seed) for family in PUBLISHED}
    knobs = {family: next(iter(blurs.items()))[::-1] for family, blurs in fits.items()}  # (k, blur) of the best
    if args.write_backgrounds is not None:
        write_backgrounds(photos, args.write_backgrounds, knobs, args.seed)
        return
    levels = []
    for family, label, multiple in LEVELS:
        k, blur = (0.0, 1.0) if not multiple else knobs[family]
        if multiple not in (0.0, 1.0):
            k = knob_for(depths, family, blur, multiple * PUBLISHED[family]["abs_rel"], args.seed)
        levels.append({"family": family, "label": f"{family}, {label}", "multiple": multiple, "k": k,
                       "edge_blur": blur, "search": PlaneSearchConfig(), "sensitivity": False})
    for blur, k in sorted(fits["metric"].items()):  # the same AbsRel with less of it in edge blur, more in warps
        if blur >= knobs["metric"][1]:
            continue
        levels.append({"family": "metric", "label": f"metric, realistic AbsRel, edge blur x{blur:g}", "multiple": 1.0,
                       "k": k, "edge_blur": blur, "search": PlaneSearchConfig(), "sensitivity": True})
    for label, search, seed in (("planes.plane_distance_rel=0.04", PlaneSearchConfig(plane_distance_rel=0.04), args.seed),
                                ("no colour growth (planes.colour_grow_steps=0)", PlaneSearchConfig(colour_grow_steps=0),
                                 args.seed),
                                (f"degradation seed {args.seed + 1}", PlaneSearchConfig(), args.seed + 1),
                                (f"degradation seed {args.seed + 2}", PlaneSearchConfig(), args.seed + 2)):
        levels.append({"family": "metric", "label": f"metric, realistic, {label}", "multiple": 1.0, "seed": seed,
                       "k": knobs["metric"][0], "edge_blur": knobs["metric"][1], "search": search, "sensitivity": True})
    results: dict = {"date": time.strftime("%Y-%m-%d %H:%M"), "command": "python -m benchmarks.mono_depth"}
    with tempfile.TemporaryDirectory() as scratch:
        for part, chosen in (("sample", photos), ("real", real_photos(args.real))):
            if not chosen:
                continue
            truths = true_planes(chosen, Path(scratch) / part / "truth")
            results[part] = []
            for number, level in enumerate(levels):
                log.info("%s: %s (k %.2f, edge blur x%g)", part, level["label"], level["k"], level["edge_blur"])
                rows = run_level(chosen, truths, level, level.get("seed", args.seed), Path(scratch) / part / str(number))
                results[part].append({**{key: value for key, value in level.items() if key != "search"},
                                      "plane_distance_rel": level["search"].plane_distance_rel,
                                      "scores": summarise(rows), "photos": [per_photo(r) for r in rows]})
        if args.speed:
            results["speed"] = speed(Path(scratch) / "speed")
    results["seconds"] = time.time() - started
    command = "python -m benchmarks.mono_depth" + (" --speed" if args.speed else "") + \
              (f" --photos {args.photos}" if args.photos else "")
    (RESULTS / "mono_depth").mkdir(parents=True, exist_ok=True)
    (RESULTS / "mono_depth" / "mono_depth.json").write_text(json.dumps(results, indent=1, default=float))
    (RESULTS / "mono_depth.md").write_text(report(results, command))
    print(report(results, command))


if __name__ == "__main__":
    main()
