"""Benchmark: one training iteration (render + L1 + backward + Adam step) at 256x256.

Compares the C++ kernel with the pure-PyTorch reference in the same run, for several Gaussian
counts and thread counts, and splits the C++ iteration into projection + binning vs the rest.
Prints one JSON object (and writes it with --out).

    OMP_WAIT_POLICY=PASSIVE python -m benchmarks.rasterizer --out /tmp/rasterizer.json
"""
from __future__ import annotations

import argparse
import json
import logging
import statistics
import time

import torch

from stages.gaussians.binning import bin_gaussians
from stages.gaussians.model import Gaussians
from stages.gaussians.projection import project_gaussians
from stages.gaussians.rasterize import render

SIZE = 256
log = logging.getLogger("benchmarks.rasterizer")


def make_scene(n: int, seed: int = 0) -> tuple[Gaussians, torch.Tensor, torch.Tensor, torch.Tensor]:
    """n Gaussians from random points in a cube filling a 60 degree view, kNN scales (3DGS init),
    opacities ~ U(0.05, 0.95), SH degree 3; plus a camera and a smooth random target image.
    Returns (gaussians, viewmat [4, 4], K [3, 3], target [H, W, 3])."""
    gen = torch.Generator().manual_seed(seed)
    points = (torch.rand(n, 3, generator=gen) * 2 - 1) * torch.tensor([1.6, 1.6, 1.0])
    points[:, 2] += 3.5
    g = Gaussians.from_points(points, torch.rand(n, 3, generator=gen), sh_degree=3)
    opacity = torch.rand(n, generator=gen) * 0.9 + 0.05
    g = Gaussians(g.means, g.log_scales, g.quats, torch.log(opacity / (1 - opacity)), g.sh)
    focal = SIZE / (2 * torch.tan(torch.tensor(torch.pi / 6)))
    K = torch.tensor([[focal, 0, SIZE / 2], [0, focal, SIZE / 2], [0, 0, 1]])
    coarse = torch.rand(1, 3, 8, 8, generator=gen)
    target = torch.nn.functional.interpolate(coarse, size=(SIZE, SIZE), mode="bilinear")[0]
    return g, torch.eye(4), K, target.permute(1, 2, 0).contiguous()


def time_iterations(n: int, backend: str, repeats: int, warmup: int) -> dict:
    """Median wall time of a full training iteration (and the process CPU time, summed over threads,
    which a loaded machine inflates less); also the projection + binning share."""
    scene, viewmat, K, target = make_scene(n)
    params = [t.clone().requires_grad_() for t in
              (scene.means, scene.log_scales, scene.quats, scene.opacity_logits, scene.sh)]
    optimiser = torch.optim.Adam([{"params": [p], "lr": lr} for p, lr in
                                  zip(params, (1.6e-4, 5e-3, 1e-3, 5e-2, 2.5e-3))], eps=1e-15)
    times, cpu_times = [], []
    for step in range(warmup + repeats):
        start, cpu_start = time.perf_counter(), time.process_time()
        out = render(Gaussians(*params), viewmat, K, SIZE, SIZE, backend=backend)
        loss = (out.rgb - target).abs().mean()
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()
        if step >= warmup:
            times.append(time.perf_counter() - start)
            cpu_times.append(time.process_time() - cpu_start)
    with torch.no_grad():
        g = Gaussians(*params)
        start = time.perf_counter()
        for _ in range(repeats):
            proj = project_gaussians(g.means, g.quats, g.scales, g.opacities, viewmat, K, SIZE, SIZE)
            bins = bin_gaussians(proj, SIZE, SIZE)
        project_bin = (time.perf_counter() - start) / repeats
    return {"gaussians": n, "backend": backend, "threads": torch.get_num_threads(),
            "iteration_ms": round(1000 * statistics.median(times), 1),
            "all_ms": [round(1000 * t, 1) for t in times],
            "process_cpu_ms": round(1000 * statistics.median(cpu_times), 1),
            "project_and_bin_ms": round(1000 * project_bin, 1),
            "tile_pairs": int(bins.gauss_ids.numel())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--counts", type=int, nargs="+", default=[10_000, 20_000, 50_000])
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--repeats", type=int, default=5, help="timed C++ iterations")
    parser.add_argument("--torch-repeats", type=int, default=2, help="timed PyTorch iterations")
    parser.add_argument("--out", help="also write the JSON here")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO)
    rows = []
    for threads in args.threads:
        torch.set_num_threads(threads)
        for n in args.counts:
            cpp = time_iterations(n, "cpp", args.repeats, warmup=2)
            ref = time_iterations(n, "torch", args.torch_repeats, warmup=1)
            cpp["speedup_vs_torch"] = round(ref["iteration_ms"] / cpp["iteration_ms"], 1)
            rows += [cpp, ref]
            log.info("%s", json.dumps(cpp))
            log.info("%s", json.dumps(ref))
    result = {"image": f"{SIZE}x{SIZE}", "torch": torch.__version__, "rows": rows}
    print(json.dumps(result, indent=1))
    if args.out:
        with open(args.out, "w") as handle:
            json.dump(result, handle, indent=1)


if __name__ == "__main__":
    main()
