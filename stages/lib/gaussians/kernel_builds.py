"""The builds of the C++ CPU kernels (stages/lib/gaussians/csrc/) and the results they give: torch-free, so that the app
keys the stages that run the kernels without loading torch.

Every build gives the same bits on every x86-64 CPU, at every instruction-set level: it is compiled without
floating-point contraction (-ffp-contract=off), the multiply-adds that matter are explicit FMAs, which round once
everywhere, and the rasterizer's gradient sums run in the same order whatever its vector width (csrc/kernel.cpp says
how; tests/gaussians/test_kernel_builds.py compares the bytes of each level the machine runs). A process builds for
the highest level its CPU runs: x86-64-v4 (AVX-512, 16 lanes), x86-64-v3 (AVX2 and FMA, 8 lanes), else x86-64-v2
(8 lanes; its FMAs are library calls, about 10x slower). Today's x86-64-v4 build steps as fast as the -march=native
build it replaced, and x86-64-v3 within 4 % of an x86-64-v3 build with contraction
(benchmarks/results/kernel_builds.md). $CUT_AND_SPLAT_KERNELS names another level (tests, benchmarks).

torch's own kernels in the same steps are pinned to its AVX2 ones (stages/__init__.py). With both, the results are
named "portable" in the cache keys of the stages that run the kernels (stages/engine/machine.py); where torch's kernels
are others (a CPU without AVX2, or ATEN_CPU_CAPABILITY set otherwise in the shell), or on another architecture, the
name says which, so that a cache shared by such machines never serves one key with two results.
"""
from __future__ import annotations

import functools
import hashlib
import os
import platform
from pathlib import Path

from stages import ATEN_PIN, cpu_flags

ENV = "CUT_AND_SPLAT_KERNELS"  # a level of LEVELS (or GENERIC) instead of the highest the CPU runs
COMMON_CFLAGS = ["-O3", "-fno-trapping-math", "-fopenmp", "-ffp-contract=off"]  # no -ffast-math: it changes
# results, and linked into a shared library with GCC 12 it flushes denormals process-wide
_V2 = ("cx16", "lahf_lm", "popcnt", "sse4_1", "sse4_2", "ssse3")
_V3 = _V2 + ("avx", "avx2", "bmi1", "bmi2", "f16c", "fma", "abm", "movbe", "xsave")
_V4 = _V3 + ("avx512f", "avx512bw", "avx512cd", "avx512dq", "avx512vl")
LEVELS = {"x86-64": (), "x86-64-v2": _V2, "x86-64-v3": _V3, "x86-64-v4": _V4}  # GCC's -march levels: the
# /proc/cpuinfo flags each needs
LEVEL_CFLAGS = {"x86-64-v4": ["-DCUT_AND_SPLAT_LANES=16",  # the rasterizer's vector: one AVX-512 register
                              "-mprefer-vector-width=256"]}  # loops GCC vectorises itself: 512-bit ones ran the SH
#                                                             colours 1.5x slower
GENERIC = "generic"  # a build for another architecture: no -march


@functools.lru_cache(maxsize=1)
def cpu_info() -> str:
    """This CPU's model name and instruction-set flags as /proc/cpuinfo gives them ("" where it cannot be read)."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return platform.processor()
    first = {}
    for line in lines:
        name = line.split(":", 1)[0].strip()
        if name in ("model name", "flags") and name not in first:
            first[name] = line
    return "\n".join(first.values())


@functools.lru_cache(maxsize=1)
def runnable_levels() -> tuple[str, ...]:
    """The x86-64 levels this CPU runs, lowest first (none on another architecture)."""
    if platform.machine() not in ("x86_64", "AMD64"):
        return ()
    flags = cpu_flags()
    return tuple(level for level, needs in LEVELS.items() if set(needs) <= flags)


def requested_build() -> str:
    """The build this process uses: $CUT_AND_SPLAT_KERNELS when set (a level of LEVELS, or GENERIC), else the highest
    level the CPU runs (GENERIC on another architecture). ValueError naming the choices for another value."""
    asked = os.environ.get(ENV)
    if asked:
        if asked != GENERIC and asked not in LEVELS:
            raise ValueError(f"${ENV}={asked!r} is not one of {', '.join((*LEVELS, GENERIC))}")
        return asked
    levels = runnable_levels()
    return levels[-1] if levels else GENERIC


def build_flags(build: str) -> list[str]:
    """The compiler flags of a build (a level of LEVELS, or GENERIC)."""
    if build == GENERIC:
        return COMMON_CFLAGS + ["-DCUT_AND_SPLAT_LANES=8"]
    if build not in LEVELS:
        raise ValueError(f"unknown kernel build {build!r}")
    return COMMON_CFLAGS + [f"-march={build}"] + LEVEL_CFLAGS.get(build, ["-DCUT_AND_SPLAT_LANES=8"])


def results_identity() -> str:
    """What the results of the kernels in this process are named by in cache keys: "portable" on x86-64 with torch
    pinned to its AVX2 kernels; "portable-aten-<torch's kernels>" where they are others, "portable-<architecture>"
    on another architecture (their bits are not compared with x86-64's)."""
    if requested_build() == GENERIC:
        return f"portable-{platform.machine()}"
    aten = os.environ.get("ATEN_CPU_CAPABILITY", "")
    if aten == ATEN_PIN:
        return "portable"
    return f"portable-aten-{aten or 'auto-' + hashlib.sha256(cpu_info().encode()).hexdigest()[:12]}"
