"""Benchmark of compose's cast shadows and relighting (issue 32).

1. Speed, for the sample's five objects (its extract nodes) on its 40 backgrounds (the default run's dataset),
   with the effects off and on, on the same images (an image's placements do not depend on the effects): the
   compose stage's images/s, alternating off / on `--repeats` times, and its ratio; and the CPU time of each
   image in one process (time.process_time, off and on in turn per image: what a loaded machine changes least).
2. Light direction: the azimuth `light_direction: photo` takes from each sample background against the
   directions of the lamp and window light that its ray tracer lit that photo with (irradiance-weighted, at the
   centre of the photo's largest plane), and against random azimuths.
3. Figure: the same placements without and with the effects, benchmarks/results/compose_effects/compose_effects.jpg.

Needs a run's cache holding the sample's nodes up to extract and planes (`python dag.py run.until=planes`; the
default cache is outputs/cache); the real plant rows need ../shared/real.

Usage: OMP_NUM_THREADS=1 python -m benchmarks.compose_effects --cache outputs/cache [--images 200] [--workers 2]
Prints one JSON object and writes it to benchmarks/results/compose_effects/compose_effects.json.
"""
from __future__ import annotations

import argparse
import json
import math
import shutil
import time
from collections import Counter
from pathlib import Path

import cv2
import numpy as np
import torch

from benchmarks.lib.real_plant import PLANT_HEIGHT_M, TUM_K, plant_extract, run_stage
from stages.bg_depth import run as bg_depth
from stages.compose import run as compose
from stages.compose.spec import ComposeConfig
from stages.contract.fan_in import fan_in
from stages.lib.composition.backgrounds import load_background
from stages.lib.composition.light import horizontal, photo_light
from stages.lib.sample_scene.rooms import make_room, scene_lighting
from stages.planes import run as planes
from stages.records.coco_dataset import CocoDataset
from tests.factories.configs import REAL

RESULTS = Path(__file__).resolve().parent / "results"
OFF = {"shadow": False, "relight": "none"}  # the paper's compose
FIGURE_ROWS = 4  # sample images in the figure (plus 2 of the real plant when present)
FIGURE_TILE = (480, 360)  # a crop around an image's objects, 4:3
MIN_OBJECT_PX = 40  # the figure shows images with a plane-placed object at least this tall


def source_sample(cache: Path, manifest: dict) -> str | None:
    """The key of the sample node a cached node's inputs lead back to (through splat_train, sfm and frames)."""
    for value in map(str, manifest["inputs"].values()):
        if "/" in value:  # a file of a sample node: <key>/...
            return value.split("/", 1)[0]
        for upstream in ("splat_train", "sfm", "frames"):
            if (path := cache / upstream / value / "manifest.json").is_file():
                return source_sample(cache, json.loads(path.read_text()))
    return None


def cached_nodes(cache: Path, stage: str, sample: str | None = None) -> dict[str, tuple[Path, dict]]:
    """{item: (folder, manifest)} of a stage's finished nodes in a run cache, made from the sample node `sample`
    when given (a cache can hold several samples), the latest per item."""
    found: dict[str, tuple[Path, dict]] = {}
    for manifest_path in sorted((cache / stage).glob("*/manifest.json")):
        manifest = json.loads(manifest_path.read_text())
        item = manifest["item"]
        if sample is not None and source_sample(cache, manifest) != sample:
            continue
        if item not in found or manifest["finished"] > found[item][1]["finished"]:
            found[item] = (manifest_path.parent, manifest)
    return found


def sample_inputs(cache: Path) -> tuple[dict[str, Path], list[dict], dict]:
    """compose's inputs for the sample's objects and backgrounds in a run cache (the sample node with the most
    extract nodes, then planes nodes), the objects [{name, height_m}] and the sample's config."""
    made_from = {stage: Counter(source_sample(cache, json.loads(path.read_text()))
                                for path in (cache / stage).glob("*/manifest.json")) for stage in ("extract", "planes")}
    if not made_from["planes"] or not made_from["extract"]:
        raise SystemExit(f"{cache}: no planes or extract node (run `python dag.py run.until=planes` first)")
    sample = max(made_from["planes"], key=lambda key: (made_from["extract"][key], made_from["planes"][key]))
    config = json.loads((cache / "sample" / sample / "sample.json").read_text())["config"]
    extracts = cached_nodes(cache, "extract", sample)
    objects = [spec for spec in config["objects"] if spec["name"] in extracts]
    photos = {item: {"background": cache / "sample" / manifest["inputs"]["image"], "planes": path,
                     "depth": cache / "bg_depth" / manifest["inputs"]["depth"]}
              for item, (path, manifest) in cached_nodes(cache, "planes", sample).items()}
    inputs = {**fan_in({spec["name"]: {"object": extracts[spec["name"]][0]} for spec in objects},
                       compose.INPUTS.object_kinds), **fan_in(photos, compose.INPUTS.photo_kinds)}
    return inputs, objects, config


def speed(root: Path, inputs: dict, objects: list[dict], images: int, workers: int, repeats: int) -> dict:
    """images/s of compose with the effects off and on (alternating, `repeats` times each; mean) and on / off."""
    rates: dict[str, list[float]] = {"off": [], "on": []}
    for repeat in range(repeats):
        for name, settings in (("off", OFF), ("on", {})):
            params = {"objects": objects, "num_images": images, "workers": workers, "preview_count": 0, **settings}
            started = time.perf_counter()
            run_stage(compose, "compose", params, inputs, root / f"{name}{repeat}")
            rates[name].append(images / (time.perf_counter() - started))
    off, on = float(np.mean(rates["off"])), float(np.mean(rates["on"]))
    return {"images": images, "workers": workers, "images_per_s_off": [round(r, 2) for r in rates["off"]],
            "images_per_s_on": [round(r, 2) for r in rates["on"]], "ratio_on_off": round(on / off, 3)}


def cpu_per_image(root: Path, inputs: dict, objects: list[dict], images: int) -> dict:
    """CPU milliseconds per image (mean; asset loading excluded) of compose_image with the effects off and on,
    one process, the two in turn for each image, and on / off."""
    assets = {name: compose.load_assets(ComposeConfig(objects=objects, num_images=images, **settings), 0, inputs)
              for name, settings in (("off", OFF), ("on", {}))}
    seconds = {"off": 0.0, "on": 0.0}
    for index in range(images):
        for name in (("off", "on") if index % 2 else ("on", "off")):
            (root / name).mkdir(parents=True, exist_ok=True)
            started = time.process_time()
            compose.compose_image(assets[name], index, root / name)
            seconds[name] += time.process_time() - started
    return {"images": images, "cpu_ms_off": round(1000 * seconds["off"] / images, 1),
            "cpu_ms_on": round(1000 * seconds["on"] / images, 1),
            "ratio_on_off": round(seconds["on"] / seconds["off"], 3)}


def light_accuracy(config: dict, inputs: dict) -> dict:
    """Azimuth error (degrees) of the photo light estimate against the sample's lights, per room background.

    The lights are rebuilt as stages/sample/run.py made them: room k of the generic family from the generator seeded
    (seed, 21, k), the photo's lighting from (seed, 22, photo index); both are Open3D-free geometry.
    """
    errors, random_errors, missing = [], [], []
    rng = np.random.default_rng(0)
    for key, image in sorted(inputs.items()):
        if not key.startswith("background:"):
            continue
        bg_id = key.split(":", 1)[1]
        meta = json.loads((image.with_suffix(".json")).read_text())
        if meta.get("kind") != "room":
            continue
        background = load_background(bg_id, image, inputs[f"planes:{bg_id}"], inputs[f"depth:{bg_id}"], 5)
        if not background.planes:
            continue
        room = make_room(np.random.default_rng([config["seed"], 21, int(meta["room"].removeprefix("generic"))]))
        lighting = scene_lighting(room, np.random.default_rng([config["seed"], 22, int(bg_id.removeprefix("bg"))]))
        viewmat = np.asarray(meta["viewmat"])
        estimate = photo_light(background.image, background.K, background.planes)
        centre = max(background.planes, key=lambda plane: plane.area).points.mean(0)
        truth = np.zeros(3)
        for light in lighting.lights:
            offset = viewmat[:3, :3] @ light.position + viewmat[:3, 3] - centre
            distance = float(np.linalg.norm(offset))
            irradiance = float(light.colour.mean()) * max(0.0, float(offset @ estimate.up) / distance) / distance ** 2
            flat = horizontal(offset, estimate.up)
            truth += 0.0 if flat is None else irradiance * flat
        truth = horizontal(truth, estimate.up)
        if estimate.towards_light is None:
            missing.append(bg_id)
            continue
        errors.append(math.degrees(math.acos(float(np.clip(truth @ estimate.towards_light, -1.0, 1.0)))))
        guess = horizontal(rng.normal(size=3), estimate.up)
        random_errors.append(math.degrees(math.acos(float(np.clip(truth @ guess, -1.0, 1.0)))))
    errors_array = np.asarray(errors)
    return {"photos": len(errors) + len(missing), "without_estimate": missing,
            "median_error_deg": round(float(np.median(errors_array)), 1),
            "mean_error_deg": round(float(errors_array.mean()), 1),
            "within_45_deg": round(float((errors_array < 45).mean()), 3),
            "random_mean_error_deg": round(float(np.mean(random_errors)), 1)}


def object_crop(boxes: list[list[float]], width: int, height: int) -> tuple[int, int, int, int]:
    """A 4:3 window (x0, y0, x1, y1) around COCO boxes [x, y, w, h], 2.5 times their extent, inside the image."""
    x0, y0 = min(b[0] for b in boxes), min(b[1] for b in boxes)
    x1, y1 = max(b[0] + b[2] for b in boxes), max(b[1] + b[3] for b in boxes)
    crop_h = min(height, max(2.5 * (y1 - y0), 2.5 * (x1 - x0) * 3 / 4, 160.0))
    crop_w = min(width, crop_h * 4 / 3)
    left = int(np.clip((x0 + x1) / 2 - crop_w / 2, 0, width - crop_w))
    top = int(np.clip((y0 + y1) / 2 - crop_h / 2, 0, height - crop_h))
    return left, top, left + int(crop_w), top + int(crop_h)


def pairs(root: Path, inputs: dict, objects: list[dict], seed: int, count: int, candidates: int) -> list[np.ndarray]:
    """[off | on] rows (BGR) of the first `count` images, among `candidates`, with a plane-placed object at least
    MIN_OBJECT_PX tall and none cut by the image's border: both cropped around the image's objects."""
    rows, outs = [], {}
    for name, settings in (("off", OFF), ("on", {})):
        outs[name] = root / name
        params = {"objects": objects, "num_images": candidates, "workers": 1, "preview_count": 0, **settings}
        run_stage(compose, "compose", params, inputs, outs[name], seed)
    coco = CocoDataset.read(outs["on"])
    cut = {ann["image_id"] for ann in coco.annotations if ann["bbox"][0] < 1 or ann["bbox"][1] < 1
           or ann["bbox"][0] + ann["bbox"][2] > coco.images[0]["width"] - 1}  # cut by the image border
    shown = {ann["image_id"] for ann in coco.annotations
             if ann["placement"] == "plane" and ann["bbox"][3] >= MIN_OBJECT_PX} - cut
    for image in [image for image in coco.images if image["id"] in shown][:count]:
        left, top, right, bottom = object_crop([ann["bbox"] for ann in coco.annotations
                                                if ann["image_id"] == image["id"]], image["width"], image["height"])
        tiles = [cv2.imread(str(CocoDataset.image_file(outs[name], image)))[top:bottom, left:right]
                 for name in ("off", "on")]
        rows.append(np.concatenate([cv2.resize(tile, FIGURE_TILE, interpolation=cv2.INTER_CUBIC) for tile in tiles],
                                   axis=1))
    return rows


def effects_figure(root: Path, sample_rows: list[np.ndarray]) -> Path:
    """benchmarks/results/compose_effects/compose_effects.jpg: the sample rows, then two of the real plant on TUM when
    present."""
    rows = list(sample_rows)
    if (REAL / "splats" / "plant.splat").is_file():
        photo = REAL / "rgbd" / "TUM_color.png"
        run_stage(bg_depth, "bg_depth", {"provider": "sidecar", "sidecar_format": "tum", "K": TUM_K},
                  {"image": photo, "depth": REAL / "rgbd" / "TUM_depth.png"}, root / "tum_depth")
        run_stage(planes, "planes", {}, {"image": photo, "depth": root / "tum_depth"}, root / "tum_planes")
        inputs = {**fan_in({"plant": {"object": plant_extract(root / "plant")}}, compose.INPUTS.object_kinds),
                  **fan_in({"tum": {"background": photo, "planes": root / "tum_planes", "depth": root / "tum_depth"}},
                           compose.INPUTS.photo_kinds)}
        rows += pairs(root / "tum", inputs, [{"name": "plant", "height_m": PLANT_HEIGHT_M}], 1, 2, 6)
    width = max(row.shape[1] for row in rows)
    header = np.full((28, width, 3), 255, np.uint8)
    for text, x in (("paper: no shadow, capture light", 8), ("issue 32: shadow + relight", width // 2 + 8)):
        cv2.putText(header, text, (x, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
    path = RESULTS / "compose_effects" / "compose_effects.jpg"
    cv2.imwrite(str(path), np.concatenate([header, *rows], axis=0), [cv2.IMWRITE_JPEG_QUALITY, 88])
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cache", type=Path, default=Path("outputs/cache"))
    parser.add_argument("--images", type=int, default=200)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path("/tmp/compose_effects_bench"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    shutil.rmtree(args.out, ignore_errors=True)
    inputs, objects, config = sample_inputs(args.cache)
    result = {"sample_objects": [spec["name"] for spec in objects],
              "speed_sample": speed(args.out / "speed", inputs, objects, args.images, args.workers, args.repeats),
              "cpu_per_image": cpu_per_image(args.out / "cpu", inputs, objects, args.images),
              "light_direction": light_accuracy(config, inputs)}
    rows = pairs(args.out / "figure", inputs, objects, 3, FIGURE_ROWS, 8 * FIGURE_ROWS)
    result["figure"] = str(effects_figure(args.out, rows))
    (RESULTS / "compose_effects" / "compose_effects.json").write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
