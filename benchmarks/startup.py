"""Time to first answer: how long `python dag.py` takes to report a wrong setting, a missing file or its help,
and to plan the default job, against the 3-second target (issue 31).

    python -m benchmarks.startup [--repeats 5]

Each command runs `--repeats` times in a fresh process from a temporary folder (so nothing is cached and no
outputs/ folder is touched); the table gives the median and the slowest wall seconds and whether the command
answered as expected (its exit status and a phrase of its message). For scale, the same run times `import torch`
alone: what every command cost before the stages' heavy libraries were loaded only when a node runs.
Writes benchmarks/results/startup.md.
"""
from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from tests.factories.configs import ROOT

TARGET_S = 3.0
RESULTS = Path(__file__).resolve().parent / "results"


def cases(scratch: Path) -> list[tuple[str, list[str], int | None, str]]:
    """(name, dag.py arguments, expected exit status or None for any non-zero, a phrase of the answer)."""
    return [
        ("--help", ["--help"], 0, "Actions"),
        ("wrong value", ["bg_depth.provider=sidecr"], None, "Invalid value 'sidecr'"),
        ("+ typo", ["+compose.num_imags=10"], 2, "did you mean compose.num_images"),
        ("value out of range", ["compose.group_share=2"], 2, "group_share must be in [0, 1]"),
        ("missing data file", ["data=/nowhere/my_data.yaml"], 1, "no such file"),
        ("missing photo folder", ["data=folder", f"data.backgrounds={scratch / 'no_photos'}",
                                  "data.objects=[{name: mug, height_m: 0.1, video: mug.mp4}]"], 2,
         "background folder not found"),
        ("plan of the default job", ["run.action=plan", f"run.cache_dir={scratch / 'cache'}"], 0, "would-run"),
    ]


def timed(command: list[str], cwd: Path) -> tuple[float, subprocess.CompletedProcess]:
    """Wall seconds of one command and its result."""
    started = time.perf_counter()
    done = subprocess.run(command, cwd=cwd, capture_output=True, text=True, timeout=300)
    return time.perf_counter() - started, done


def main() -> None:
    """Command line: see the module docstring."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        scratch = Path(tmp)
        for name, arguments, status, phrase in cases(scratch):
            seconds, answered = [], True
            for repeat in range(args.repeats):
                run_dir = scratch / f"run_{len(rows)}_{repeat}"
                took, done = timed([sys.executable, str(ROOT / "dag.py"), *arguments, f"hydra.run.dir={run_dir}"],
                                   scratch)
                seconds.append(took)
                code_ok = done.returncode != 0 if status is None else done.returncode == status
                answered &= code_ok and phrase in done.stdout + done.stderr
            rows.append((name, statistics.median(seconds), max(seconds), answered))
        torch_s = statistics.median(timed([sys.executable, "-c", "import torch"], scratch)[0]
                                    for _ in range(args.repeats))
    lines = ["# Time to first answer of `python dag.py` (issue 31)", "",
             f"`python -m benchmarks.startup --repeats {args.repeats}` (fresh process each time, empty cache; "
             f"target {TARGET_S:.0f} s):", "",
             "| command | median s | slowest s | answered as expected | within target |", "|---|---|---|---|---|"]
    lines += [f"| {name} | {median:.2f} | {worst:.2f} | {'yes' if ok else 'NO'} | {'yes' if worst <= TARGET_S else 'NO'} |"
              for name, median, worst, ok in rows]
    lines += ["", f"For scale, in the same run: `python -c \"import torch\"` alone took {torch_s:.2f} s (median)."]
    text = "\n".join(lines) + "\n"
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "startup.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
