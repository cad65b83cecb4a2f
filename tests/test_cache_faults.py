"""Faults during a run (issue 58), each in driver processes of its own (tests/factories/toy_cache.py): the disk
fills while an entry is written (RLIMIT_FSIZE), a node's process is killed between writing its files and renaming
its folder, two runs share one cache and one of them is killed. In each, nothing half-written is ever trusted, the
next run finishes, and verify finds the cache whole."""
from __future__ import annotations

import signal
import time
from pathlib import Path

import pytest

from stages.engine.cache_entry import MANIFEST
from stages.engine.cache_verify import verify_cache
from tests.factories.toy_cache import start_driver, statuses

SIZE = 4096  # bytes of each payload


@pytest.fixture
def count_file(tmp_path, monkeypatch):
    path = tmp_path / "count.txt"
    monkeypatch.setenv("TOY_COUNT_FILE", str(path))
    return path


def drive(cache: Path, items: str, *options: str) -> tuple[dict[str, str], str]:
    """Run the driver to its end: ({label: status}, its output)."""
    out, _ = start_driver(cache, items, *options).communicate(timeout=120)
    return statuses(out), out


def entries_and_temps(cache: Path) -> tuple[list[Path], list[Path]]:
    """The folders with a manifest, and the temporary folders, of every stage."""
    return (sorted(p for p in cache.glob(f"*/*/{MANIFEST}") if ".tmp-" not in p.parent.name),
            sorted(cache.glob("*/.*.tmp-*")))


def assert_whole_after_a_clean_run(cache: Path, items: str) -> None:
    """The next run (no fault) finishes, and every entry of the cache is whole."""
    done, out = drive(cache, items)
    assert set(done.values()) <= {"ran", "cached"}, out
    assert {check.status for check in verify_cache(cache)} == {"whole"}
    assert entries_and_temps(cache)[1] == []


@pytest.mark.parametrize("options, failed, cause", [
    (("--fsize", str(SIZE // 2)), "payload[a]", "OSError: [Errno 27] File too large"),  # the stage's own file
    (("--fsize", str(SIZE + 1024), "--metrics-bytes", str(SIZE + 2048)), "payload[a]",
     "payload[a]: cannot write its cache entry"),  # the engine's metrics.json
])
def test_a_disk_that_fills_while_an_entry_is_written_leaves_no_entry(tmp_path, count_file, options, failed, cause):
    cache = tmp_path / "cache"
    done, out = drive(cache, "a", *options)
    assert done == {"payload[a]": "failed", "checksum[a]": "blocked"}, out
    assert cause in out
    assert entries_and_temps(cache) == ([], [])  # nothing half-written: no entry, no temporary folder
    assert_whole_after_a_clean_run(cache, "a")


def test_a_process_killed_between_writing_its_files_and_renaming_them_leaves_nothing_trusted(tmp_path, count_file):
    cache = tmp_path / "cache"
    driver = start_driver(cache, "a", "--kill-at-rename")
    driver.communicate(timeout=120)
    assert driver.returncode == -signal.SIGKILL
    manifests, temps = entries_and_temps(cache)
    assert manifests == [] and len(temps) == 1 and (temps[0] / MANIFEST).is_file()  # complete, but never renamed
    done, _ = drive(cache, "a")
    assert done == {"payload[a]": "ran", "checksum[a]": "ran"}
    assert_whole_after_a_clean_run(cache, "a")


def wait_for(path: Path, line: str, timeout: float = 60.0) -> None:
    deadline = time.time() + timeout
    while not (path.exists() and line in path.read_text().split()):
        assert time.time() < deadline, f"{line} did not start"
        time.sleep(0.05)


def test_two_runs_share_a_cache_and_one_is_killed(tmp_path, count_file):
    """Run A computes payload[a] (slowly); run B, started beside it, needs payload[a] too: it computes its other
    nodes meanwhile, then waits on payload[a]'s lock; A is killed mid-node. B takes over payload[a] (A's lock went
    with it), drops A's temporary folder and finishes; the next run finds everything cached and whole."""
    cache = tmp_path / "cache"
    first = start_driver(cache, "a", "--sleep", "60")
    wait_for(count_file, "payload[a]")
    second = start_driver(cache, "b,a", "--sleep", "1")
    wait_for(count_file, "checksum[b]")
    time.sleep(0.5)  # B waits on the lock of payload[a]
    assert first.poll() is None and second.poll() is None
    first.send_signal(signal.SIGKILL)
    first.wait()
    out, _ = second.communicate(timeout=120)
    assert statuses(out) == {"payload[b]": "ran", "checksum[b]": "ran", "payload[a]": "ran", "checksum[a]": "ran"}
    assert count_file.read_text().split().count("payload[a]") == 2  # A's half was not taken for a result
    done, _ = drive(cache, "a,b")
    assert set(done.values()) == {"cached"}
    assert {check.status for check in verify_cache(cache)} == {"whole"} and entries_and_temps(cache)[1] == []
