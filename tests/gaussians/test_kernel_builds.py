"""One cache key, one result: every build of the C++ kernels gives the same bytes (a projection, a raster and a
loss, forward and backward, and a few dozen training steps with densification), torch is pinned to its AVX2 kernels,
and what still differs between machines (torch's other kernels, another architecture, the device) names itself in
the cache keys."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from stages import ATEN_PIN_NEEDS, cpu_flags
from stages.engine.machine import machine_facts
from stages.engine.graph import Node, Stage
from stages.engine.scheduler import Engine
from stages.lib.gaussians import kernel_builds
from tests.factories.kernel_probe import EDGE_PIXEL, edge_raster, kernel_digests
from tests.factories.raster import needs_cpp

ROOT = Path(__file__).resolve().parents[2]
LEVELS_HERE = [level for level in ("x86-64-v2", "x86-64-v3", "x86-64-v4") if level in kernel_builds.runnable_levels()]


@pytest.mark.slow
def test_every_level_gives_the_same_bytes(monkeypatch):
    """x86-64-v2 runs the rasterizer's 8-lane vector as two SSE halves and calls fmaf, v3 runs it in one AVX2
    register, v4 runs 16 lanes in one AVX-512 register: the bytes must not move (each build compiles once per
    machine, ~40 s)."""
    needs_cpp()
    if len(LEVELS_HERE) < 2:
        pytest.skip(f"this CPU runs only {LEVELS_HERE} of the x86-64 levels v2-v4")
    found = {}
    for level in LEVELS_HERE:
        monkeypatch.setenv(kernel_builds.ENV, level)
        found[level] = kernel_digests(steps=24)
    reference = found[LEVELS_HERE[0]]
    assert int(reference["gaussians"]) != 200  # densification ran (the start has 200)
    assert all(digests == reference for digests in found.values()), found


def test_no_pixel_beyond_the_reached_columns_takes_part():
    """Rounding can put an alpha of 1/255 just beyond a Gaussian's computed extent; every build leaves that pixel
    alone, whatever its lane count (kernel.cpp column_window)."""
    needs_cpp()
    image, trans = edge_raster()
    row, column = EDGE_PIXEL
    assert trans[row, column] == 1.0 and not image[row, column].any()
    tile = trans[row // 16 * 16:row // 16 * 16 + 16, column // 16 * 16:column // 16 * 16 + 16]
    assert (tile < 1.0).any()  # the Gaussian does reach the pixel's tile


def test_a_process_builds_for_the_highest_level_its_cpu_runs(monkeypatch):
    monkeypatch.delenv(kernel_builds.ENV, raising=False)
    levels = kernel_builds.runnable_levels()
    assert kernel_builds.requested_build() == (levels[-1] if levels else kernel_builds.GENERIC)
    for build in (*kernel_builds.LEVELS, kernel_builds.GENERIC):
        flags = kernel_builds.build_flags(build)
        assert "-ffp-contract=off" in flags and "-march=native" not in flags
        assert sum(flag.startswith("-DCUT_AND_SPLAT_LANES=") for flag in flags) == 1
    monkeypatch.setenv(kernel_builds.ENV, "native")
    with pytest.raises(ValueError, match="CUT_AND_SPLAT_KERNELS='native' is not one of"):
        kernel_builds.requested_build()


def test_results_name_torch_kernels_and_the_architecture(monkeypatch):
    monkeypatch.setenv("ATEN_CPU_CAPABILITY", kernel_builds.ATEN_PIN)
    for level in LEVELS_HERE:
        monkeypatch.setenv(kernel_builds.ENV, level)
        assert kernel_builds.results_identity() == "portable"
    monkeypatch.setenv("ATEN_CPU_CAPABILITY", "avx512")
    assert kernel_builds.results_identity() == "portable-aten-avx512"
    monkeypatch.delenv("ATEN_CPU_CAPABILITY")
    assert kernel_builds.results_identity().startswith("portable-aten-auto-")
    monkeypatch.setenv(kernel_builds.ENV, kernel_builds.GENERIC)
    assert kernel_builds.results_identity().startswith("portable-") and "aten" not in kernel_builds.results_identity()


def test_torch_is_pinned_to_its_avx2_kernels():
    """stages/__init__.py pins torch before its first operation; a value from the shell wins."""
    if not set(ATEN_PIN_NEEDS) <= cpu_flags():
        pytest.skip("this CPU has no AVX2 and FMA: torch keeps its own choice (and the keys say so)")
    code = "import stages, torch; print(torch.backends.cpu.get_cpu_capability())"
    env = {k: v for k, v in os.environ.items() if k != "ATEN_CPU_CAPABILITY"}
    pinned = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True,
                            check=True)
    assert pinned.stdout.split() == ["AVX2"]
    chosen = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env={**env, "ATEN_CPU_CAPABILITY": "default"},
                            capture_output=True, text=True, check=True)
    assert chosen.stdout.split() == ["DEFAULT"]


def toy_stage(machine: tuple[str, ...]) -> Stage:
    return Stage("toy", lambda ctx: None, machine=machine)


def test_machine_facts_enter_the_keys_of_the_stages_that_declare_them(tmp_path):
    cpu = machine_facts("cpu")
    assert set(cpu) == {"device", "cpu_kernels"} and cpu["device"] == "cpu"
    nodes = {declared: Node(toy_stage(declared), "x", {"n": 1})
             for declared in ((), ("device",), ("cpu_kernels",), ("device", "cpu_kernels"))}
    keys = {}
    for name, machine in (("cpu", cpu), ("cuda", {**cpu, "device": "cuda"}),
                          ("other_torch", {**cpu, "cpu_kernels": "portable-aten-avx512"})):
        engine = Engine(tmp_path / "cache", machine=machine)
        keys[name] = {declared: engine.key(node) for declared, node in nodes.items()}
    assert len({keys[name][()] for name in keys}) == 1  # a stage that declares nothing is keyed alike
    assert keys["cuda"][("device",)] != keys["cpu"][("device",)]
    assert keys["cuda"][("cpu_kernels",)] == keys["cpu"][("cpu_kernels",)]
    assert keys["other_torch"][("cpu_kernels",)] != keys["cpu"][("cpu_kernels",)]
    assert keys["other_torch"][("device",)] == keys["cpu"][("device",)]
    with pytest.raises(ValueError, match="unknown machine facts"):
        toy_stage(("cpu_model",))


def test_the_stages_that_run_kernels_or_a_device_declare_it():
    from stages.app.pipeline import STAGES

    declared = {name: stage.machine for name, stage in STAGES.items() if stage.machine}
    assert declared == {"splat_train": ("device", "cpu_kernels"), "extract": ("cpu_kernels",),
                        "compose": ("cpu_kernels",), "cut_and_paste": ("cpu_kernels",), "bg_depth": ("device",),
                        "train_maskrcnn": ("device",), "eval": ("device",)}


def test_probe_prints_its_digests_as_json():
    """The probe runs as a command too (to compare machines: run it on each and diff the output)."""
    needs_cpp()
    done = subprocess.run([sys.executable, "-m", "tests.factories.kernel_probe", "--steps", "4"], cwd=ROOT,
                          capture_output=True, text=True, check=True)
    digests = json.loads(done.stdout.splitlines()[-1])
    assert set(digests) == {"projection", "raster", "raster_edge", "loss", "training", "gaussians"}
