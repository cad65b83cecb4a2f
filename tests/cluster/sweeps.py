"""The cluster tests' sweeps: the smoke DAG as a `python dag.py --multirun` sweep (on SLURM or locally), its jobs'
summaries and logs, and a cache entry's files without timings, to compare two runs."""
from __future__ import annotations

import json
import re
import subprocess
import sys
import time
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

from stages.engine.cache_entry import MANIFEST
from tests.factories.configs import ROOT

SHARED = ("sample", "frames", "sfm", "splat_train", "extract", "bg_depth", "planes")  # the same in every job
# The smoke DAG with the object models and planes shared by every job (only the per-job stages follow
# run.seed), one node at a time and one torch thread per job, as a one-CPU job runs it.
JOB = ("+experiment=smoke", "run.reseed=[compose,cut_and_paste,dataset,train_maskrcnn,eval]", "run.workers=1",
       "train_maskrcnn.threads=1", "eval.threads=1")
SWEEP_TIMEOUT_S = 600
RUNNING = re.compile(r"\] - (\w+)\[([^\]]*)\] running \((\w+)\)")
LOG_TIME = re.compile(r"^\[(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3})\]")


@dataclass
class Job:
    """One finished sweep job: its folder, summary.json and log."""

    folder: Path
    summary: dict
    log: str

    @property
    def name(self) -> tuple[str, int]:
        return self.summary["config"]["variant"]["name"], self.summary["config"]["run"]["seed"]

    def keys(self, stages: tuple[str, ...]) -> dict[tuple[str, str], str]:
        return {(r["stage"], r["item"]): r["key"] for r in self.summary["outcomes"] if r["stage"] in stages}

    def ran(self) -> list[tuple[str, str]]:
        """(stage, key) of the nodes this job computed, from its log."""
        return [(stage, key) for stage, _, key in RUNNING.findall(self.log)]

    def first_log_time(self) -> datetime:
        return datetime.strptime(LOG_TIME.match(self.log).group(1), "%Y-%m-%d %H:%M:%S,%f")


def dag_command(*overrides: str, sweep_dir: Path, cache: Path) -> list[str]:
    return [sys.executable, str(ROOT / "dag.py"), "--multirun", *JOB, *overrides, f"run.cache_dir={cache}",
            f"hydra.sweep.dir={sweep_dir}"]


def run_sweep(*overrides: str, sweep_dir: Path, cache: Path, env: dict[str, str]) -> tuple[list[Job], float]:
    """`python dag.py --multirun ...` to the end; its jobs (asserting it succeeded) and its wall time."""
    started = time.monotonic()
    done = subprocess.run(dag_command(*overrides, sweep_dir=sweep_dir, cache=cache), cwd=sweep_dir.parent, env=env,
                          capture_output=True, text=True, timeout=SWEEP_TIMEOUT_S)
    wall = time.monotonic() - started
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    return sweep_jobs(sweep_dir), wall


def sweep_jobs(sweep_dir: Path) -> list[Job]:
    return [Job(path.parent, json.loads(path.read_text()), (path.parent / "dag.log").read_text())
            for path in sorted(sweep_dir.glob("*/summary.json"))]


def node_outputs(folder: Path) -> dict[str, object]:
    """A cache entry's result files without timings: JSON files parsed, minus every "...second..." and
    "..._per_s" field; other files as bytes (images, annotations, model weights, predictions), Markdown with the
    cache's folder written <cache> (a dataset's card names the test set's folder in the cache).
    manifest.json is bookkeeping (when, how long, versions) and left out."""
    cache = str(folder.parent.parent).encode()
    found = {}
    for path in sorted(folder.rglob("*")):
        name = str(path.relative_to(folder))
        if path.is_file() and name != MANIFEST:
            found[name] = without_timings(json.loads(path.read_text())) if path.suffix == ".json" else path.read_bytes()
            if path.suffix == ".md":
                found[name] = found[name].replace(cache, b"<cache>")
    return found


def without_timings(value):
    if isinstance(value, dict):
        return {k: without_timings(v) for k, v in value.items() if "second" not in k and not k.endswith("per_s")}
    if isinstance(value, list):
        return [without_timings(v) for v in value]
    return value
