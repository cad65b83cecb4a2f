"""One cache entry: a node's output folder, computed once under its key's lock into a temporary folder and
renamed into `<cache>/<stage>/<key>/` with manifest.json (key, inputs, config, seconds, versions, metrics, the
warnings it logged, and the size and SHA-256 of every file it holds: stages/engine/cache_files.py) and metrics.json only
when complete; a folder without manifest.json is never trusted, nor one whose files are missing or of another size
than its manifest records (checked on every cache hit; the contents by `run.action=verify`, docs/cache.md). A node
whose stage found nothing to compute (stages/contract/errors.py EmptyInput) is an entry too: no files but its manifest,
which says why (EMPTY), and an empty metrics.json.
"""
from __future__ import annotations

import fcntl
import importlib.util
import json
import logging
import os
import platform
import shutil
import socket
import time
import traceback
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterator

from stages.contract.errors import EmptyInput, StageError
from stages.engine.cache_files import describe_files, size_problem
from stages.engine.context import Context
from stages.engine.worker_lanes import ElasticContext

log = logging.getLogger("stages.engine.scheduler")

MANIFEST = "manifest.json"
METRICS = "metrics.json"
EMPTY = "empty"  # the manifest's reason why its node had nothing to compute (stages/contract/errors.py EmptyInput)
MANIFEST_PART = "manifest.json.part"  # a manifest being replaced (stages/engine/cache_verify.py records older entries')
FILES = "files"  # the manifest's record of the entry's files (stages/engine/cache_files.py); absent in older entries
UNRECORDED = frozenset({MANIFEST, MANIFEST_PART})  # the files of an entry its record leaves out


@dataclass
class Outcome:
    """What happened to one node in a run (or, for plan, what would happen).

    status: cached | ran | empty (nothing to compute: its stage found its input slot empty, an outcome kept in the
    cache like a result, or a node it needs is empty) | failed | blocked (an upstream node failed) | would-run |
    bad-input (plan: a raw input is missing or broken). error: why it failed or was blocked, or why it is empty.
    warnings: the WARNING log lines of the stage's run (kept in its manifest,
    so a cached node shows them again). left_out: {group: why} of the optional inputs it ran without.
    distrusted: why the node's cache entry was not trusted (a file missing or of another size than its manifest
    says), so that it is computed again; "" when there was none or it was whole.
    """

    stage: str
    item: str
    key: str
    status: str
    seconds: float = 0.0
    started: float = 0.0  # when it began computing (time.time()); 0 when it did not run here
    error: str = ""
    path: str = ""
    traceback: str = ""
    warnings: list[str] = field(default_factory=list)
    left_out: dict[str, str] = field(default_factory=dict)
    distrusted: str = ""

    @property
    def label(self) -> str:
        return f"{self.stage}[{self.item}]"


def key_busy(cache_dir: Path, stage: str, key: str) -> bool:
    """True while another process holds the key's lock, i.e. is computing that node now."""
    lock_path = cache_dir / stage / f"{key}.lock"
    if not lock_path.is_file():
        return False
    with open(lock_path, "a") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        fcntl.flock(handle, fcntl.LOCK_UN)
    return False


@contextmanager
def key_lock(cache_dir: Path, stage: str, key: str, wait: bool = True) -> Iterator[bool]:
    """An exclusive lock on one cache key, shared by every process using the cache folder. Yields whether it is
    held: always with `wait`, else only when no other process held it."""
    lock_path = cache_dir / stage / f"{key}.lock"
    lock_path.parent.mkdir(parents=True, exist_ok=True)
    with open(lock_path, "a") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
            held = True
        except BlockingIOError:
            held = False
        try:
            yield held
        finally:
            if held:
                fcntl.flock(handle, fcntl.LOCK_UN)


def read_manifest(folder: Path) -> dict:
    """The manifest.json of a cache entry (its key, inputs, config, seconds, versions, metrics, warnings)."""
    return json.loads((Path(folder) / MANIFEST).read_text())


def entry_problem(folder: Path) -> str | None:
    """The cheap check of a cache hit: what is wrong with the entry `folder` (its manifest.json does not parse, or
    a file it records is missing or of another size), or None (also when it has no manifest: no entry). An entry
    written before manifests recorded files passes (docs/cache.md: `run.action=verify` records them)."""
    if not (Path(folder) / MANIFEST).is_file():
        return None
    try:
        problem = size_problem(Path(folder), read_manifest(folder).get(FILES, {}))
    except (OSError, ValueError, AttributeError, TypeError, KeyError) as error:
        problem = f"its {MANIFEST} cannot be read ({type(error).__name__}: {error})"
    return f"cache entry {folder}: {problem}" if problem else None


def is_whole(folder: Path) -> bool:
    """Whether `folder` is a cache entry to trust: it has a manifest.json and passes entry_problem."""
    return (Path(folder) / MANIFEST).is_file() and entry_problem(folder) is None


def remove_entry(folder: Path) -> None:
    """Delete a cache entry's folder, its manifest first: a removal cut short leaves no entry to trust."""
    (Path(folder) / MANIFEST).unlink(missing_ok=True)
    shutil.rmtree(folder)


def cached_outcome(stage: str, item: str, key: str, folder: Path, left_out: dict[str, str]) -> Outcome:
    """The outcome of a node whose cache entry `folder` is whole: cached, or empty when its stage found nothing to
    compute (the manifest keeps why), with the warnings its run logged."""
    manifest = read_manifest(folder)
    empty = manifest.get(EMPTY, "")
    return Outcome(stage, item, key, "empty" if empty else "cached", path=str(folder), error=empty,
                  warnings=manifest.get("warnings", []), left_out=left_out)


def unreached_entries(cache_dir: Path, keep: set[tuple[str, str]]) -> list[Path]:
    """Cache entries (and stale temp folders) under `cache_dir` whose (stage, key) is not in `keep`."""
    found = []
    for stage_dir in sorted(p for p in Path(cache_dir).glob("*") if p.is_dir()):
        for entry in sorted(stage_dir.iterdir()):
            name = entry.name
            if name.endswith(".lock"):
                continue
            key = name.split(".tmp-")[0].lstrip(".") if ".tmp-" in name else name
            if ".tmp-" in name or (stage_dir.name, key) not in keep:
                found.append(entry)
    return found


def input_path(folder: Path, input_name: str) -> Path | None:
    """What input `input_name` of the node whose cache entry is `folder` was: the upstream entry (or the path
    inside it) whose key its manifest records, in `<cache>/<stage>/<key>/` (keys are unique across stages).
    None when `folder` is not a cache entry, had no such input, the input was a raw file (the manifest keeps
    only its content hash), or the upstream entry is gone. `a>b` names input b of the entry that was input a
    (a joined dataset's references into its shards' inputs, stages/lib/composition/shards.py)."""
    first, _, rest = input_name.partition(">")
    if not (Path(folder) / MANIFEST).is_file():
        return None
    key, _, subpath = str(read_manifest(folder).get("inputs", {}).get(first, "")).partition("/")
    found = sorted(Path(folder).resolve().parent.parent.glob(f"*/{key}")) if key else []
    if not found:
        return None
    if rest:
        return input_path(found[0], rest)
    return found[0] / subpath if subpath else found[0]


class _WarningCollector(logging.Handler):
    """Collects the messages of WARNING and worse log records."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


@contextmanager
def collected_warnings() -> Iterator[list[str]]:
    """The warnings logged (by any logger of this process) while the block runs."""
    collector = _WarningCollector()
    root = logging.getLogger()
    root.addHandler(collector)
    try:
        yield collector.messages
    finally:
        root.removeHandler(collector)


def _versions() -> dict[str, str]:
    versions = {"python": platform.python_version()}
    for name in ("numpy", "torch", "torchvision", "open3d", "pycolmap"):
        module = importlib.util.find_spec(name)
        if module is not None:
            try:
                from importlib.metadata import version
                versions[name] = version(name)
            except Exception:  # noqa: BLE001 - a version string is informative only
                pass
    return versions


def of_this_machine(temp_name: str) -> bool:
    """True for a temp folder `.<key>.tmp-<host>-<pid>` of this machine. A process writes its temp folder only while
    it holds the key's lock, so to whoever holds that lock now such a folder is left over (its run was killed, and
    the kill released the lock, even before the process was reaped). Another machine's is left alone: locks may
    hold per machine (`run.action=gc` lists every temp folder)."""
    host, _, pid = temp_name.partition(".tmp-")[2].rpartition("-")
    return host == socket.gethostname() and pid.isdigit()


@dataclass(frozen=True)
class Job:
    """One node to compute, as the scheduler hands it to compute_node in this process or a pool worker (pickled).

    stage: the engine's Stage (stages/engine/graph.py: name, run, version, config, elastic_threads).
    key: the node's cache key. code_hash: its stage's, computed once by the scheduler (a spawned worker's hash cache
    starts empty). params: its settings (plain JSON values); settings: the same, typed and checked at start
    (`Node.settings`). inputs: {name: path} of what it reads; input_keys:
    {name: upstream key (and path inside) or content hash}, for its manifest. left_out: {group: why} of the
    optional inputs it runs without. device: "cpu" or "cuda". threads: torch's thread count in a pool worker (0:
    left alone, in-process); cores: the machine's, which elastic stages share.
    """

    stage: Any
    item: str
    params: dict[str, Any]
    key: str
    code_hash: str
    inputs: dict[str, str]
    input_keys: dict[str, str]
    left_out: dict[str, str]
    seed: int
    cache_dir: str
    device: str
    threads: int
    cores: int
    settings: Any = None


def compute_node(job: Job) -> Outcome:
    """Compute one node (in this process or a pool worker): lock, temp folder, run, atomic rename."""
    stage = job.stage
    cache_dir = Path(job.cache_dir)
    key, item, left_out = job.key, job.item, job.left_out
    final = cache_dir / stage.name / key
    label = f"{stage.name}[{item}]"
    if job.threads:
        import torch

        torch.set_num_threads(job.threads)
    with key_lock(cache_dir, stage.name, key):
        problem = entry_problem(final)
        if (final / MANIFEST).is_file() and problem is None:  # another process computed it while we waited
            log.info("%s computed by another process (%s)", label, key)
            return cached_outcome(stage.name, item, key, final, left_out)
        distrusted = problem or ""
        if distrusted:
            log.warning("%s: %s; not trusted, computing it again", label, distrusted)
        for stale in final.parent.glob(f".{key}.tmp-*"):
            if of_this_machine(stale.name):
                shutil.rmtree(stale, ignore_errors=True)
        if final.exists():  # a folder without manifest, or with files other than it records, is never trusted
            remove_entry(final)
        tmp = final.parent / f".{key}.tmp-{socket.gethostname()}-{os.getpid()}"
        tmp.mkdir(parents=True)
        fields = dict(stage=stage.name, item=item, params=job.params,
                      inputs={k: Path(v) for k, v in job.inputs.items()}, out=tmp, seed=job.seed,
                      device=job.device, left_out=left_out, log=logging.getLogger(f"stages.{stage.name}"),
                      settings=job.settings)
        elastic = stage.elastic_threads and job.threads > 0  # in a pool worker (in-process: all cores)
        ctx = ElasticContext(**fields, cores=job.cores) if elastic else Context(**fields)
        started = time.time()
        log.info("%s running (%s)%s", label, key, f", without {', '.join(left_out)}" if left_out else "")
        empty = ""
        with collected_warnings() as warnings:
            try:
                metrics = stage.function()(ctx) or {}
            except EmptyInput as error:  # nothing to compute: an outcome, kept in the cache like a result
                metrics, empty = {}, str(error)
                shutil.rmtree(tmp)
                tmp.mkdir()
            except Exception as error:  # noqa: BLE001 - every failure becomes an outcome, never a cache entry
                shutil.rmtree(tmp, ignore_errors=True)
                message = str(error) if isinstance(error, StageError) else f"{type(error).__name__}: {error}"
                if not isinstance(error, StageError):
                    log.debug("%s", traceback.format_exc())
                return Outcome(stage.name, item, key, "failed", seconds=time.time() - started, started=started,
                              error=message, traceback=traceback.format_exc(), warnings=list(warnings),
                              left_out=left_out, distrusted=distrusted)
        seconds = time.time() - started
        try:
            _write_manifest(tmp, job, metrics, seconds, warnings, empty)
        except OSError as error:  # a full disk or a file-size limit: the temp folder is dropped, no entry made
            shutil.rmtree(tmp, ignore_errors=True)
            return Outcome(stage.name, item, key, "failed", seconds=seconds, started=started, warnings=warnings,
                          error=f"{label}: cannot write its cache entry in {final.parent} ({error}); is the disk "
                                "full?", left_out=left_out, distrusted=distrusted)
        try:
            os.rename(tmp, final)
        except OSError:  # another machine finished it meanwhile (a file system whose locks are per machine)
            shutil.rmtree(tmp, ignore_errors=True)
            if not (final / MANIFEST).is_file():
                raise
            log.info("%s computed by another process meanwhile (%s)", label, key)
            return cached_outcome(stage.name, item, key, final, left_out)
    log.info("%s %s in %.1f s", label, f"empty ({empty})" if empty else "done", seconds)
    return Outcome(stage.name, item, key, "empty" if empty else "ran", seconds=seconds, started=started,
                  path=str(final), error=empty, warnings=warnings, left_out=left_out, distrusted=distrusted)


def _write_manifest(tmp: Path, job: Job, metrics: dict, seconds: float, warnings: list[str], empty: str = "") -> None:
    """Write metrics.json, then manifest.json with the size and SHA-256 of every file of the entry in `tmp`
    (metrics.json among them) and, for a node with nothing to compute, why (EMPTY). OSError when a write fails (a
    full disk)."""
    stage = job.stage
    (tmp / METRICS).write_text(json.dumps(metrics, indent=2, default=float))
    manifest = {
        "key": job.key, "stage": stage.name, "item": job.item, "version": stage.version,
        "code_hash": job.code_hash, "params": job.params, "inputs": job.input_keys,
        "left_out": job.left_out, "seed": job.seed, "seconds": seconds, "device": job.device,
        "finished": datetime.now(timezone.utc).isoformat(), "versions": _versions(), "metrics": metrics,
        "warnings": warnings, FILES: describe_files(tmp, UNRECORDED), **({EMPTY: empty} if empty else {}),
    }
    (tmp / MANIFEST).write_text(json.dumps(manifest, indent=2, default=float))
