"""Convert a COCO dataset folder (compose, cut_and_paste, a test set) for other trainers: YOLO or BOP.

    python -m stages.app.convert DATASET --format yolo-segment|yolo-detect|bop --out OUT [--val FOLDER] [--test FOLDER]
                            [--model NAME=OBJECT_PLY ...]

DATASET and the --val / --test folders hold images/ + annotations.json; OUT must be new or empty. YOLO writes
one dataset (train = DATASET) with data.yaml for Ultralytics; BOP needs a compose dataset (poses) and writes
its models when it finds the objects' object.ply in the engine's cache (or from --model). Prints a JSON
summary and writes it to OUT/convert.json (docs/stage_contracts.md, section "Dataset formats").
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from stages.contract.errors import StageError
from stages.engine.cache_entry import input_path
from stages.lib.composition.placement import MetricFrame, model_points
from stages.lib.dataset_formats.bop import export_bop
from stages.lib.dataset_formats.yolo import export_yolo
from stages.lib.gaussians.ply import read_ply
from stages.records.coco_dataset import CocoDataset

log = logging.getLogger("stages.app.convert")
FORMATS = ("yolo-segment", "yolo-detect", "bop")
SUMMARY = "convert.json"


def object_model_points(dataset_folder: Path, dataset: CocoDataset, name: str,
                        model_file: Path | None = None) -> np.ndarray:
    """The model points [N, 3] of object `name` (the means of its Gaussians at least MODEL_OPACITY opaque)
    in the metric frame of the dataset's poses (metres), from its object.ply (`model_file`, else the one of the
    dataset's input info["object_models"][name]["input"], found through the engine's cache) and the map in
    info["object_models"]. StageError when the dataset has no such map or the file cannot be found."""
    models = dataset.info.get("object_models", {})
    source = Path(dataset_folder) / CocoDataset.JSON
    if name not in models:
        raise StageError(f"{source}: info.object_models has no {name!r} (a compose dataset lists its objects' "
                         "models there)")
    model = models[name]
    if model_file is None:
        folder = input_path(dataset_folder, model["input"])
        if folder is None:
            raise StageError(f"{source}: cannot find the model of {name!r} ({model['input']}, {model['file']}): "
                             f"the dataset is not in the engine's cache; give the object.ply file")
        model_file = folder / model["file"]
    gaussians = read_ply(model_file)
    return MetricFrame.from_dict(model).from_model(model_points(gaussians.means.numpy(), gaussians.opacities.numpy()))


def bop_models(folder: Path, dataset: CocoDataset, given: dict[str, Path]) -> dict:
    """{object name: model points [N, 3] in metres} of the objects of `dataset` (read from `folder`) whose
    object.ply is given or found in the cache; the others are named in a warning."""
    models = {}
    for name in dataset.info.get("object_models", {}):
        try:
            models[name] = object_model_points(folder, dataset, name, given.get(name))
        except StageError as error:
            log.warning("no BOP model for %s: %s", name, error)
    return models


def export(dataset: Path, fmt: str, out: Path, val: Path | None = None, test: Path | None = None,
           models: dict[str, Path] | None = None) -> dict:
    """Export `dataset` (and the val / test folders, YOLO only) in format `fmt` into `out`; returns the summary
    also written to out/convert.json."""
    if fmt not in FORMATS:
        raise StageError(f"export format must be one of {FORMATS}, not {fmt!r}")
    if out.exists() and any(out.iterdir()):
        raise StageError(f"export folder {out} is not empty; give a new or empty folder")
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    progress = lambda items: tqdm(items, desc=f"export {fmt}", leave=False)  # noqa: E731
    if fmt == "bop":
        if val is not None or test is not None:
            raise StageError("the BOP export takes one compose dataset; --val and --test are for YOLO")
        coco = CocoDataset.read(dataset)
        summary = export_bop(dataset, coco, out, models=bop_models(dataset, coco, models or {}), progress=progress)
    else:
        splits = {"train": dataset, **({"val": val} if val else {}), **({"test": test} if test else {})}
        summary = export_yolo(splits, out, fmt.split("-")[1], progress)
    summary = {"format": fmt, "source": str(dataset), **summary, "seconds": round(time.perf_counter() - started, 3)}
    (out / SUMMARY).write_text(json.dumps(summary, indent=1))
    return summary


def model_argument(text: str) -> tuple[str, Path]:
    """NAME=PATH of --model."""
    name, _, path = text.partition("=")
    if not name or not path:
        raise argparse.ArgumentTypeError(f"--model takes NAME=PATH/object.ply, not {text!r}")
    return name, Path(path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path, help="a COCO dataset folder (images/ + annotations.json)")
    parser.add_argument("--format", required=True, choices=FORMATS, dest="fmt")
    parser.add_argument("--out", required=True, type=Path, help="a new or empty folder")
    parser.add_argument("--val", type=Path, help="YOLO: a COCO folder for the val split (default: train)")
    parser.add_argument("--test", type=Path, help="YOLO: a COCO folder for the test split")
    parser.add_argument("--model", type=model_argument, action="append", default=[],
                        help="BOP: NAME=PATH of an object's object.ply when the dataset is not in the cache")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        summary = export(args.dataset, args.fmt, args.out, args.val, args.test, dict(args.model))
    except StageError as error:
        log.error("%s", error)
        return 1
    log.info("%s", json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
