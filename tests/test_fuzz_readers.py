"""Every reader of a file from a stranger, fuzzed (issue 58): truncated files, lying headers, wrong magic, random
bytes, huge declared counts, NaNs, zero-size files, a folder where a file is expected and unreadable files each end
in the project's StageError naming the file or in a clean result, never another exception, a crash or a hang, and
no case's child process peaks above 1 GB of resident memory (tests/factories/fuzz_child.py: one child per reader,
under an address-space limit). The default run draws FUZZ_EXAMPLES Hypothesis cases per reader besides its named
ones (about 40 s for all readers); `python -m pytest -m fuzz_long` draws 10,000 per reader.
"""
from __future__ import annotations

from pathlib import Path

import pytest

from tests.factories.fuzz_child import fuzz_reader
from tests.factories.fuzz_readers import READERS

FUZZ_EXAMPLES = 40  # Hypothesis cases per reader in the default run
LONG_EXAMPLES = 10_000
SEED = 58
PEAK_MB = 1024
CASE_SECONDS = 30.0  # a loaded machine; the cases take 0.01 to 2 s


def check_results(results: dict, minimum: int) -> None:
    """No case ended in another exception, each named error names its file, no case peaked above PEAK_MB or took
    longer than CASE_SECONDS, and at least `minimum` cases ran."""
    cases = results["named"] + results["drawn"]
    assert results["failure"] is None, results["failure"]
    assert [(c["name"], c["message"]) for c in results["named"] if c["outcome"] == "other"] == []
    unnamed = [(c["name"], c["message"]) for c in results["named"] if c["outcome"] == "named"
               and Path(c["file"]).name not in c["message"] and READERS[results["reader"]].target not in c["message"]]
    assert unnamed == []
    assert len(cases) >= minimum
    assert max(c["peak_mb"] for c in cases) < PEAK_MB
    assert max(c["seconds"] for c in cases) < CASE_SECONDS


@pytest.mark.parametrize("reader", sorted(READERS))
def test_every_bad_file_ends_in_a_named_error_or_a_clean_result(tmp_path, reader):
    check_results(fuzz_reader(reader, tmp_path, FUZZ_EXAMPLES, SEED), minimum=50)


@pytest.mark.fuzz_long
@pytest.mark.parametrize("reader", sorted(READERS))
def test_ten_thousand_cases_per_reader(tmp_path, reader):
    check_results(fuzz_reader(reader, tmp_path, LONG_EXAMPLES, SEED, timeout=3 * 3600), minimum=LONG_EXAMPLES)
