"""Benchmark: one splat training step on a real capture, part by part: the C++ kernels against the PyTorch parts
they replaced, measured in the same run.

    python -m benchmarks.train_step --sfm outputs/cache/sfm/<key> --splat outputs/cache/splat_train/<key>/scene.ply \
        [--long-sides 256 320] [--threads 1 2] [--rounds 5] [--out benchmarks/results/train_step/train_step.json] \
        [--builds x86-64-v4 x86-64-v3 x86-64-v2 [--reference REV [--reference-flags "..."]]]

A step is the trainer's (render, L1 + D-SSIM against the photo, backward, Adam over all parameters; no
densification) on the trained scene (its Gaussian count, SH degree 3) and the capture's first 20 training views
at each long side. The ladder adds one C++ part at a time to the step of 2026-11-25 (PyTorch projection, binning,
SH colours and kornia loss around the C++ compositor, foreach Adam): projection and binning, then SH colours,
then the fused loss, then fused Adam (today's step, `GaussianTrainer.step`'s parts). Rounds alternate the
variants so that the machine's drift falls on all of them; the table gives the median step of each and its speed-up
over the first, from the same rounds.

With --builds, the variants are today's step with each build of the kernels instead (stages/lib/gaussians/
kernel_builds.py), and each row also gives the sha256 of the parameters after all its steps: every variant takes the
same steps on the same views, so equal digests are the same bits. --reference REV adds, first, the step with the
kernels' sources at git revision REV built with --reference-flags (default: the -march=native build of the kernels
before 2026-11-27), the reference of the speed-ups.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import logging
import os
import statistics
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Callable

import torch

from stages.lib.gaussians import kernel_builds
from stages.lib.gaussians import native
from stages.lib.gaussians.binning import bin_gaussians
from stages.lib.gaussians.losses import photometric_loss
from stages.lib.gaussians.model import Gaussians
from stages.lib.gaussians.native import bin_gaussians_cpp, project_gaussians_cpp, rasterize_tiles_cpp, load_extension
from stages.lib.gaussians.ply import read_ply
from stages.lib.gaussians.projection import project_gaussians
from stages.lib.gaussians.rasterize import gaussian_colors
from stages.lib.gaussians.trainer import TrainView
from stages.records.sfm import SfmRecord
from stages.splat_train.run import load_view
from tests.factories.reference_losses import photometric_loss_reference

log = logging.getLogger("benchmarks.train_step")
LADDER = {  # variant: (C++ projection and binning, C++ SH colours, fused loss, fused Adam)
    "previous (PyTorch parts)": (False, False, False, False),
    "+ projection and binning": (True, False, False, False),
    "+ SH colours": (True, True, False, False),
    "+ fused loss": (True, True, True, False),
    "today (+ fused Adam)": (True, True, True, True),
}
LR = (1.6e-4, 5e-3, 1e-3, 5e-2, 2.5e-3)  # means, log-scales, quaternions, opacity logits, SH


class Step:
    """One variant's parameters, optimiser and step function on a copy of the scene."""

    def __init__(self, scene: Gaussians, parts: tuple[bool, bool, bool, bool]):
        self.cpp_project, self.cpp_colours, self.fused_loss, fused_adam = parts
        self.params = [torch.nn.Parameter(t.detach().clone()) for t in
                       (scene.means, scene.log_scales, scene.quats, scene.opacity_logits, scene.sh)]
        self.optimiser = torch.optim.Adam([{"params": [p], "lr": lr} for p, lr in zip(self.params, LR)],
                                          eps=1e-15, fused=fused_adam)

    def __call__(self, view: TrainView) -> None:
        means, log_scales, quats, logits, sh = self.params
        g = Gaussians(means, log_scales, torch.nn.functional.normalize(quats, dim=-1), logits, sh)
        colours = gaussian_colors(g, view.viewmat, backend="cpp" if self.cpp_colours else "torch")
        project, binning = ((project_gaussians_cpp, bin_gaussians_cpp) if self.cpp_project
                            else (project_gaussians, bin_gaussians))
        proj = project(g.means, g.quats, g.scales, g.opacities, view.viewmat, view.K, view.width, view.height)
        bins = binning(proj, view.width, view.height)
        features = torch.cat([colours, proj.depths[:, None]], dim=-1)
        image, _ = rasterize_tiles_cpp(proj.means2d, proj.conics, g.opacities, features, bins, view.width,
                                       view.height)
        loss_fn = photometric_loss if self.fused_loss else photometric_loss_reference
        loss = loss_fn(image[..., :3], view.image, 0.2)
        loss.backward()
        self.optimiser.step()
        self.optimiser.zero_grad(set_to_none=True)


ROOT = Path(__file__).resolve().parents[1]
NATIVE_FLAGS = "-O3 -march=native -fno-trapping-math -fopenmp"  # the kernels' build until 2026-11-27


class WithKernels:
    """A Step that runs with one build of the kernels (a level of kernel_builds.LEVELS), or with a given extension
    module (`module`); the process's kernels are switched before each call."""

    def __init__(self, step: Step, build: str = "", module=None):
        self.step, self.build, self.module = step, build, module

    def __call__(self, view: TrainView) -> None:
        if self.module is not None:
            native.load_extension = lambda build=None: self.module
        else:
            native.load_extension = load_extension
            os.environ[kernel_builds.ENV] = self.build
        self.step(view)


def reference_module(revision: str, flags: str):
    """The kernels' extension built from their sources at git revision `revision` with `flags`, in a temporary
    folder (the functions it binds must be today's)."""
    from torch.utils.cpp_extension import load

    folder = Path(tempfile.mkdtemp(prefix="kernels-"))
    for path in native.SOURCES + native.HEADERS:
        text = subprocess.run(["git", "show", f"{revision}:{path.relative_to(ROOT)}"], cwd=ROOT, check=True,
                              capture_output=True, text=True).stdout
        (folder / path.name).write_text(text)
    return load(name=f"kernels_{revision}", sources=[str(folder / path.name) for path in native.SOURCES],
                extra_cflags=flags.split(), extra_include_paths=[str(folder)], extra_ldflags=["-fopenmp"],
                build_directory=str(folder))


def measure(runners: dict[str, Callable[[TrainView], None]], views: list[TrainView], rounds: int,
            steps: int) -> list[dict]:
    """Median ms per step of every runner over `rounds` alternating rounds of `steps` steps, and its speed-up over
    the first; each runner takes the same steps on the same views."""
    for runner in runners.values():  # warm-up (and the extension's first load)
        for view in views[:2]:
            runner(view)
    times: dict[str, list[float]] = {name: [] for name in runners}
    for _ in range(rounds):
        for name, runner in runners.items():
            started = time.perf_counter()
            for i in range(steps):
                runner(views[i % len(views)])
            times[name].append(1000 * (time.perf_counter() - started) / steps)
    first = statistics.median(times[next(iter(runners))])
    return [{"variant": name, "ms_per_step": round(statistics.median(values), 1),
             "rounds_ms": [round(v, 1) for v in values], "speedup": round(first / statistics.median(values), 2)}
            for name, values in times.items()]


def params_digest(step: Step) -> str:
    """sha256 of a step's parameters."""
    digest = hashlib.sha256()
    for param in step.params:
        digest.update(param.detach().numpy().tobytes())
    return digest.hexdigest()


def main() -> None:
    """Command line: see the module docstring."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sfm", type=Path, required=True, help="an sfm stage output (the capture's views)")
    parser.add_argument("--splat", type=Path, required=True, help="a trained scene.ply of the same capture")
    parser.add_argument("--long-sides", type=int, nargs="+", default=[256, 320])
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--steps", type=int, default=10, help="steps per variant and round")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--builds", nargs="+", help="today's step with each of these kernel builds instead of the "
                        "ladder (x86-64-v2, x86-64-v3, x86-64-v4)")
    parser.add_argument("--reference", help="with --builds: first, the kernels at this git revision")
    parser.add_argument("--reference-flags", default=NATIVE_FLAGS, help="their compiler flags")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s][%(name)s][%(levelname)s] - %(message)s")
    sfm = SfmRecord.read(args.sfm)
    frames = sfm.scene().frames[:20]
    scene = read_ply(args.splat).with_sh_degree(3)
    kernels = {build: (build, None) for build in args.builds or []}  # variant: WithKernels' (build, module)
    if args.builds and args.reference:
        kernels = {f"{args.reference} {args.reference_flags}": ("", reference_module(args.reference,
                                                                                     args.reference_flags)), **kernels}
    result = {"splat": str(args.splat), "gaussians": scene.num, "torch": torch.__version__,
              "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(), "rows": []}
    for threads in args.threads:
        torch.set_num_threads(threads)
        for long_side in args.long_sides:
            views = [load_view(sfm.images_dir, frame, long_side, "cpu") for frame in frames]
            steps = ({name: Step(scene, LADDER["today (+ fused Adam)"]) for name in kernels} if args.builds else
                     {name: Step(scene, parts) for name, parts in LADDER.items()})
            runners = {name: WithKernels(steps[name], *kernels[name]) for name in kernels} if args.builds else steps
            for row in measure(runners, views, args.rounds, args.steps):
                if args.builds:
                    row["params_sha256"] = params_digest(steps[row["variant"]])
                row.update(threads=threads, resolution=f"{views[0].width}x{views[0].height}")
                result["rows"].append(row)
                log.info("%s", json.dumps(row))
    print(json.dumps(result, indent=1))
    if args.out:
        args.out.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
