"""Benchmark of the `sample` stage: wall and CPU time, disk size, and a determinism check.

Usage (from the repository root):
  python -m benchmarks.sample [--out DIR] [--workers 2] [--tiny] [--repeat-check] [--json PATH]
    renders the full-size sample (defaults of SampleConfig) into DIR (default: a temp folder);
    --tiny uses the test suite's small config; --repeat-check renders a second time and compares bytes.
Prints one JSON object.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import logging
import resource
import shutil
import tempfile
import time
from pathlib import Path

from stages.engine.context import Context
from stages.sample.run import run

TINY = {"width": 160, "height": 120, "num_frames": 12, "num_backgrounds": 4, "num_indomain": 2, "num_test": 4,
        "objects": [{"name": "bottle", "height_m": 0.25}, {"name": "plant", "height_m": 0.30},
                    {"name": "vase", "height_m": 0.22}]}


def _digests(folder: Path) -> dict[str, str]:
    """sha256 of every file except sample.json (which holds timings)."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file() and p.name != "sample.json"}


def _render(out: Path, params: dict) -> dict:
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    cpu0 = time.process_time()
    children0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.perf_counter()
    metrics = run(Context("sample", "sample", params, {}, out))
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return {"wall_s": round(time.perf_counter() - started, 1),
            "cpu_s": round(time.process_time() - cpu0 + children.ru_utime - children0.ru_utime
                           + children.ru_stime - children0.ru_stime, 1),
            "disk_mb": round(metrics["disk_bytes"] / 1e6, 1), "metrics": metrics}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--tiny", action="store_true")
    parser.add_argument("--repeat-check", action="store_true")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO)
    params = {**(TINY if args.tiny else {}), "workers": args.workers}
    out = args.out or Path(tempfile.mkdtemp(prefix="sample_bench_"))
    report = {"params": params, "out": str(out), "first": _render(out, params)}
    if args.repeat_check:
        first = _digests(out)
        again = out.with_name(out.name + "_again")
        report["second"] = _render(again, params)
        second = _digests(again)
        report["identical_files"] = sum(first.get(k) == v for k, v in second.items())
        report["differing_files"] = sorted(k for k, v in second.items() if first.get(k) != v)
        report["total_files"] = len(first)
    print(json.dumps(report, indent=1))
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
