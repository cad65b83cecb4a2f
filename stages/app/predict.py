"""predict: a trained detector on your photos, folders and videos, without writing Python (docs/predict.md).

    python -m stages.app.predict MODEL SOURCE [--out DIR] [--conf 0.5] [--classes A B] [--max-det N] [--masks]
                             [--crops] [--no-overlays] [--device auto|cpu|cuda] [--threads N]

MODEL is a model folder (written by `python dag.py run.action=predict predict.export=DIR`) or its model.onnx (run by
onnxruntime on the CPU); SOURCE a photo, a folder, a glob, a video or a .txt list of photos. Neither Hydra nor the
cache is needed. `python dag.py run.action=predict predict.source=SOURCE` runs the detector of the current config
from the cache instead, with the config's eval settings (`predict_action`, which dag.py calls).
"""
from __future__ import annotations

import stages  # noqa: F401  (first: sets OMP_WAIT_POLICY before torch loads libgomp, see stages/__init__.py)

import argparse
import json
import logging
import os
import sys
from dataclasses import asdict
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from tqdm.auto import tqdm

from stages.contract.errors import StageError
from stages.engine.cache_entry import METRICS, Outcome
from stages.lib.detection.backends import TorchDetector
from stages.lib.detection.model import load_detector
from stages.lib.detection.model_card import check_text
from stages.lib.detection.model_folder import LoadedModel, open_model, write_model_folder
from stages.lib.detection.postprocess import PostProcessing
from stages.lib.detection.predict_config import PredictConfig
from stages.lib.detection.predict_outputs import PredictionWriter
from stages.lib.detection.predictor import predict_source, summary_line
from stages.lib.detection.sources import open_source, read_photo
from stages.lib.device import DEVICES, choose_device
from stages.lib.imageio import list_images
from stages.records.coco_dataset import CocoDataset

if TYPE_CHECKING:
    import numpy as np
    from omegaconf import DictConfig

    from stages.app.pipeline import Graph
    from stages.engine.scheduler import Engine

log = logging.getLogger("stages.app.predict")
OUTPUTS = Path("outputs") / "predict"  # default output folders: outputs/predict/<time>/ under the start folder


def new_output_folder(base: Path) -> Path:
    """base/outputs/predict/<time>/, with a numeric suffix when that folder exists (two calls in one second)."""
    folder = base / OUTPUTS / datetime.now().strftime("%Y-%m-%d_%H-%M-%S")
    candidate, number = folder, 1
    while candidate.exists():
        number += 1
        candidate = folder.with_name(f"{folder.name}_{number}")
    return candidate


def progress_bar(frames, total: int):
    """A progress bar on a terminal (none in logs)."""
    return tqdm(frames, total=total or None, unit="image", desc="predict", disable=None)


def run_predict(model: LoadedModel, options: PredictConfig, base: Path) -> dict:
    """Predict with `model` on options.source into options.out (relative to `base`; None: a new folder under `base`);
    prints the summary line and returns the summary (predictor.predict_source)."""
    source = open_source(options.source)
    out = base / options.out if options.out else new_output_folder(base)
    header = {"model": str(model.path), "backend": model.detector.backend, "device": model.detector.device,
              "source": str(options.source), "settings": {"conf": options.conf, "classes": options.classes,
                                                          "max_det": options.max_det, **asdict(model.post)}}
    writer = PredictionWriter(out, source, model.class_names, options, header)
    summary = predict_source(model, source, writer, options, progress_bar)
    print(summary_line(summary, out))
    return summary


def set_threads(threads: int) -> None:
    """torch's CPU threads: `threads`, 0 = all cores."""
    torch.set_num_threads(threads or os.cpu_count() or 1)


def predict_action(cfg: DictConfig, engine: Engine, graph: Graph, problems: dict, base: Path, device: str,
                   overrides: list[str]) -> int:
    """dag.py's run.action=predict: the config's detector (its train_maskrcnn node, from the cache) written as a model
    folder (predict.export) and/or run on predict.source with the config's eval settings. Returns the exit status
    (2 with the command that trains it when the detector is not cached)."""
    from omegaconf import OmegaConf

    options: PredictConfig = OmegaConf.to_object(cfg.predict)
    if not options.source and not options.export:
        log.error("run.action=predict needs predict.source=PATH (photos or a video) and/or predict.export=DIR (the "
                  "detector as a model folder)")
        return 2
    train = graph.nodes["train_maskrcnn"][0]
    outcome = engine.plan([train], problems)[-1]
    if outcome.status != "cached":
        kept = [o for o in overrides if not o.startswith(("run.action=", "run.until=", "predict.", "+predict."))]
        log.error("the detector of this config, %s (key %s), is not in the cache %s (%s); train it with:\n"
                  "  python dag.py %s", outcome.label, outcome.key, engine.cache_dir, outcome.status,
                  " ".join([*kept, "run.until=train_maskrcnn"]))
        return 2
    model_file, post = Path(outcome.path) / "model.pt", PostProcessing.of(cfg.eval)
    try:
        if options.export:
            export = base / options.export
            card, example, config_text = export_facts(cfg, engine, graph, problems, outcome, overrides)
            written = write_model_folder(export, model_file, post, card, example, config_text)
            print(f"model folder {export} ({', '.join(written['class_names'])}); model.onnx against PyTorch: "
                  f"{check_text(written['card'].get('onnx_check'))}")
        if options.source:
            set_threads(options.threads)
            model, model_cfg, names = load_detector(model_file, device)
            loaded = LoadedModel(TorchDetector(model, device), names, model_cfg.image_size, post, model_file)
            run_predict(loaded, options, base)
    except (ValueError, FileNotFoundError, StageError) as error:
        log.error("%s", error)
        return 2
    return 0


def export_facts(cfg: DictConfig, engine: Engine, graph: Graph, problems: dict, outcome: Outcome,
                 overrides: list[str]) -> tuple[dict, np.ndarray | None, str]:
    """The model card's facts of the config's detector (training, evaluation of its cached evals, source), a test
    photo to trace and check the ONNX graph on (None without a test set), and the config as YAML."""
    from omegaconf import OmegaConf

    train = graph.nodes["train_maskrcnn"][0]
    trained = json.loads((Path(outcome.path) / "train.json").read_text())
    training = {"images": trained["images"], "variant": cfg.variant.name, "generator": str(cfg.variant.generator),
                "seed": engine.seed(train), "run_seed": int(cfg.run.seed), "backbone": trained["backbone"],
                "iterations": trained["iterations"], "epochs": train.params["epochs"],
                "seconds": trained["seconds"], "device": trained["device"]}
    evaluation, example = {}, None
    evals = graph.nodes.get("eval", [])
    outcomes = {(found.stage, found.item): found for found in engine.plan(evals, problems)} if evals else {}
    for node in evals:
        found = outcomes[(node.stage.name, node.item)]
        if found.status == "cached":
            m = json.loads((Path(found.path) / METRICS).read_text())
            evaluation[node.item.partition("@")[2]] = {
                "images": m["images"], "box_AP": m["bbox"]["AP"], "box_AP50": m["bbox"]["AP50"],
                "mask_AP": m["segm"]["AP"], "mask_AP50": m["segm"]["AP50"]}
        photos = engine.input_paths(node)["testset"] / CocoDataset.IMAGES
        if example is None and photos.is_dir() and list_images(photos):
            example = read_photo(list_images(photos)[0])[0]
    source = {"command": " ".join(["python dag.py", *overrides]), "train_maskrcnn": outcome.path,
              "created": datetime.now().astimezone().isoformat(timespec="seconds")}
    return ({"training": training, "evaluation": evaluation, "source": source}, example,
            OmegaConf.to_yaml(cfg, resolve=True))


def parse_args(argv: list[str]) -> argparse.Namespace:
    defaults = PredictConfig()
    parser = argparse.ArgumentParser(prog="python -m stages.app.predict", description=__doc__.split("\n\n")[0])
    parser.add_argument("model", help="a model folder, or its model.onnx (onnxruntime, CPU)")
    parser.add_argument("source", help="a photo, a folder of photos, a glob ('photos/*.jpg'), a video (mp4, avi, mov, "
                                       "mkv) or a .txt file listing photos")
    parser.add_argument("--out", help="output folder, new or empty (default: outputs/predict/<time>/)")
    parser.add_argument("--conf", type=float, default=defaults.conf, help="lowest box score kept (default %(default)s)")
    parser.add_argument("--classes", nargs="+", metavar="NAME", help="keep these classes only")
    parser.add_argument("--max-det", type=int, default=defaults.max_det,
                        help="at most this many detections per photo, the best (default: the detector's cap)")
    parser.add_argument("--masks", action="store_true", help="one PNG per detection in masks/")
    parser.add_argument("--crops", action="store_true", help="each detection's box cut out, in crops/<class>/")
    parser.add_argument("--no-overlays", action="store_true", help="no drawn photos or video")
    parser.add_argument("--device", choices=DEVICES, default="auto", help="PyTorch's device (default %(default)s)")
    parser.add_argument("--threads", type=int, default=defaults.threads, help="CPU threads (default: all cores)")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    """The command line; returns the exit status (2: a bad input, named; 130: interrupted)."""
    args = parse_args(sys.argv[1:] if argv is None else argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        options = PredictConfig(args.source, args.out, args.conf, args.classes, args.max_det, not args.no_overlays,
                                args.masks, args.crops, args.threads)
        set_threads(options.threads)
        run_predict(open_model(args.model, choose_device(args.device), options.threads), options, Path.cwd())
    except (ValueError, FileNotFoundError, StageError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted: what was done is in predictions.partial.json", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
