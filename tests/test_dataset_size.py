"""Issue 56, item 5: the dataset-size sweep (conf/experiment/dataset_size.yaml, the conf/dataset_size points) and its
table from sweep summaries (benchmarks/dataset_size.py)."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmarks.dataset_size import report
from stages.app.pipeline import build_graph
from stages.engine.scheduler import Engine
from stages.train_maskrcnn.spec import TrainMaskrcnnConfig
from tests.factories.configs import CONF, ROOT, compose_cfg

POINTS = sorted(path.stem for path in (CONF / "dataset_size").glob("*.yaml"))


def detector_iterations(overrides: list[str]) -> tuple[int, int]:
    """(composed images, detector iterations) of a config."""
    cfg = compose_cfg(overrides)
    budget = TrainMaskrcnnConfig(epochs=cfg.train_maskrcnn.epochs, batch_size=cfg.train_maskrcnn.batch_size)
    return cfg.compose.num_images, budget.iterations(cfg.compose.num_images)


@pytest.mark.parametrize("point", POINTS)
def test_each_size_keeps_the_default_epochs_or_the_default_iterations(point):
    images, steps = detector_iterations(["+experiment=dataset_size", f"+dataset_size={point}"])
    default_images, default_steps = detector_iterations([])
    if point.endswith("_equal_steps"):
        assert images != default_images and steps == default_steps
    else:
        assert steps * default_images == default_steps * images  # the default epochs
    assert f"images_{images}" in point


def test_the_default_size_is_the_ablations_full_job(tmp_path):
    """The 1000-image point has the keys of +experiment=ablation's full job: it comes from the cache."""
    def detector_key(overrides: list[str]) -> str:
        cfg = compose_cfg(overrides)
        graph = build_graph(cfg, ROOT)
        engine = Engine(tmp_path, global_seed=int(cfg.run.seed), workers=1, reseed=list(cfg.run.reseed))
        return engine.key(graph.nodes["train_maskrcnn"][0])

    assert detector_key(["+experiment=dataset_size", "+dataset_size=images_1000", "run.seed=1"]) == \
        detector_key(["+experiment=ablation", "variant=full", "run.seed=1"])
    assert detector_key(["+experiment=dataset_size", "+dataset_size=images_2000", "run.seed=1"]) != \
        detector_key(["+experiment=ablation", "variant=full", "run.seed=1"])


def write_job(sweep: Path, number: int, images: int, epochs: float, ap: float) -> None:
    """One job's archived summary.json (test_a, no cache entry beside it) in `sweep`, with its stage minutes."""
    job = sweep / f"{number}_full"
    job.mkdir(parents=True)
    steps = TrainMaskrcnnConfig(epochs=epochs).iterations(images)
    (job / "summary.json").write_text(json.dumps({
        "variant": {"name": "full"},
        "outcomes": [{"stage": "train_maskrcnn", "status": "ran", "path": str(job / "gone")}],
        "config": {"data": {"test_sets": [{"name": "test_a", "path": "test_a"}]}, "compose": {"num_images": images},
                   "train_maskrcnn": {"epochs": epochs, "batch_size": TrainMaskrcnnConfig().batch_size}},
        "compute_seconds_by_stage": {"compose": 60.0 * images / 1000, "train_maskrcnn": 6.0 * steps},
        "eval": {"full@test_a": {"bbox": {"AP": ap, "AP50": ap}, "segm": {"AP": ap + 10}}}}))


def test_the_table_pools_seeds_per_size_and_budget(tmp_path):
    jobs = [(5000, 1.6, 61.0), (1000, 8.0, 60.0), (2000, 8.0, 63.0), (1000, 8.0, 62.0), (2000, 4.0, 61.5),
            (5000, 8.0, 64.0)]
    for number, job in enumerate(jobs):
        write_job(tmp_path / ("a" if number < 3 else "b"), number, *job)
    lines = report([tmp_path / "a", tmp_path / "b"]).splitlines()
    assert lines[2:7] == ["| 1000 | default epochs | 2000 | 2 | 61.0 ± 1.4 | 71.0 ± 1.4 | 1.0 | 200.0 |",
                          "| 2000 | equal steps | 2000 | 1 | 61.5 | 71.5 | 2.0 | 200.0 |",
                          "| 2000 | default epochs | 4000 | 1 | 63.0 | 73.0 | 2.0 | 400.0 |",
                          "| 5000 | equal steps | 2000 | 1 | 61.0 | 71.0 | 5.0 | 200.0 |",
                          "| 5000 | default epochs | 10000 | 1 | 64.0 | 74.0 | 5.0 | 1000.0 |"]
    assert (tmp_path / "a" / "dataset_size.png").stat().st_size > 0
