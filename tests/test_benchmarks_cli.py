"""Every benchmark script starts: its module imports and its command line (defaults included) parses, and the
GPU measurements say they are skipped on a machine without CUDA. A benchmark is run by hand, often on a machine
lent for minutes (a GPU): a crash at its first line wastes that machine, so it is caught here."""
from __future__ import annotations

import importlib
import json
import pkgutil
import sys

import pytest
import torch

import benchmarks

SCRIPTS = sorted(m.name for m in pkgutil.iter_modules(benchmarks.__path__)
                 if hasattr(importlib.import_module(f"benchmarks.{m.name}"), "main"))


def run_main(module: str, argv: list[str], monkeypatch) -> None:
    """Call benchmarks.<module>.main() with the command line `argv` (the program name is added)."""
    monkeypatch.setattr(sys, "argv", [f"benchmarks.{module}", *argv])
    importlib.import_module(f"benchmarks.{module}").main()


def test_the_scripts_are_found():
    assert {"splat_train", "rasterizer", "detector", "rendered_training"} <= set(SCRIPTS)


@pytest.mark.parametrize("module", SCRIPTS)
def test_help_parses_the_command_line(module, monkeypatch, capsys):
    with pytest.raises(SystemExit) as done:
        run_main(module, ["--help"], monkeypatch)
    assert done.value.code == 0
    assert "usage:" in capsys.readouterr().out


@pytest.mark.skipif(torch.cuda.is_available(), reason="a CUDA device is here: the GPU measurements would run")
@pytest.mark.parametrize("module, argv", [("splat_train", ["--gpu"]), ("rasterizer", ["--device", "cuda"]),
                                          ("gsplat_step", []), ("gpu_session", [])])
def test_gpu_measurements_are_skipped_without_cuda(module, argv, monkeypatch, capsys):
    run_main(module, argv, monkeypatch)
    assert "no CUDA device: skipped" in capsys.readouterr().out


def test_splat_train_trains_each_seed_with_the_settings_changed(tmp_path, monkeypatch, capsys):
    out = tmp_path / "runs.json"
    run_main("splat_train", ["--budgets", "300", "--iterations", "30", "--truth-gaussians", "100", "--views", "6",
                             "--width", "64", "--height", "48", "--sfm-points", "100", "--seed", "0", "1",
                             "--set", "iterations=12", "--out", str(out)], monkeypatch)
    rows = json.loads(out.read_text())["results"]
    assert [(row["seed"], row["iterations_run"]) for row in rows] == [(0, 12), (1, 12)]
