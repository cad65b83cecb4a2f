"""Cut-and-Splat: the stage modules, the libraries they share, the engine and the app (docs/layout.md).

The package's side effects, here so that they happen before torch loads or computes; a value set in the shell
wins. This module is part of every stage's cache key (stages/engine/cache_keys.py): keep it small and stable.
- Idle OpenMP threads sleep instead of spinning (OMP_WAIT_POLICY=PASSIVE). With another process busy on a 2-core
  machine, a spinning team of 2 OpenMP threads (torch's, and the C++ rasterizer's, which shares torch's libgomp)
  ran about 13x slower than 1 thread. libgomp reads the variable once, when it is loaded (on the first
  `import torch`), so entry points import this package before torch.
- torch's own CPU kernels are those of AVX2 on every CPU that has it (ATEN_CPU_CAPABILITY=avx2): torch picks its
  kernels by instruction set, and its AVX-512 kernels give other last bits than its AVX2 ones (a splat trained
  a few dozen steps differed), so one cache key would stand for two results. torch reads the variable at its
  first operation. stages/lib/gaussians/kernel_builds.py names the results in the cache keys.
"""
import os

ATEN_PIN = "avx2"  # torch's kernels on every CPU that runs them ...
ATEN_PIN_NEEDS = ("avx2", "fma")  # ... the /proc/cpuinfo flags they need


def cpu_flags() -> frozenset[str]:
    """The instruction-set flags of /proc/cpuinfo (empty where it cannot be read)."""
    try:
        with open("/proc/cpuinfo") as info:
            for line in info:
                if line.startswith("flags"):
                    return frozenset(line.split(":", 1)[1].split())
    except OSError:
        pass
    return frozenset()


os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
if set(ATEN_PIN_NEEDS) <= cpu_flags():
    os.environ.setdefault("ATEN_CPU_CAPABILITY", ATEN_PIN)
