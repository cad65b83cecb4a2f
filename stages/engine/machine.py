"""The facts of the machine a node's results depend on besides its inputs and settings, by name: the cache key of
a stage that declares one holds its value (stages/engine/scheduler.py `Stage.machine`), so that a cache shared by
machines never serves one key with two results.

- "device": "cpu" or "cuda" (CUDA results differ from the CPU's; gsplat's atomics are not even reproducible on one
  GPU, BENCHMARKS.md);
- "cpu_kernels": the results of the C++ CPU kernels and of torch's CPU kernels beside them
  (stages/lib/gaussians/kernel_builds.py: "portable", the same bits on every x86-64 CPU with AVX2; another name where
  torch's kernels are others or on another architecture).
"""
from __future__ import annotations

from stages.lib.gaussians.kernel_builds import results_identity

FACTS = ("device", "cpu_kernels")


def machine_facts(device: str) -> dict[str, str]:
    """{fact: value} of this process on `device` ("cpu" or "cuda")."""
    return {"device": device, "cpu_kernels": results_identity()}
