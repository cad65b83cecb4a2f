"""`python dag.py run.action=verify`: every entry of a cache folder read back and compared with its manifest.

An entry is bad when its manifest is missing (a folder never completed) or does not parse, or a file it records
is missing, of another size or of other contents (SHA-256), or it holds a file its manifest does not record; a
temporary folder left by a killed run of this machine is bad too. `apply` removes the bad ones (their nodes are
computed again by the next run). An entry written before manifests recorded their files has its files' sizes and
hashes recorded now, once: from then on a cache hit checks its sizes and verify its contents (docs/cache.md).
An entry whose key another process holds (computing it) is left alone.
"""
from __future__ import annotations

import json
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

from stages.engine.cache_entry import (FILES, MANIFEST, MANIFEST_PART, UNRECORDED, key_lock, of_this_machine,
                                       read_manifest, remove_entry)
from stages.engine.cache_files import content_problems, describe_files


@dataclass
class EntryCheck:
    """The verdict on one folder of the cache.

    status: "whole" | "bad" | "recorded" (written before manifests recorded files: recorded now) | "busy"
    (another process holds its key, or a temporary folder of a live process). bytes: the bytes read.
    """

    path: Path
    status: str
    problems: list[str] = field(default_factory=list)
    bytes: int = 0
    removed: bool = False


def record_files(folder: Path, manifest: dict) -> None:
    """Add the record of the files of `folder` to its manifest, replacing manifest.json atomically."""
    manifest[FILES] = describe_files(folder, UNRECORDED)
    part = Path(folder) / MANIFEST_PART
    part.write_text(json.dumps(manifest, indent=2, default=float))
    os.replace(part, Path(folder) / MANIFEST)


def check_entry(folder: Path) -> EntryCheck:
    """The check of one entry `folder` (`<cache>/<stage>/<key>`), under its key's lock held by the caller."""
    if not (folder / MANIFEST).is_file():
        return EntryCheck(folder, "bad", [f"no {MANIFEST}: it was never completed"])
    try:
        manifest = read_manifest(folder)
        files = manifest.get(FILES)
        if files is None:
            record_files(folder, manifest)
            return EntryCheck(folder, "recorded", bytes=sum(f["size"] for f in manifest[FILES].values()))
        problems = content_problems(folder, files, UNRECORDED)
        return EntryCheck(folder, "bad" if problems else "whole", problems, sum(f["size"] for f in files.values()))
    except (OSError, ValueError, AttributeError, TypeError, KeyError) as error:
        return EntryCheck(folder, "bad", [f"its {MANIFEST} cannot be read ({type(error).__name__}: {error})"])


def verify_folder(cache_dir: Path, folder: Path, apply: bool) -> EntryCheck:
    """The check of one folder of `<cache>/<stage>/`, an entry or a temporary folder, under its key's lock (left
    alone when another process holds it); with `apply`, a bad one removed. A temporary folder of this machine is
    bad once its key's lock is free (its run was killed: stages/engine/cache_entry.py of_this_machine)."""
    temporary = ".tmp-" in folder.name
    key = folder.name.partition(".tmp-")[0].lstrip(".") if temporary else folder.name
    with key_lock(cache_dir, folder.parent.name, key, wait=False) as held:
        if not held:
            return EntryCheck(folder, "busy", ["another process is computing it"])
        if temporary and not of_this_machine(folder.name):
            return EntryCheck(folder, "busy", ["the temporary folder of another machine"])
        check = EntryCheck(folder, "bad", ["a temporary folder left by a killed run"]) if temporary else check_entry(folder)
        if apply and check.status == "bad":
            shutil.rmtree(folder) if temporary else remove_entry(folder)
            check.removed = True
    return check


def verify_cache(cache_dir: Path, apply: bool = False) -> list[EntryCheck]:
    """The check of every folder of every stage in `cache_dir` (stage and key order)."""
    cache_dir = Path(cache_dir)
    stage_dirs = sorted(p for p in cache_dir.iterdir() if p.is_dir()) if cache_dir.is_dir() else []
    return [verify_folder(cache_dir, folder, apply) for stage_dir in stage_dirs
            for folder in sorted(p for p in stage_dir.iterdir() if p.is_dir())]


def verify_report(checks: list[EntryCheck], seconds: float, apply: bool) -> str:
    """What verify prints: a line per bad or busy folder with its problems, then the counts, bytes read and time."""
    lines = [f"{'removed' if c.removed else c.status} {c.path}: {'; '.join(c.problems)}" for c in checks
             if c.status in ("bad", "busy")]
    counts = {status: sum(c.status == status for c in checks) for status in ("whole", "bad", "recorded", "busy")}
    read = sum(c.bytes for c in checks)
    lines.append(f"{len(checks)} cache folders checked ({read / 1e6:.1f} MB read in {seconds:.1f} s): "
                 f"{counts['whole']} whole, {counts['bad']} bad"
                 + (" (removed)" if apply and counts["bad"] else " (run.verify_apply=true removes them)" if counts["bad"]
                    else "")
                 + f", {counts['recorded']} written before manifests recorded files (recorded now), "
                   f"{counts['busy']} busy (left alone)")
    return "\n".join(lines)


def timed_verify(cache_dir: Path, apply: bool) -> tuple[list[EntryCheck], float]:
    """verify_cache and the seconds it took."""
    started = time.perf_counter()
    checks = verify_cache(cache_dir, apply)
    return checks, time.perf_counter() - started
