"""Cut-and-Splat: the stage modules, the libraries they share, the engine and the app (docs/layout.md).

The package's one side effect, here so that it happens before anything imports torch: idle OpenMP
threads sleep instead of spinning (OMP_WAIT_POLICY=PASSIVE). With another process busy on a 2-core
machine, a spinning team of 2 OpenMP threads (torch's, and the C++ rasterizer's, which shares torch's
libgomp) ran about 13x slower than 1 thread. libgomp reads the variable once, when it is loaded (on the
first `import torch`), so entry points import this package before torch; a value set in the shell wins.
"""
import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
