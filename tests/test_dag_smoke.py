"""End to end: `python dag.py +experiment=smoke` runs every stage on the embedded sample, and a
second run recomputes nothing."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def run_dag(*overrides: str, cwd: Path) -> tuple[subprocess.CompletedProcess, dict | None]:
    command = [sys.executable, str(ROOT / "dag.py"), *overrides, f"hydra.run.dir={cwd}/run"]
    done = subprocess.run(command, cwd=cwd, capture_output=True, text=True, timeout=900)
    summary_path = cwd / "run" / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.is_file() else None
    return done, summary


@pytest.mark.slow
def test_smoke_experiment_runs_every_stage_then_is_fully_cached(tmp_path):
    cache = f"run.cache_dir={tmp_path / 'cache'}"
    first_dir, second_dir = tmp_path / "first", tmp_path / "second"
    first_dir.mkdir()
    second_dir.mkdir()

    done, summary = run_dag("+experiment=smoke", cache, cwd=first_dir)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    stages = {r["stage"] for r in summary["records"]}
    assert stages == {"sample", "frames", "sfm", "splat_train", "extract", "bg_depth", "planes", "compose",
                      "train_maskrcnn", "eval"}
    assert all(r["status"] == "ran" for r in summary["records"])
    assert set(summary["eval"]) == {"full@test_a", "full@test_b"}
    for metrics in summary["eval"].values():
        assert 0.0 <= metrics["bbox"]["AP"] <= 100.0 and "segm" in metrics

    done, summary = run_dag("+experiment=smoke", cache, cwd=second_dir)
    assert done.returncode == 0, done.stderr[-3000:]
    assert {r["status"] for r in summary["records"]} == {"cached"}
    assert summary["eval"]["full@test_a"]["bbox"]["AP"] >= 0.0

    done, _ = run_dag("+experiment=smoke", cache, "variant=no_placement", "run.action=plan", cwd=second_dir)
    lines = [line.split() for line in done.stdout.splitlines() if line.startswith(("compose", "extract"))]
    assert ["compose", "no_placement", "would-run"] == lines[-1][:3]
    assert all(line[2] == "cached" for line in lines if line[0] == "extract")
