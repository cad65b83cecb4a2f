"""Benchmark of the cache's checks (issue 58): the full check of `run.action=verify` (every byte of every entry
hashed) against the compute time of those entries, and the size check every cache hit makes against a cached rerun.

Usage: python -m benchmarks.cache_verify CACHE [--rerun-seconds S] [--command TEXT]

CACHE is a copy of a run's cache: the first verify records the sizes and hashes of the entries written before
manifests kept them (docs/cache.md), which changes their manifests. Measured: `compute_seconds`, the sum of the
entries' manifest `seconds`; `first_verify_seconds` (hashes recorded where missing) and `verify_seconds` (a second
verify, every entry checked against its record); `size_check_seconds`, the cheap check of every entry (what a
cached rerun of all of them adds); and, with --rerun-seconds, that share of a cached rerun (`/usr/bin/time python
dag.py run.cache_dir=CACHE`, after the run that filled it). Prints the figures as JSON and adds a section to
benchmarks/results/cache_verify.md.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from stages.engine.cache_entry import MANIFEST, entry_problem, read_manifest
from stages.engine.cache_verify import verify_cache

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "cache_verify.md"


def entries(cache: Path) -> list[Path]:
    """The entries (folders with a manifest) of every stage of `cache`."""
    return sorted(path.parent for path in cache.glob(f"*/*/{MANIFEST}") if ".tmp-" not in path.parent.name)


def measure(cache: Path, rerun_seconds: float | None) -> dict:
    """The figures of the module doc for `cache`."""
    found = entries(cache)
    compute = sum(float(read_manifest(entry).get("seconds", 0.0)) for entry in found)
    started = time.perf_counter()
    first = verify_cache(cache)
    first_seconds = time.perf_counter() - started
    started = time.perf_counter()
    second = verify_cache(cache)
    verify_seconds = time.perf_counter() - started
    started = time.perf_counter()
    problems = [entry_problem(entry) for entry in found]
    size_seconds = time.perf_counter() - started
    result = {"cache": str(cache), "entries": len(found), "bytes": sum(c.bytes for c in second),
              "files": sum(len(read_manifest(entry).get("files", {})) for entry in found),
              "compute_seconds": round(compute, 1), "first_verify_seconds": round(first_seconds, 2),
              "recorded_by_first_verify": sum(c.status == "recorded" for c in first),
              "verify_seconds": round(verify_seconds, 2), "verify_share_of_compute": verify_seconds / compute,
              "bad": [c.path.name for c in second if c.status == "bad"],
              "size_check_seconds": round(size_seconds, 3), "size_check_problems": sum(p is not None for p in problems)}
    if rerun_seconds:
        result.update(rerun_seconds=rerun_seconds, size_check_share_of_rerun=size_seconds / rerun_seconds)
    return result


def write_markdown(result: dict, command: str) -> None:
    """Add a section to benchmarks/results/cache_verify.md: the targets and what was measured."""
    rerun = (f"{result['size_check_seconds']} s = {result['size_check_share_of_rerun']:.2%} of the cached rerun's "
             f"{result['rerun_seconds']} s" if "rerun_seconds" in result else
             f"{result['size_check_seconds']} s (no cached rerun timed: --rerun-seconds)")
    before = RESULTS.read_text() if RESULTS.is_file() else "# The cache's checks (issue 58)\n"
    RESULTS.write_text(before + "\n".join([
        "", f"## {Path(result['cache']).name}", "", f"`{command}`", "",
        "| what | target | measured |", "|---|---|---|",
        f"| full verify (SHA-256 of every file) | <= 10 % of the run's compute | {result['verify_seconds']} s for "
        f"{result['entries']} entries, {result['files']} files, {result['bytes'] / 1e6:.0f} MB = "
        f"{result['verify_share_of_compute']:.2%} of their {result['compute_seconds']} s of compute |",
        f"| the first verify of entries written before manifests recorded files | (once) | "
        f"{result['first_verify_seconds']} s, {result['recorded_by_first_verify']} entries recorded |",
        f"| size check of every entry (what a cached rerun adds) | <= 10 % of a cached rerun | {rerun} |", "",
        "All figures: `" + json.dumps(result) + "`", ""]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("cache", type=Path, help="a copy of a run's cache folder")
    parser.add_argument("--rerun-seconds", type=float, help="wall seconds of a cached rerun of the run that filled it")
    parser.add_argument("--command", default="", help="the command line to note in the results (default: this one)")
    args = parser.parse_args()
    result = measure(args.cache, args.rerun_seconds)
    print(json.dumps(result, indent=1))
    write_markdown(result, args.command or f"python -m benchmarks.cache_verify {args.cache}"
                   + (f" --rerun-seconds {args.rerun_seconds}" if args.rerun_seconds else ""))


if __name__ == "__main__":
    main()
