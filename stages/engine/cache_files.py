"""The files of a cache entry and their checks: each file's size and SHA-256, recorded in the entry's manifest.json
when the entry is written (stages/engine/cache_entry.py), its sizes compared on every cache hit (`size_problem`: a stat
per file) and its contents by `run.action=verify` (`content_problems`: every byte read; stages/engine/cache_verify.py).

A record is {relative path (POSIX): {"size": bytes, "sha256": hex}} over the regular files under the entry's
folder, sub-folders included, minus the files the caller leaves out (the manifest, which holds the record).
"""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

CHUNK = 1 << 20  # bytes read at a time while hashing


def file_sha256(path: Path) -> str:
    """The SHA-256 (hex) of a file's bytes, read CHUNK bytes at a time."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while chunk := handle.read(CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


def entry_files(folder: Path, leave_out: frozenset[str]) -> list[str]:
    """Relative POSIX paths of the files under `folder` (sorted), minus those named in `leave_out` (top level)."""
    found = []
    for root, _, names in os.walk(folder):
        relative = Path(root).relative_to(folder)
        found += [(relative / name).as_posix() for name in names]
    return sorted(name for name in found if name not in leave_out)


def describe_files(folder: Path, leave_out: frozenset[str]) -> dict[str, dict]:
    """{relative path: {"size", "sha256"}} of the files under `folder` minus `leave_out`."""
    folder = Path(folder)
    return {name: {"size": (folder / name).stat().st_size, "sha256": file_sha256(folder / name)}
            for name in entry_files(folder, leave_out)}


def _size_mismatch(folder: Path, name: str, expected: int) -> str | None:
    """What is wrong with the size of one recorded file, or None."""
    try:
        size = (Path(folder) / name).stat().st_size
    except OSError:
        return f"file {name} is missing"
    if size != expected:
        return f"file {name} is {size} bytes, its manifest says {expected}"
    return None


def size_problem(folder: Path, files: dict[str, dict]) -> str | None:
    """The first recorded file (`files`, describe_files' record) that is missing or of another size, or None."""
    for name, recorded in files.items():
        problem = _size_mismatch(folder, name, recorded["size"])
        if problem:
            return problem
    return None


def content_problems(folder: Path, files: dict[str, dict], leave_out: frozenset[str]) -> list[str]:
    """Every disagreement between the files under `folder` and their record: a file missing, of another size,
    of other contents (SHA-256), or not in the record at all (a file added to the entry)."""
    problems = []
    for name, recorded in files.items():
        problem = _size_mismatch(folder, name, recorded["size"])
        if problem is None and file_sha256(Path(folder) / name) != recorded["sha256"]:
            problem = f"file {name} has other contents than when it was written (SHA-256 differs)"
        if problem:
            problems.append(problem)
    problems += [f"file {name} is not in its manifest (added after the entry was written)"
                 for name in entry_files(folder, leave_out) if name not in files]
    return problems
