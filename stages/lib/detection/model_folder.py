"""A trained detector as a self-contained folder: what predict needs on any machine, without the cache or the config.

    model.json      format and version, class names (label i+1 = class_names[i]), input size and preprocessing,
                    post-processing settings (postprocess.PostProcessing), the card's facts, the files
    weights.pt      {"state_dict", "model_config", "category_names"}, read by model.load_detector with
                    torch.load(weights_only=True)
    model.onnx      the same detector for onnxruntime (export.py), with model.json's description in its metadata
                    (key "cut_and_splat"), so the .onnx file alone also runs
    MODEL_CARD.md   the card for people (model_card.py): training data, eval metrics, versions, where it came from
    config.yaml     the config the detector came from (when written from a run's config)

The folder is written into a temporary folder beside it and renamed when complete. A reader refuses a folder of
another format version, naming it.
"""
from __future__ import annotations

import json
import os
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from stages.lib.detection.backends import OnnxDetector, TorchDetector
from stages.lib.detection.model import load_detector
from stages.lib.detection.model_card import render_card, versions
from stages.lib.detection.model_config import ModelConfig
from stages.lib.detection.onnx_export import check_onnx, export_onnx
from stages.lib.detection.postprocess import PostProcessing

FORMAT, FORMAT_VERSION = "cut-and-splat-detector", 1
MODEL_JSON, WEIGHTS, ONNX_FILE, CARD, CONFIG = "model.json", "weights.pt", "model.onnx", "MODEL_CARD.md", "config.yaml"
ONNX_KEY = "cut_and_splat"  # the metadata_props key of model.onnx that holds the description
EXPORT_HINT = "python dag.py run.action=predict predict.export=DIR"  # the command that writes a model folder


def describe(names: list[str], model_cfg: ModelConfig, post: PostProcessing) -> dict:
    """What it takes to run the detector and read its outputs: format, class names, input, post-processing."""
    return {"format": FORMAT, "format_version": FORMAT_VERSION, "class_names": list(names),
            "input": {"image_size": model_cfg.image_size, "backbone": str(model_cfg.backbone),
                      "preprocessing": "RGB uint8 / 255 as float32 [3, H, W] in [0, 1], any H and W; the detector "
                                       "resizes the longer side to image_size and normalises the colours itself"},
            "post_processing": asdict(post)}


def check_description(description: dict, source: str) -> None:
    """ValueError naming `source` when `description` is not describe()'s of this format version."""
    if description.get("format") != FORMAT:
        raise ValueError(f"{source}: not a Cut-and-Splat model (format {description.get('format')!r}, expected "
                         f"{FORMAT!r}); export one with {EXPORT_HINT}")
    version = description.get("format_version")
    if version != FORMAT_VERSION:
        raise ValueError(f"{source}: a model folder of format version {version}, but this version of Cut-and-Splat "
                         f"reads version {FORMAT_VERSION} ({versions()['cut-and-splat']}); export it again with "
                         f"{EXPORT_HINT}, or use the Cut-and-Splat version that wrote it")


def write_model_folder(folder: Path, model_file: Path, post: PostProcessing, card: dict, example: np.ndarray | None,
                       config_text: str | None = None) -> dict:
    """Write the model folder of a train_maskrcnn model.pt at `folder` (new, or an empty folder). `card`: the facts of
    model_card.render_card (training, evaluation, source); `example`: a test photo, RGB uint8 [H, W, 3], the ONNX
    graph is traced on and compared with PyTorch on (export.check_onnx, kept in the card); None: traced on a grey
    image, not compared. Returns model.json's content."""
    folder = Path(folder)
    if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
        raise ValueError(f"{folder}: exists and is not an empty folder; give a new folder for the model")
    model, model_cfg, names = load_detector(model_file)
    staging = folder.parent / f".{folder.name}.tmp-{os.getpid()}"
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    try:
        description = describe(names, model_cfg, post)
        shutil.copyfile(model_file, staging / WEIGHTS)  # train_maskrcnn's model.pt as it is
        grey = np.full((model_cfg.image_size * 3 // 4, model_cfg.image_size, 3), 128, np.uint8)
        export_onnx(model, staging / ONNX_FILE, grey if example is None else example,
                    {ONNX_KEY: json.dumps(description)})
        card = {**card, "versions": versions()}
        if example is not None:
            card["onnx_check"] = check_onnx(model, staging / ONNX_FILE, example, post, model_cfg.image_size)
        files = {"weights": WEIGHTS, "onnx": ONNX_FILE, "card": CARD, **({"config": CONFIG} if config_text else {})}
        written = {**description, "files": files, "card": card}
        (staging / MODEL_JSON).write_text(json.dumps(written, indent=1))
        (staging / CARD).write_text(render_card(written))
        if config_text:
            (staging / CONFIG).write_text(config_text)
        if folder.exists():
            folder.rmdir()
        staging.rename(folder)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return written


@dataclass
class LoadedModel:
    """A detector ready to run: its backend (TorchDetector or OnnxDetector), class names, input size, the
    post-processing settings, and where it came from."""

    detector: TorchDetector | OnnxDetector
    class_names: list[str]
    detector_size: int
    post: PostProcessing
    path: Path


def read_description(folder: Path) -> dict:
    """model.json of a model folder, checked (check_description); ValueError or FileNotFoundError naming the file."""
    path = Path(folder) / MODEL_JSON
    if not path.is_file():
        raise ValueError(f"{folder}: not a model folder (it has no {MODEL_JSON}); export one with {EXPORT_HINT}")
    try:
        description = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise ValueError(f"{path}: not valid JSON ({error})") from error
    check_description(description, str(path))
    return description


def open_model(path: str | Path, device: str = "cpu", threads: int = 0) -> LoadedModel:
    """The detector of a model folder (PyTorch on `device`, with torch's threads as they are set) or of an .onnx
    file written with one (onnxruntime on the CPU, `threads` threads, 0 = all). FileNotFoundError or ValueError
    naming the path when it is neither."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"model {path} not found (give a model folder or its .onnx file)")
    if path.is_file() and path.suffix.lower() == ".onnx":
        detector = OnnxDetector(path, threads)
        text = detector.metadata().get(ONNX_KEY)
        if text is None:
            raise ValueError(f"{path}: an ONNX file without Cut-and-Splat's description (class names, "
                             f"post-processing) in its metadata; export the detector with {EXPORT_HINT}")
        description = json.loads(text)
        check_description(description, str(path))
    elif path.is_dir():
        description = read_description(path)
        weights = path / description["files"]["weights"]
        try:
            model, _, names = load_detector(weights, device)
        except (OSError, RuntimeError, TypeError, ValueError, KeyError, EOFError) as error:
            raise ValueError(f"{weights}: cannot load the detector's weights ({error})") from error
        if names != description["class_names"]:
            raise ValueError(f"{path}: {WEIGHTS} has classes {names}, {MODEL_JSON} {description['class_names']}")
        detector = TorchDetector(model, device)
    else:
        raise ValueError(f"{path}: not a model; give a model folder (written by {EXPORT_HINT}) or its .onnx file")
    return LoadedModel(detector, list(description["class_names"]), int(description["input"]["image_size"]),
                       PostProcessing(**description["post_processing"]), path)
