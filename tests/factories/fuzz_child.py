"""Fuzzing one file reader in a child process: `fuzz_reader` (the test's side) starts
`python -m tests.factories.fuzz_child READER FOLDER EXAMPLES SEED`, which runs the reader's named cases and then
EXAMPLES cases drawn by Hypothesis (seeded), each on a fresh copy of the reader's seed folder, and writes what
each ended in to FOLDER/results.json.

The child runs without the capabilities that let root read any file (so that "unreadable" is), under an
address-space limit (RLIMIT_AS) of ADDRESS_SPACE bytes; torch alone maps 3.3 GB, so the torch-file reader's
limit is ADDRESS_SPACE above what the child maps once torch is loaded. Before each case it names the case in
FOLDER/current.json, so that a crash (pycolmap, OpenCV and FFmpeg are C++ and C) or a hang names the case that
caused it; each case's peak resident memory is read from /proc (VmHWM, reset before the case).
"""
from __future__ import annotations

import ctypes
import json
import os
import resource
import shutil
import subprocess
import sys
import time
import traceback
from pathlib import Path

from tests.factories.fuzz_inputs import Case, field_cases, generic_cases, mutations

ROOT = Path(__file__).resolve().parents[2]  # the repository (not tests.factories.configs: it loads Hydra)
ADDRESS_SPACE = 2 << 30  # bytes
CAP_DAC = (1 << 1) | (1 << 2)  # CAP_DAC_OVERRIDE, CAP_DAC_READ_SEARCH


def drop_file_capabilities() -> None:
    """Drop the capabilities that let root bypass file permissions (no-op for other users)."""
    libc = ctypes.CDLL(None, use_errno=True)
    header = (ctypes.c_uint32 * 2)(0x20080522, 0)  # _LINUX_CAPABILITY_VERSION_3, this process
    data = (ctypes.c_uint32 * 6)()  # two {effective, permitted, inheritable}
    if libc.capget(header, data) == 0:
        data[0] &= ~CAP_DAC
        data[1] &= ~CAP_DAC
        libc.capset(header, data)


def _status_kb(key: str) -> int:
    """A value of /proc/self/status in kB (VmHWM: the peak resident memory, VmSize: the address space)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    return 0


def _reset_peak() -> None:
    """Reset VmHWM to the current resident memory (Linux: clear_refs 5)."""
    Path("/proc/self/clear_refs").write_text("5")


def _prepare(case: Case, seed_dir: Path, work: Path) -> Path:
    """A fresh copy of the seed folder at `work` with the case applied."""
    shutil.rmtree(work, ignore_errors=True)
    shutil.copytree(seed_dir, work)
    target = work / case.file
    if case.special == "missing":
        target.unlink()
    elif case.special == "folder":
        shutil.rmtree(target) if target.is_dir() else target.unlink()
        target.mkdir()
    else:
        target.write_bytes(case.content)
        if case.special == "unreadable":
            target.chmod(0)
    return work


def run_case(reader, case: Case, seed_dir: Path, folder: Path) -> dict:
    """Run the reader on one case: {"name", "file", "outcome": "clean" | "named" | "other", "message" (a clean
    case's: the warnings it logged), "seconds", "peak_mb"}; "other" is any exception but the project's StageError
    (a bug)."""
    from stages.contract.errors import StageError
    from stages.engine.cache_entry import collected_warnings

    work = _prepare(case, seed_dir, folder / "case")
    (folder / "current.json").write_text(json.dumps({"name": case.name, "file": case.file}))
    (folder / "current.bin").write_bytes(case.content)
    _reset_peak()
    started = time.perf_counter()
    with collected_warnings() as warnings:  # a reader that skips a bad file says so in a warning
        try:
            reader.read(work / reader.target)
            outcome, message = "clean", "; ".join(warnings).replace(str(work), "")
        except StageError as error:
            outcome, message = "named", str(error).replace(str(work), "")
        except Exception as error:  # noqa: BLE001 - what the test counts: any exception but StageError is a failure
            outcome, message = "other", f"{type(error).__name__}: {error}\n{traceback.format_exc()}"
    record = {"name": case.name, "file": case.file, "outcome": outcome, "message": message[:2000],
              "seconds": time.perf_counter() - started, "peak_mb": _status_kb("VmHWM") / 1024}
    target = work / case.file
    if target.exists() and not target.is_dir():
        target.chmod(0o644)
    return record


def main(reader_name: str, folder: Path, examples: int, seed: int) -> None:
    """The child: seed folder, named cases, Hypothesis cases; results.json."""
    from hypothesis import HealthCheck, Phase, given, settings
    from hypothesis import seed as hypothesis_seed

    from tests.factories.fuzz_readers import READERS

    drop_file_capabilities()
    reader = READERS[reader_name]
    seed_dir = folder / "seed"
    seed_dir.mkdir(parents=True, exist_ok=True)
    reader.seed(seed_dir)
    reader.read(seed_dir / reader.target)  # the seed reads cleanly (and the reader's libraries are loaded)
    files = {p.relative_to(seed_dir).as_posix(): p.read_bytes() for p in sorted(seed_dir.rglob("*")) if p.is_file()}
    limit = ADDRESS_SPACE + (_status_kb("VmSize") * 1024 if reader.torch else 0)
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    named = reader.named(files) + [case for file, data in files.items() for case in generic_cases(file, data)]
    named += [case for file, data in files.items() for case in field_cases(file, data, reader.fields.get(file, {}))]
    results = {"reader": reader_name, "address_space_limit": limit, "named": [], "drawn": [], "failure": None}
    for case in named:
        results["named"].append(run_case(reader, case, seed_dir, folder))

    @settings(max_examples=examples, database=None, deadline=None, derandomize=False, print_blob=False,
              phases=[Phase.generate, Phase.shrink], suppress_health_check=list(HealthCheck))
    @hypothesis_seed(seed)
    @given(mutations(files, reader.fields))
    def drawn(case: Case) -> None:
        record = run_case(reader, case, seed_dir, folder)
        results["drawn"].append({key: record[key] for key in ("name", "outcome", "seconds", "peak_mb")})
        assert record["outcome"] != "other", f"{case.name}: {record['message']}"

    try:
        drawn()
    except AssertionError as error:
        results["failure"] = str(error)[:4000]
    (folder / "results.json").write_text(json.dumps(results, indent=1))


def fuzz_reader(reader: str, folder: Path, examples: int, seed: int = 0, timeout: float = 120.0) -> dict:
    """Run the child for `reader` in `folder`; its results, or an AssertionError naming the case that crashed the
    child (a signal) or ran past `timeout` seconds."""
    folder.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    command = [sys.executable, "-m", "tests.factories.fuzz_child", reader, str(folder), str(examples), str(seed)]
    with open(folder / "child.log", "w") as log:
        try:
            done = subprocess.run(command, env=env, stdout=log, stderr=subprocess.STDOUT, timeout=timeout, cwd=ROOT)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"fuzz {reader}: ran past {timeout} s in case {_current(folder)}") from None
    if done.returncode != 0 or not (folder / "results.json").is_file():
        tail = (folder / "child.log").read_text()[-3000:]
        raise AssertionError(f"fuzz {reader}: the child ended with {done.returncode} in case {_current(folder)} "
                             f"(its input: {folder / 'current.bin'}):\n{tail}")
    return json.loads((folder / "results.json").read_text())


def _current(folder: Path) -> str:
    """The case the child was in (current.json)."""
    path = folder / "current.json"
    return path.read_text() if path.is_file() else "(before the first case)"


if __name__ == "__main__":
    main(sys.argv[1], Path(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]))
