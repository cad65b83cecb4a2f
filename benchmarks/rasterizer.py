"""Benchmark: one training iteration (render + L1 + backward + Adam step) at 256x256.

Compares the C++ kernel with the pure-PyTorch reference in the same run, for several Gaussian
counts and thread counts, and splits the C++ iteration into projection + binning vs the rest.
Prints one JSON object (and writes it with --out).

    OMP_WAIT_POLICY=PASSIVE python -m benchmarks.rasterizer --out /tmp/rasterizer.json

With `--device cuda` it compares the two CUDA backends on the same scenes instead: our PyTorch path
on the GPU ("cuda") and gsplat ("gsplat", `pip install -e ".[gpu]"`), with their ratio, after a
first gsplat call that builds its CUDA code (timed apart). Target (H100): gsplat at most 5 ms per
iteration at 20k Gaussians. Without a GPU it prints "no CUDA device: skipped".

    python -m benchmarks.rasterizer --device cuda --out benchmarks/results/rasterizer_cuda.json
"""
from __future__ import annotations

import argparse
import json
import logging
import statistics
import time
from importlib.metadata import version

import torch

from stages.lib.gaussians.binning import bin_gaussians
from stages.lib.gaussians.model import Gaussians
from stages.lib.gaussians.projection import project_gaussians
from stages.lib.gaussians.rasterize import render
from stages.lib.gaussians.rasterize_gsplat import gsplat_unavailable

SIZE = 256
CUDA_TARGET_MS = {20_000: 5.0}  # gsplat, per iteration at 256x256 on an H100 (issue 35)
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


def time_iterations(n: int, backend: str, repeats: int, warmup: int, device: str = "cpu") -> dict:
    """Median wall time of a full training iteration (and the process CPU time, summed over threads,
    which a loaded machine inflates less); also the projection + binning share (our backends)."""
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    scene, viewmat, K, target = (x.to(device) for x in make_scene(n))
    params = [t.clone().requires_grad_() for t in
              (scene.means, scene.log_scales, scene.quats, scene.opacity_logits, scene.sh)]
    optimiser = torch.optim.Adam([{"params": [p], "lr": lr} for p, lr in
                                  zip(params, (1.6e-4, 5e-3, 1e-3, 5e-2, 2.5e-3))], eps=1e-15)
    times, cpu_times = [], []
    for step in range(warmup + repeats):
        sync()
        start, cpu_start = time.perf_counter(), time.process_time()
        out = render(Gaussians(*params), viewmat, K, SIZE, SIZE, backend=backend)
        loss = (out.rgb - target).abs().mean()
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()
        sync()
        if step >= warmup:
            times.append(time.perf_counter() - start)
            cpu_times.append(time.process_time() - cpu_start)
    row = {"gaussians": n, "backend": backend, "device": device, "threads": torch.get_num_threads(),
           "iteration_ms": round(1000 * statistics.median(times), 2),
           "all_ms": [round(1000 * t, 2) for t in times],
           "process_cpu_ms": round(1000 * statistics.median(cpu_times), 1)}
    if backend == "gsplat":
        return row
    with torch.no_grad():
        g = Gaussians(*params)
        sync()
        start = time.perf_counter()
        for _ in range(repeats):
            proj = project_gaussians(g.means, g.quats, g.scales, g.opacities, viewmat, K, SIZE, SIZE)
            bins = bin_gaussians(proj, SIZE, SIZE)
        sync()
        project_bin = (time.perf_counter() - start) / repeats
    return {**row, "project_and_bin_ms": round(1000 * project_bin, 1), "tile_pairs": int(bins.gauss_ids.numel())}


def cuda_rows(counts: list[int], repeats: int) -> dict:
    """Our PyTorch path on the GPU against gsplat, per Gaussian count (module docstring)."""
    missing = gsplat_unavailable(torch.device("cuda"), torch.float32)
    if missing:
        raise SystemExit(f"the gsplat backend cannot run: {missing}")
    started = time.perf_counter()
    time_iterations(1000, "gsplat", repeats=1, warmup=0, device="cuda")  # builds gsplat's CUDA code once
    first_call_s = round(time.perf_counter() - started, 1)
    rows = []
    for n in counts:
        ours = time_iterations(n, "cuda", repeats, warmup=2, device="cuda")
        theirs = time_iterations(n, "gsplat", repeats, warmup=3, device="cuda")
        theirs["speedup_vs_cuda"] = round(ours["iteration_ms"] / theirs["iteration_ms"], 1)
        if n in CUDA_TARGET_MS:
            theirs["target_ms"] = CUDA_TARGET_MS[n]
            theirs["target_met"] = theirs["iteration_ms"] <= CUDA_TARGET_MS[n]
        rows += [ours, theirs]
        log.info("%s", json.dumps(ours))
        log.info("%s", json.dumps(theirs))
    return {"gpu": torch.cuda.get_device_name(), "gsplat": version("gsplat"), "gsplat_first_call_s": first_call_s,
            "rows": rows}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--counts", type=int, nargs="+", default=[10_000, 20_000, 50_000])
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--repeats", type=int, default=5, help="timed C++ iterations")
    parser.add_argument("--torch-repeats", type=int, default=2, help="timed PyTorch iterations")
    parser.add_argument("--out", help="also write the JSON here")
    parser.add_argument("--device", choices=["cpu", "cuda"], default="cpu",
                        help="cuda: our PyTorch path on the GPU against gsplat (default counts 10k-200k)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO)
    if args.device == "cuda":
        if not torch.cuda.is_available():
            print("no CUDA device: skipped")
            return
        counts = args.counts if args.counts != parser.get_default("counts") else [10_000, 20_000, 50_000, 200_000]
        result = {"image": f"{SIZE}x{SIZE}", "torch": torch.__version__, **cuda_rows(counts, max(args.repeats, 20))}
        print(json.dumps(result, indent=1))
        if args.out:
            with open(args.out, "w") as handle:
                json.dump(result, handle, indent=1)
        return
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
