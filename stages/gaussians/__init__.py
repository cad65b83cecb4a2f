"""Gaussian splatting core: model, PLY I/O, projection, rasterizers and trainer.

Kept import-light on purpose (no torch import here). The one side effect: OpenMP threads of the
C++ rasterizer must not spin-wait, because on this shared 2-core machine a spinning OpenMP
team made 2 threads ~13x slower than 1 (MEASURED.md). libgomp reads OMP_WAIT_POLICY once, when
it is first loaded (torch loads it on `import torch`), so it is set here, as early as possible;
an explicit user setting wins.
"""
import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
