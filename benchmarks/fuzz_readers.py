"""The fuzz corpus of the file readers (issue 58) as a report: every reader in a child process of its own
(tests/factories/fuzz_child.py), its named cases and EXAMPLES cases drawn by Hypothesis, and what each ended in.

Usage: python -m benchmarks.fuzz_readers [--examples 40] [--seed 58] [--readers ply,coco] [--out FOLDER]

Prints one line per reader and writes benchmarks/results/fuzz_readers.md: a table per reader of its named cases
(the field cases grouped: one row per header field, the message of its first lying value) with the message each
ended in, and the counts of the drawn ones. docs/bad_inputs.md lists the named cases from it. The default test
run draws 40 per reader (tests/test_fuzz_readers.py), `python -m pytest -m fuzz_long` 10,000.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from collections import Counter
from pathlib import Path

from tests.factories.fuzz_child import fuzz_reader
from tests.factories.fuzz_inputs import HUGE
from tests.factories.fuzz_readers import READERS

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "fuzz_readers.md"


def named_rows(cases: list[dict]) -> list[str]:
    """Markdown rows `| case | file | what it ended in |`, the lying values of one field in one row."""
    rows, fields = [], set()
    for case in cases:
        name = case["name"]
        field, _, value = name.rpartition(" = ")
        if field and value.isdigit() and int(value) in HUGE:
            if (case["file"], field) in fields:
                continue
            fields.add((case["file"], field))
            name = f"{field} = each of {', '.join(map(str, HUGE))} (first shown)"
        ended = {"named": "StageError: ", "clean": "read" + (", warning: " if case["message"] else ""),
                 "other": "ANOTHER EXCEPTION: "}[case["outcome"]]
        message = case["message"].split("\n")[0].replace("|", "\\|")
        rows.append(f"| {name} | {case['file']} | {ended}{message} |")
    return rows


def summary_row(name: str, results: dict, seconds: float) -> str:
    """One row of the summary table."""
    cases = results["named"] + results["drawn"]
    outcomes = Counter(case["outcome"] for case in cases)
    return (f"| {name} | {len(results['named'])} | {len(results['drawn'])} | {outcomes['named']} | {outcomes['clean']} "
            f"| {outcomes['other']} | {results['failure'] or '-'} | {max(c['peak_mb'] for c in cases):.0f} | "
            f"{max(c['seconds'] for c in cases):.2f} | {seconds:.0f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--examples", type=int, default=40, help="cases drawn by Hypothesis per reader")
    parser.add_argument("--seed", type=int, default=58)
    parser.add_argument("--readers", default=",".join(sorted(READERS)), help="comma-separated reader names")
    parser.add_argument("--out", type=Path, help="work folder (default: a temporary one)")
    args = parser.parse_args()
    work = args.out or Path(tempfile.mkdtemp(prefix="fuzz_readers_"))
    summary, details = [], []
    for name in args.readers.split(","):
        started = time.perf_counter()
        results = fuzz_reader(name, work / name, args.examples, args.seed, timeout=6 * 3600)
        summary.append(summary_row(name, results, time.perf_counter() - started))
        print(summary[-1], flush=True)
        details += ["", f"### {name}", "", "| case | file | what it ended in |", "|---|---|---|",
                    *named_rows(results["named"])]
    RESULTS.write_text("\n".join([
        "# Fuzzing the file readers (issue 58)", "",
        f"`python -m benchmarks.fuzz_readers --examples {args.examples} --seed {args.seed}`: each reader in a child "
        "process under an address-space limit (tests/factories/fuzz_child.py); peak = the highest resident memory of "
        "one case (VmHWM).", "",
        "| reader | named cases | drawn cases | StageError | clean | other exception | Hypothesis failure | peak MB "
        "| slowest case s | wall s |", "|---|---|---|---|---|---|---|---|---|---|", *summary, *details, ""]))


if __name__ == "__main__":
    main()
