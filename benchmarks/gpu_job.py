"""Benchmark report: the whole default job with one GPU, stage by stage.

    python -m benchmarks.gpu_job --gpu-summary GPU_RUN/summary.json --cpu-summary CPU_RUN/summary.json \
        [--out benchmarks/results/gpu/job.md]
    python -m benchmarks.gpu_job --gpu-seconds splat_train=S train_maskrcnn=S eval=S bg_depth=S --cpu-summary ...

GPU_RUN is a cold `python dag.py` on the GPU machine (run.device=auto picks its CUDA device), CPU_RUN a cold
`python dag.py` of the same commit on the 2 cores. The stages that run on the run's device (their spec's MACHINE
names "device": splat_train, bg_depth, train_maskrcnn, eval) are taken from GPU_RUN, the others (sample, frames,
sfm, extract, planes, compose, dataset: CPU-bound) from CPU_RUN: the job on a machine of 2 cores and one GPU, as a
sum of compute seconds per stage (the engine runs some nodes side by side, so the job's wall is shorter), and
labelled so. With --gpu-seconds instead of a GPU run's summary, the device stages' seconds are given as measured
elsewhere (the benchmarks of each stage on a GPU machine that cannot run the whole job). Prints the table, what
dominates, and what halving the sum would take; writes it to --out.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from stages.app.pipeline import ORDER, STAGES

RESULTS = Path(__file__).parent / "results"


def on_device(stage: str) -> bool:
    """Whether `stage` runs on the run's device (a GPU when there is one): its spec's MACHINE names "device"."""
    return "device" in STAGES[stage].machine


def stage_seconds(summary: Path) -> dict[str, float]:
    """{stage: compute seconds} of a run's summary.json; SystemExit naming the file when it has none."""
    seconds = json.loads(summary.read_text()).get("compute_seconds_by_stage")
    if not seconds:
        raise SystemExit(f"{summary}: no compute_seconds_by_stage (not a dag.py run's summary.json, or nothing ran)")
    return seconds


def job_rows(gpu: dict[str, float], cpu: dict[str, float]) -> list[dict]:
    """Per stage in the pipeline's order: where it runs, its seconds in each run and the one counted."""
    rows = []
    for stage in (s for s in ORDER if s in gpu or s in cpu):
        device = on_device(stage)
        counted = gpu.get(stage) if device else cpu.get(stage)
        if counted is None:
            raise SystemExit(f"stage {stage} is missing from the {'GPU' if device else '2-core'} run's summary: "
                             "give cold runs of the whole default job")
        rows.append({"stage": stage, "on": "GPU" if device else "2 cores", "gpu_run_s": gpu.get(stage),
                     "cpu_run_s": cpu.get(stage), "counted_s": counted})
    return rows


def halving(rows: list[dict]) -> str:
    """What dominates the sum and what halving it takes, in words."""
    total = sum(r["counted_s"] for r in rows)
    ranked = sorted(rows, key=lambda r: -r["counted_s"])
    top = ranked[0]
    share = top["counted_s"] / total
    if share > 0.5:
        need = f"{top['stage']} at {top['counted_s'] - total / 2:.0f} s or less, the others as they are"
    else:
        largest, held = [], 0.0
        for row in ranked:
            largest.append(row["stage"])
            held += row["counted_s"]
            if held >= total / 2:
                break
        need = (f"{total / 2:.0f} s less, from stages that hold {held:.0f} s together at the least "
                f"({', '.join(largest)})")
    return (f"{top['stage']} dominates ({top['counted_s']:.0f} s, {100 * share:.0f} % of {total:.0f} s, on "
            f"{top['on']}); halving the sum takes {need}.")


def given_seconds(pairs: list[str]) -> dict[str, float]:
    """{stage: seconds} of STAGE=SECONDS pairs; SystemExit naming a pair that is not one, or a stage that does not
    run on the device."""
    seconds = {}
    for pair in pairs:
        stage, _, value = pair.partition("=")
        try:
            seconds[stage] = float(value)
        except ValueError:
            raise SystemExit(f"--gpu-seconds {pair}: give STAGE=SECONDS") from None
        if stage not in ORDER or not on_device(stage):
            raise SystemExit(f"--gpu-seconds {pair}: {stage} is not a stage that runs on the device")
    return seconds


def markdown(rows: list[dict], gpu_source: str, cpu_summary: Path) -> str:
    """The report (module docstring)."""
    def cell(value: float | None) -> str:
        return "-" if value is None else f"{value:.1f}"

    total = sum(r["counted_s"] for r in rows)
    lines = ["# The default job with one GPU, stage by stage", "",
             f"GPU run: {gpu_source}; 2-core run: `{cpu_summary}`. Stages on the device from the GPU run, "
             "the others from the 2-core run; compute seconds summed (a sum, not the job's wall).", "",
             "| stage | runs on | GPU machine (s) | 2 cores (s) | counted (s) | share |", "|---|---|---|---|---|---|"]
    lines += [f"| {r['stage']} | {r['on']} | {cell(r['gpu_run_s'])} | {cell(r['cpu_run_s'])} | "
              f"{r['counted_s']:.1f} | {100 * r['counted_s'] / total:.0f} % |" for r in rows]
    lines += [f"| **sum** | | | | **{total:.1f}** ({total / 60:.1f} min) | |", "", halving(rows)]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    gpu = parser.add_mutually_exclusive_group(required=True)
    gpu.add_argument("--gpu-summary", type=Path, help="summary.json of a cold dag.py run on the GPU machine")
    gpu.add_argument("--gpu-seconds", nargs="+", metavar="STAGE=SECONDS",
                     help="the device stages' seconds, measured on a GPU machine by their benchmarks")
    parser.add_argument("--cpu-summary", type=Path, required=True)
    parser.add_argument("--out", type=Path, default=RESULTS / "gpu" / "job.md")
    args = parser.parse_args()
    if args.gpu_summary:
        gpu_seconds, source = stage_seconds(args.gpu_summary), f"`{args.gpu_summary}`"
    else:
        gpu_seconds, source = given_seconds(args.gpu_seconds), "given (" + ", ".join(args.gpu_seconds) + ")"
    rows = job_rows(gpu_seconds, stage_seconds(args.cpu_summary))
    text = markdown(rows, source, args.cpu_summary)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
