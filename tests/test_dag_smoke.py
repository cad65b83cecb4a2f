"""End to end: `python dag.py +experiment=smoke` runs every stage on the embedded sample and ends with a
short report; a second run recomputes nothing; without test sets it trains and skips eval."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.factories.configs import run_dag

STAGES = ["sample", "frames", "sfm", "splat_train", "extract", "bg_depth", "planes", "compose", "dataset",
          "train_maskrcnn", "eval"]


def stage_metrics(summary: dict) -> dict[str, list[dict]]:
    """{stage: [metrics.json of each of its nodes]} of a run's summary."""
    found: dict[str, list[dict]] = {}
    for outcome in summary["outcomes"]:
        found.setdefault(outcome["stage"], []).append(json.loads((Path(outcome["path"]) / "metrics.json").read_text()))
    return found


@pytest.mark.slow
def test_smoke_experiment_runs_every_stage_then_is_fully_cached(tmp_path):
    cache = f"run.cache_dir={tmp_path / 'cache'}"
    first_dir, second_dir, third_dir = tmp_path / "first", tmp_path / "second", tmp_path / "third"
    for folder in (first_dir, second_dir, third_dir):
        folder.mkdir()

    done, summary = run_dag("+experiment=smoke", cache, cwd=first_dir)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert {r["stage"] for r in summary["outcomes"]} == set(STAGES)
    assert all(r["status"] == "ran" for r in summary["outcomes"])
    assert set(summary["eval"]) == {"full@test_a", "full@test_b"}
    for metrics in summary["eval"].values():  # each test set scored on eval.max_images images, class by class
        assert metrics["images"] == 4 and metrics["detections"] > 0, metrics
        for kind in ("bbox", "segm"):
            per_class = metrics[kind]["per_class"]
            assert set(per_class) == {"bottle", "soda_can"}, metrics[kind]
            assert metrics[kind]["AP"] == pytest.approx(sum(per_class.values()) / len(per_class)), metrics[kind]
    # what the smoke budget reaches (2026-11-25: every frame registered, 20.2 / 21.4 dB, 331 / 351 object
    # Gaussians cut on a RANSAC plane, 1.5 objects per image); a detector of 2 iterations finds nothing yet
    metrics = stage_metrics(summary)
    assert all(m["registered_ratio"] >= 0.9 for m in metrics["sfm"]), metrics["sfm"]
    assert all(m["best_psnr"] >= 18.0 for m in metrics["splat_train"]), metrics["splat_train"]
    assert all(m["kept"] >= 100 and m["plane_source"] == "ransac" and m["base_gap"] < 0.05
               for m in metrics["extract"]), metrics["extract"]
    # the cut passes each of extract's checks with at least 20 % of its limit to spare (issue 53: on another
    # CPU's splats the smoke run once failed them; the kernels now give the same bits on every CPU)
    margins = {(m["kept"], name): value for m in metrics["extract"] for name, value in m.items()
               if name.startswith("margin_")}
    assert {name for _, name in margins} >= {"margin_core_below", "margin_layer", "margin_base_gap"}, margins
    assert min(margins.values()) >= 0.2, margins
    assert [(m["images"], m["images_without_objects"]) for m in metrics["compose"]] == [(8, 0)]
    assert metrics["compose"][0]["objects_per_image"] >= 1.0
    lines = done.stdout.splitlines()
    report = lines[max(k for k, line in enumerate(lines) if line.split()[:2] == ["stage", "items"]):]
    assert [line.split()[0] for line in report[1:12]] == STAGES and len(report) < 40  # one row per stage
    assert any(line.startswith("full@test_a: box AP") for line in report)
    assert report[-1] == f"summary: {first_dir / 'run' / 'summary.json'}"
    assert {p.rsplit("/", 1)[1] for p in summary["previews"]} == {"preview.png", "card.md", "predictions.png"}

    first_eval = summary["eval"]
    done, summary = run_dag("+experiment=smoke", cache, cwd=second_dir)
    assert done.returncode == 0, done.stderr[-3000:]
    assert {r["status"] for r in summary["outcomes"]} == {"cached"}
    assert summary["eval"] == first_eval  # the cached entries are the first run's results

    done, summary = run_dag("+experiment=smoke", cache, "data.test_sets=[]", cwd=third_dir)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "no test sets: eval skipped" in done.stdout and summary["notes"] == ["no test sets: eval skipped"]
    assert [r["stage"] for r in summary["outcomes"]][-1] == "train_maskrcnn" and summary["eval"] == {}

    done, _ = run_dag("+experiment=smoke", cache, "variant=no_placement", "run.action=plan", cwd=second_dir)
    plan = {(r["stage"], r["item"]): r["status"] for r in json.loads((second_dir / "run" / "plan.json").read_text())}
    assert plan[("compose", "no_placement#0")] == "would-run"
    assert all(status == "cached" for (stage, _), status in plan.items() if stage == "extract")
