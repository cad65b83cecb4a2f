"""dag.py's run.action=predict: the config's detector from the cache, or the command that trains it; its export as a
model folder with the card's facts (training, eval metrics, the config). Real tiny training and eval through the
engine (tests/factories/detectors.py)."""
import json
import logging

import pytest
import yaml

from stages.app.pipeline import STAGES, Graph, build_graph
from stages.app.predict import predict_action
from stages.engine.graph import Node, Stage
from stages.engine.scheduler import Engine
from tests.factories.configs import ROOT, compose_cfg
from tests.factories.detectors import TINY_TRAINING
from tests.factories.shapes import write_shapes_dataset

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def test_without_the_detector_in_the_cache_it_names_the_command_that_trains_it(tmp_path, caplog):
    overrides = ["variant=no_aug", "run.action=predict", f"predict.source={tmp_path / 'photo.jpg'}"]
    cfg = compose_cfg([*overrides, f"run.cache_dir={tmp_path / 'cache'}"])
    engine = Engine(tmp_path / "cache")
    with caplog.at_level(logging.ERROR):
        status = predict_action(cfg, engine, build_graph(cfg, ROOT), {}, tmp_path, "cpu", overrides)
    assert status == 2
    assert "train_maskrcnn[no_aug]" in caplog.text and "is not in the cache" in caplog.text
    assert "python dag.py variant=no_aug run.until=train_maskrcnn" in caplog.text


def test_neither_source_nor_export_is_a_clear_error(tmp_path, caplog):
    cfg = compose_cfg(["run.action=predict"])
    with caplog.at_level(logging.ERROR):
        assert predict_action(cfg, Engine(tmp_path), build_graph(cfg, ROOT), {}, tmp_path, "cpu", []) == 2
    assert "needs predict.source=PATH" in caplog.text


def shapes_dataset(ctx) -> dict:
    """A dataset generator's stand-in: 16 shapes images (train_maskrcnn reads an upstream node's dataset)."""
    write_shapes_dataset(ctx.out, 16, size=96, seed=0)
    return {}


def test_predict_and_export_the_configs_detector(tmp_path, capsys):
    testset = write_shapes_dataset(tmp_path / "test", 4, size=96, seed=1)
    dataset = Node(Stage("shapes", shapes_dataset), "full")
    train = Node(STAGES["train_maskrcnn"], "full", dict(TINY_TRAINING), {"dataset": dataset})
    evaluation = Node(STAGES["eval"], "full@shapes", {"threads": 1}, {"model": train, "testset": testset})
    engine = Engine(tmp_path / "cache")
    assert [r.status for r in engine.run([evaluation])] == ["ran", "ran", "ran"]
    graph = Graph({"train_maskrcnn": [train], "eval": [evaluation]})  # the run's nodes, as build_graph gives them
    overrides = ["run.action=predict", f"predict.source={testset / 'images'}", "predict.out=found", "predict.conf=0",
                 "predict.threads=1", "predict.export=detector"]
    cfg = compose_cfg(overrides)
    assert predict_action(cfg, engine, graph, {}, tmp_path, "cpu", overrides) == 0
    assert "4 images" in capsys.readouterr().out
    found = json.loads((tmp_path / "found" / "predictions.json").read_text())
    assert found["annotations"] == json.loads((engine.output_dir(evaluation) / "predictions.json").read_text())
    description = json.loads((tmp_path / "detector" / "model.json").read_text())
    metrics = json.loads((engine.output_dir(evaluation) / "metrics.json").read_text())
    assert description["card"]["evaluation"]["shapes"]["box_AP"] == metrics["bbox"]["AP"]
    assert description["card"]["training"]["images"] == 16 and description["card"]["training"]["variant"] == "full"
    assert description["card"]["onnx_check"]["same_labels"]
    assert description["post_processing"]["mask_refine_radius"] == cfg.eval.mask_refine_radius
    assert yaml.safe_load((tmp_path / "detector" / "config.yaml").read_text())["predict"]["export"] == "detector"
    card = (tmp_path / "detector" / "MODEL_CARD.md").read_text()
    assert "| shapes | 4 |" in card and str(engine.output_dir(train)) in card
