"""One cache entry: a node's output folder, computed once under its key's lock into a temporary folder and
renamed into `<cache>/<stage>/<key>/` with manifest.json (key, inputs, config, seconds, versions, metrics, the
warnings it logged) and metrics.json only when complete; a folder without manifest.json is never trusted.
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
from typing import Iterator

from stages.context import Context
from stages.errors import StageError
from stages.worker_lanes import ElasticContext

log = logging.getLogger("stages.engine")

MANIFEST = "manifest.json"
METRICS = "metrics.json"


@dataclass
class Record:
    """What happened to one node in a run (or, for plan, what would happen).

    status: cached | ran | failed | blocked (an upstream node failed) | would-run | bad-input (plan: a raw
    input is missing or broken). warnings: the WARNING log lines of the stage's run (kept in its manifest,
    so a cached node shows them again). left_out: {group: why} of the optional inputs it ran without.
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
def key_lock(cache_dir: Path, stage: str, key: str) -> Iterator[None]:
    """An exclusive lock on one cache key, shared by every process using the cache folder."""
    lock_path = cache_dir / stage / f"{key}.lock"
    lock_path.parent.mkdir(parents=True, exist_ok=True)
    with open(lock_path, "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def read_manifest(folder: Path) -> dict:
    """The manifest.json of a cache entry (its key, inputs, config, seconds, versions, metrics, warnings)."""
    return json.loads((Path(folder) / MANIFEST).read_text())


def manifest_warnings(folder: Path) -> list[str]:
    """The warnings a cached node's run logged, from its manifest.json."""
    return read_manifest(folder).get("warnings", [])


def input_path(folder: Path, input_name: str) -> Path | None:
    """What input `input_name` of the node whose cache entry is `folder` was: the upstream entry (or the path
    inside it) whose key its manifest records, in `<cache>/<stage>/<key>/` (keys are unique across stages).
    None when `folder` is not a cache entry, had no such input, the input was a raw file (the manifest keeps
    only its content hash), or the upstream entry is gone. `a>b` names input b of the entry that was input a
    (a joined dataset's references into its shards' inputs, stages/composition/shards.py)."""
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


def left_by_a_dead_process(temp_name: str) -> bool:
    """True for a temp folder `.<key>.tmp-<host>-<pid>` of this machine whose process is gone (a killed run);
    another machine's is left alone (`run.action=gc` lists every temp folder)."""
    host, _, pid = temp_name.partition(".tmp-")[2].rpartition("-")
    if host != socket.gethostname() or not pid.isdigit():
        return False
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        return False
    return False


def compute_node(job: dict) -> Record:
    """Compute one node (in this process or a pool worker): lock, temp folder, run, atomic rename."""
    stage = job["stage"]  # the engine's Stage: name, run, version
    cache_dir = Path(job["cache_dir"])
    key, item, left_out = job["key"], job["item"], job["left_out"]
    final = cache_dir / stage.name / key
    label = f"{stage.name}[{item}]"
    if job["threads"]:
        import torch

        torch.set_num_threads(job["threads"])
    with key_lock(cache_dir, stage.name, key):
        if (final / MANIFEST).is_file():  # another process computed it while we waited
            log.info("%s computed by another process (%s)", label, key)
            return Record(stage.name, item, key, "cached", path=str(final), warnings=manifest_warnings(final),
                          left_out=left_out)
        for stale in final.parent.glob(f".{key}.tmp-*"):
            if left_by_a_dead_process(stale.name):
                shutil.rmtree(stale, ignore_errors=True)
        if final.exists():  # a folder without manifest is never trusted
            shutil.rmtree(final)
        tmp = final.parent / f".{key}.tmp-{socket.gethostname()}-{os.getpid()}"
        tmp.mkdir(parents=True)
        fields = dict(stage=stage.name, item=item, params=job["params"],
                      inputs={k: Path(v) for k, v in job["inputs"].items()}, out=tmp, seed=job["seed"],
                      device=job["device"], left_out=left_out, log=logging.getLogger(f"stages.{stage.name}"))
        elastic = stage.elastic_threads and job["threads"] > 0  # in a pool worker (in-process: all cores)
        ctx = ElasticContext(**fields, cores=job["cores"]) if elastic else Context(**fields)
        started = time.time()
        log.info("%s running (%s)%s", label, key, f", without {', '.join(left_out)}" if left_out else "")
        with collected_warnings() as warnings:
            try:
                metrics = stage.function()(ctx) or {}
            except Exception as error:  # noqa: BLE001 - every failure becomes a record, never a cache entry
                shutil.rmtree(tmp, ignore_errors=True)
                message = str(error) if isinstance(error, StageError) else f"{type(error).__name__}: {error}"
                if not isinstance(error, StageError):
                    log.debug("%s", traceback.format_exc())
                return Record(stage.name, item, key, "failed", seconds=time.time() - started, started=started,
                              error=message, traceback=traceback.format_exc(), warnings=list(warnings),
                              left_out=left_out)
        seconds = time.time() - started
        (tmp / METRICS).write_text(json.dumps(metrics, indent=2, default=float))
        manifest = {
            "key": key, "stage": stage.name, "item": item, "version": stage.version,
            "code_hash": job["code_hash"], "params": job["params"], "inputs": job["input_keys"],
            "left_out": left_out, "seed": job["seed"], "seconds": seconds, "device": job["device"],
            "finished": datetime.now(timezone.utc).isoformat(), "versions": _versions(), "metrics": metrics,
            "warnings": warnings,
        }
        (tmp / MANIFEST).write_text(json.dumps(manifest, indent=2, default=float))
        try:
            os.rename(tmp, final)
        except OSError:  # another machine finished it meanwhile (a file system whose locks are per machine)
            shutil.rmtree(tmp, ignore_errors=True)
            if not (final / MANIFEST).is_file():
                raise
            log.info("%s computed by another process meanwhile (%s)", label, key)
            return Record(stage.name, item, key, "cached", path=str(final), warnings=manifest_warnings(final),
                          left_out=left_out)
    log.info("%s done in %.1f s", label, seconds)
    return Record(stage.name, item, key, "ran", seconds=seconds, started=started, path=str(final), warnings=warnings,
                  left_out=left_out)
