"""Issue 59's GPU measurements as one prepared command, in its order of importance; each part writes its figures and
its log under --out, and a failed part does not stop the next.

    python -m benchmarks.gpu_session --out benchmarks/results/gpu/<date> [--dog-sfm SFM_DIR] \
        [--parts iteration dog job detector] [--dataset DIR --testset DIR] [--epochs 4 6 10] [--seeds 0 1 2]

1. iteration: our gsplat step against the bare gsplat loop, and the bare loop with a compiled loss
   (benchmarks/gsplat_step.py --compiled-loss): gsplat_step.json and the profile tables.
2. dog: the plush dog through splat_train on the GPU (benchmarks/splat_train.py --gpu, at the GPU budget's own
   2000 iterations; today's budget with gsplat beside it, not on the PyTorch path, whose 2 minutes say nothing new):
   splat_train_gpu.json. Its sfm folder is --dog-sfm (made on any machine:
   `run_real_chain(Path(cache), "sfm")` of tests/factories/runs.py, some 12 MB), else ../shared/real's photos.
3. job: a cold default `python dag.py` on this machine (run.device=auto: the GPU), its summary as dag_summary.json,
   and benchmarks/gpu_job.py against the 2-core run of --cpu-summary: job.md. It needs every dependency of the
   project there (Open3D among them) and writes some 1 GB of cache; where they do not import it is skipped, named
   in its log, and job.md can be made later from the stage seconds measured elsewhere (gpu_job.py --gpu-seconds).
4. detector: `train_maskrcnn.cuda` on a composed dataset (--dataset, else the job's), evaluated on test A
   (--testset, else the job's sample's), through benchmarks/detector.py runs --device cuda: a curve over --epochs
   at seed 0, then each of --seeds at the last of --epochs, into detector.json (seed 0's run there is not
   trained twice).
Without a CUDA device it prints "no CUDA device: skipped".
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import logging
import subprocess
import sys
import time
from pathlib import Path

import torch

from stages.app.summary import summary_outcomes

log = logging.getLogger("benchmarks.gpu_session")
PARTS = ("iteration", "dog", "job", "detector")
RESULTS = Path(__file__).parent / "results"
CPU_SUMMARY = RESULTS / "gpu" / "cpu_job_summary.json"  # a cold default run on the 2 cores (its commit inside)


def run_part(name: str, command: list[str], out: Path) -> bool:
    """Run one part's command with its output into <out>/<name>.log; whether it succeeded."""
    started = time.perf_counter()
    with open(out / f"{name}.log", "w") as log_file:
        done = subprocess.run(command, stdout=log_file, stderr=subprocess.STDOUT)
    log.info("%s: exit %d after %.0f s (%s)", name, done.returncode, time.perf_counter() - started, " ".join(command))
    return done.returncode == 0


def missing_job_dependency() -> str | None:
    """Why `python dag.py` cannot run on this machine (a dependency that does not import), or None."""
    for module in ("open3d", "pycolmap", "hydra", "pycocotools", "onnxruntime", "cv2", "kornia"):
        if importlib.util.find_spec(module) is None:
            return f"{module} is not installed here: the whole job needs every dependency of the project"
    return None


def newest_summary(before: set[Path]) -> Path:
    """The summary.json of the dag.py run that made the newest folder of outputs/runs not in `before`."""
    new = sorted(set(Path("outputs/runs").glob("*/summary.json")) - before)
    if not new:
        raise SystemExit("dag.py wrote no summary.json under outputs/runs")
    return new[-1]


def dataset_and_test_a(summary: Path) -> tuple[Path, Path]:
    """The first composed dataset and the sample's test A of a run's summary."""
    outcomes = summary_outcomes(json.loads(summary.read_text()))
    paths = {o["stage"]: Path(o["path"]) for o in reversed(outcomes)}  # the first of each stage wins
    return paths["dataset"], paths["sample"] / "test_a"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=RESULTS / "gpu" / time.strftime("%Y-%m-%d"))
    parser.add_argument("--parts", nargs="+", choices=PARTS, default=list(PARTS))
    parser.add_argument("--dog-sfm", type=Path)
    parser.add_argument("--cpu-summary", type=Path, default=CPU_SUMMARY)
    parser.add_argument("--cache", type=Path, default=Path("/tmp/gpu_session_cache"))
    parser.add_argument("--dataset", type=Path, help="a composed COCO dataset folder for the detector part")
    parser.add_argument("--testset", type=Path, help="the test set it is evaluated on (the sample's test_a)")
    parser.add_argument("--epochs", type=float, nargs="+", default=[4.0, 6.0, 10.0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    if not torch.cuda.is_available():
        print("no CUDA device: skipped")
        return
    args.out.mkdir(parents=True, exist_ok=True)
    python = [sys.executable, "-m"]
    if "iteration" in args.parts:
        run_part("iteration", python + ["benchmarks.gsplat_step", "--compiled-loss", "--out",
                                        str(args.out / "gsplat_step.json")], args.out)
    if "dog" in args.parts:
        sfm = ["--sfm", str(args.dog_sfm)] if args.dog_sfm else ["--cache", str(args.cache)]
        run_part("dog", python + ["benchmarks.splat_train", "--gpu", *sfm, "--skip-torch", "--gpu-iterations", "2000",
                                  "--out", str(args.out / "splat_train_gpu.json")], args.out)
    dataset, testset = args.dataset, args.testset
    if "job" in args.parts:
        missing = missing_job_dependency()
        if missing:
            (args.out / "job.log").write_text(f"skipped: {missing}\n")
            log.info("job: skipped: %s", missing)
        else:
            before = set(Path("outputs/runs").glob("*/summary.json"))
            if run_part("dag", [sys.executable, "dag.py", f"run.cache_dir={args.cache}"], args.out):
                summary = newest_summary(before)
                (args.out / "dag_summary.json").write_text(summary.read_text())
                run_part("job", python + ["benchmarks.gpu_job", "--gpu-summary", str(summary), "--cpu-summary",
                                          str(args.cpu_summary), "--out", str(args.out / "job.md")], args.out)
                job_dataset, job_testset = dataset_and_test_a(summary)
                dataset, testset = dataset or job_dataset, testset or job_testset
    if "detector" in args.parts:
        if dataset is None or testset is None:
            (args.out / "detector.log").write_text("skipped: no --dataset and --testset, and no job run to take "
                                                   "them from\n")
            return
        detector = python + ["benchmarks.detector", "runs", "--device", "cuda", "--dataset", str(dataset),
                             "--testset", str(testset), "--work", str(args.cache / "detector")]
        curve = [f"--config=epochs_{e:g}=" + json.dumps({"epochs": e}) for e in args.epochs]
        out = ["--out", str(args.out / "detector.json")]  # one file: a run already in it is not trained again
        run_part("detector_epochs", detector + curve + out, args.out)
        chosen = f"--config=epochs_{args.epochs[-1]:g}=" + json.dumps({"epochs": args.epochs[-1]})
        for seed in args.seeds:
            run_part(f"detector_seed{seed}", detector + [chosen, "--seed", str(seed), *out], args.out)


if __name__ == "__main__":
    main()
