"""Trained detectors for the tests of predict: a tiny Mask R-CNN trained (40 iterations, about 10 s on one thread) on
the shapes dataset, whose scores differ from one detection to the next (an untrained one's are all equal, so that
two backends may order them differently), and its model folder."""
from __future__ import annotations

from pathlib import Path

from stages.engine.context import Context
from stages.eval.spec import EvalConfig
from stages.lib.detection.model_folder import write_model_folder
from stages.lib.detection.postprocess import PostProcessing
from stages.lib.detection.sources import read_photo
from stages.train_maskrcnn.run import run as train
from tests.factories.shapes import write_shapes_dataset

# train_maskrcnn settings of the tiny detector: 96 px images, 10 epochs of 16 images in batches of 4
TINY_TRAINING = dict(image_size=96, threads=1, lr=0.02, warmup_iterations=3, batch_size=4, rpn_post_nms_train=100,
                     box_batch_size_per_image=32, scale_min=0.9, scale_max=1.1, epochs=10.0, train_crop=0,
                     loader_workers=0, closeup_share=0.0)


def train_tiny_detector(root: Path) -> Path:
    """Train the tiny detector on 16 shapes images written under root/train; returns its train_maskrcnn folder
    (root/model: model.pt, train.json). Its classes are the shapes' (SHAPE_NAMES), in that order."""
    dataset = write_shapes_dataset(root / "train", 16, size=96, seed=0)
    out = root / "model"
    out.mkdir(parents=True)
    train(Context("train_maskrcnn", "tiny", dict(TINY_TRAINING), {"dataset": dataset}, out, seed=3))
    return out


def tiny_card(model_dir: Path) -> dict:
    """Model-card facts of the tiny detector (what dag.py's export gathers from a run)."""
    return {"training": {"images": 16, "variant": "tiny", "generator": "shapes", "seed": 3, "backbone":
                         "efficientnet_lite0_fpn", "iterations": 40, "epochs": 10.0, "seconds": 10.0, "device": "cpu"},
            "evaluation": {}, "source": {"command": "tests/factories/detectors.py", "train_maskrcnn": str(model_dir),
                                         "created": "test"}}


def write_tiny_model_folder(folder: Path, model_dir: Path, example_photo: Path) -> Path:
    """The model folder of the tiny detector (eval's default post-processing), its ONNX graph traced and checked on
    `example_photo`; returns `folder`."""
    write_model_folder(folder, model_dir / "model.pt", PostProcessing.of(EvalConfig()), tiny_card(model_dir),
                       read_photo(example_photo)[0], "variant: tiny\n")
    return folder

