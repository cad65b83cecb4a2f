"""The DAG engine: stage nodes, content-hashed cache keys, atomic outputs, file locks, a scheduler.

A node is one stage applied to one item (an object, a background photo, a variant). Its cache key is
the sha256 of: the stage name and version, the hash of the stage's source code (its module and every
`stages.*` module it imports, recursively), the canonical JSON of its config slice, its seed, the keys
of its upstream nodes and the content hashes of its raw input files. Outputs are written into a
temporary folder and renamed into `<cache>/<stage>/<key>/` with `manifest.json` only when complete; a
per-key file lock makes concurrent processes compute a key once.
"""
from __future__ import annotations

import ast
import fcntl
import hashlib
import importlib.util
import json
import logging
import os
import platform
import shutil
import time
import traceback
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from multiprocessing import get_context
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import datetime, timezone
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable, Iterator

from stages.context import Context, StageError

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"
METRICS = "metrics.json"


@dataclass(frozen=True)
class Stage:
    """A stage declaration: its name, the function that runs it, and a version to bump by hand."""

    name: str
    run: Callable[[Context], dict | None]
    version: str = "1"

    @property
    def code_hash(self) -> str:
        """Hash of the source of the stage's module and every `stages.*` module it imports."""
        return _module_closure_hash(self.run.__module__)


@dataclass(frozen=True)
class Ref:
    """An input that is a path inside an upstream node's output folder ('' = the folder itself)."""

    node: "Node"
    subpath: str = ""


@dataclass(eq=False)
class Node:
    """One stage applied to one item, with its config slice and named inputs.

    inputs map a name to an upstream Node (its output folder), a Ref (a path inside it) or a Path
    (a raw file or folder, hashed by content).
    """

    stage: Stage
    item: str
    params: dict[str, Any] = field(default_factory=dict)
    inputs: dict[str, "Node | Ref | Path"] = field(default_factory=dict)

    @property
    def label(self) -> str:
        return f"{self.stage.name}[{self.item}]"

    def upstream(self) -> list["Node"]:
        """The nodes this node reads from, in input order."""
        deps = []
        for value in self.inputs.values():
            if isinstance(value, Node):
                deps.append(value)
            elif isinstance(value, Ref):
                deps.append(value.node)
        return deps


# ----------------------------------------------------------------------------------------- hashing

def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def canonical_json(value: Any) -> str:
    """JSON with sorted keys and no whitespace: equal configs give equal strings."""
    return json.dumps(value, sort_keys=True, separators=(",", ":"), default=str)


def _module_file(name: str) -> Path | None:
    """The source file of a module, or None for names that are not modules (e.g. `pkg.mod.Class`)."""
    try:
        spec = importlib.util.find_spec(name)
    except (ImportError, ValueError):
        return None
    if spec is None or spec.origin is None or not spec.origin.endswith(".py"):
        return None
    return Path(spec.origin)


def stages_imports(name: str, source: str) -> set[str]:
    """Names of `stages.*` modules imported by a module's source (absolute and relative imports)."""
    package = name if name.endswith("__init__") else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                parts = parts[: len(parts) - node.level + 1]
                base = ".".join(parts + ([base] if base else []))
            found.add(base)
            found.update(f"{base}.{alias.name}" for alias in node.names)
    return {n for n in found if n == "stages" or n.startswith("stages.")}


@lru_cache(maxsize=None)
def _module_closure_hash(name: str) -> str:
    """Hash of a module's source plus its `stages.*` imports, and native sources beside them."""
    seen: dict[str, Path] = {}
    todo = [name]
    while todo:
        current = todo.pop()
        if current in seen:
            continue
        path = _module_file(current)
        if path is None:
            continue
        seen[current] = path
        todo.extend(stages_imports(current, path.read_text()))
    digest = hashlib.sha256()
    for mod in sorted(seen):
        digest.update(mod.encode() + b"\0" + seen[mod].read_bytes())
        native = seen[mod].parent / "csrc"
        for src in sorted(native.rglob("*")) if native.is_dir() else []:
            if src.is_file():
                digest.update(str(src.relative_to(native)).encode() + b"\0" + src.read_bytes())
    return digest.hexdigest()


@lru_cache(maxsize=4096)
def _file_hash(path: str, size: int, mtime_ns: int) -> str:
    """Content hash of one file (memoised on size and mtime within a process; never keyed on them)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for chunk in iter(lambda: handle.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def content_hash(path: Path) -> str:
    """Hash of a raw input's content: a file's bytes, or a folder's relative names and file bytes."""
    if not path.exists():
        raise StageError(f"input not found: {path}")
    if path.is_file():
        stat = path.stat()
        return _file_hash(str(path), stat.st_size, stat.st_mtime_ns)
    digest = hashlib.sha256()
    for child in sorted(p for p in path.rglob("*") if p.is_file()):
        stat = child.stat()
        digest.update(str(child.relative_to(path)).encode() + b"\0")
        digest.update(_file_hash(str(child), stat.st_size, stat.st_mtime_ns).encode())
    return digest.hexdigest()


def derive_seed(global_seed: int, stage: str, item: str) -> int:
    """A 31-bit seed from (global seed, stage, item): independent of worker count and order."""
    return int(_sha256(f"{global_seed}/{stage}/{item}".encode())[:8], 16) & 0x7FFFFFFF


# ------------------------------------------------------------------------------------------ engine

@dataclass
class Record:
    """What happened to one node in a run."""

    stage: str
    item: str
    key: str
    status: str  # cached | ran | failed | blocked | would-run
    seconds: float = 0.0
    error: str = ""
    path: str = ""
    traceback: str = ""


class Engine:
    """Runs a graph of nodes against a content-addressed cache folder."""

    def __init__(self, cache_dir: str | Path, *, global_seed: int = 0, workers: int = 1,
                 partial: bool = True, device: str = "cpu", reseed: tuple[str, ...] | None = None):
        """reseed: the stages whose seeds follow global_seed; the others keep the seeds of global seed 0
        (and so their cached outputs). None: every stage follows global_seed."""
        self.cache_dir = Path(cache_dir)
        self.global_seed = global_seed
        self.reseed = None if reseed is None else frozenset(reseed)
        self.workers = max(1, workers)
        self.partial = partial
        self.device = device
        self._keys: dict[int, str] = {}
        self._input_keys: dict[int, dict[str, str]] = {}  # per node: what each input contributed to its key

    # keys and paths -------------------------------------------------------------------------------
    def key(self, node: Node) -> str:
        """The node's cache key (memoised per engine)."""
        cached = self._keys.get(id(node))
        if cached is not None:
            return cached
        inputs = {}
        for name, value in sorted(node.inputs.items()):
            if isinstance(value, Node):
                inputs[name] = self.key(value)
            elif isinstance(value, Ref):
                inputs[name] = f"{self.key(value.node)}/{value.subpath}"
            else:
                inputs[name] = content_hash(Path(value))
        payload = {
            "stage": node.stage.name, "version": node.stage.version, "code": node.stage.code_hash,
            "params": node.params, "seed": self.seed(node), "inputs": inputs,
        }
        key = _sha256(canonical_json(payload).encode())[:20]
        self._keys[id(node)] = key
        self._input_keys[id(node)] = inputs
        return key

    def seed(self, node: Node) -> int:
        """The node's seed: from the global seed if its stage is reseeded, else from global seed 0."""
        follows = self.reseed is None or node.stage.name in self.reseed
        return derive_seed(self.global_seed if follows else 0, node.stage.name, node.item)

    def output_dir(self, node: Node) -> Path:
        return self.cache_dir / node.stage.name / self.key(node)

    def is_cached(self, node: Node) -> bool:
        return (self.output_dir(node) / MANIFEST).is_file()

    def input_paths(self, node: Node) -> dict[str, Path]:
        """Concrete paths of a node's inputs (upstream outputs must exist)."""
        paths = {}
        for name, value in node.inputs.items():
            if isinstance(value, Node):
                paths[name] = self.output_dir(value)
            elif isinstance(value, Ref):
                paths[name] = self.output_dir(value.node) / value.subpath
            else:
                paths[name] = Path(value)
        return paths

    # graph --------------------------------------------------------------------------------------
    @staticmethod
    def closure(targets: list[Node]) -> list[Node]:
        """All nodes the targets need, in a topological order (dependencies first)."""
        order: list[Node] = []
        state: dict[int, int] = {}

        def visit(node: Node, path: tuple[str, ...]) -> None:
            mark = state.get(id(node), 0)
            if mark == 2:
                return
            if mark == 1:
                raise ValueError(f"cycle in the stage graph: {' -> '.join(path + (node.label,))}")
            state[id(node)] = 1
            for dep in node.upstream():
                visit(dep, path + (node.label,))
            state[id(node)] = 2
            order.append(node)

        for target in targets:
            visit(target, ())
        return order

    def key_or_error(self, node: Node) -> tuple[str, str]:
        """(key, "") or ("?", why) when the key cannot be computed (e.g. a raw input is missing)."""
        try:
            return self.key(node), ""
        except StageError as error:
            return "?", str(error)

    def plan(self, targets: list[Node]) -> list[Record]:
        """What a run would do, without running anything."""
        records = []
        for node in self.closure(targets):
            key, error = self.key_or_error(node)
            if error:
                records.append(Record(node.stage.name, node.item, key, "missing-input", error=error))
                continue
            status = "cached" if self.is_cached(node) else "would-run"
            records.append(Record(node.stage.name, node.item, key, status, path=str(self.output_dir(node))))
        return records

    def reachable_keys(self, targets: list[Node]) -> set[tuple[str, str]]:
        return {(n.stage.name, self.key(n)) for n in self.closure(targets)}

    def garbage(self, keep: set[tuple[str, str]]) -> list[Path]:
        """Cache entries (and stale temp folders) whose (stage, key) is not in `keep`."""
        found = []
        for stage_dir in sorted(p for p in self.cache_dir.glob("*") if p.is_dir()):
            for entry in sorted(stage_dir.iterdir()):
                name = entry.name
                if name.endswith(".lock"):
                    continue
                key = name.split(".tmp-")[0].lstrip(".") if ".tmp-" in name else name
                if ".tmp-" in name or (stage_dir.name, key) not in keep:
                    found.append(entry)
        return found

    # running ------------------------------------------------------------------------------------
    def run(self, targets: list[Node]) -> list[Record]:
        """Run every node the targets need; returns one record per node (cached/ran/failed/blocked)."""
        order = self.closure(targets)
        records: dict[int, Record] = {}
        pending = list(order)
        running: dict[Future, Node] = {}
        stop = False
        # spawn, not fork: a forked child of a process that ran OpenMP (torch, the rasterizer) can hang
        pool = ProcessPoolExecutor(self.workers, mp_context=get_context("spawn")) if self.workers > 1 else None
        try:
            while pending or running:
                progressed = False
                for node in list(pending):
                    deps = node.upstream()
                    if any(records.get(id(d)) is None for d in deps):
                        continue
                    pending.remove(node)
                    progressed = True
                    bad = [d.label for d in deps if records[id(d)].status in ("failed", "blocked")]
                    key, error = self.key_or_error(node)
                    if bad or stop:
                        why = f"upstream failed: {', '.join(bad)}" if bad else "run stopped after a failure"
                        records[id(node)] = Record(node.stage.name, node.item, key, "blocked", error=why)
                        continue
                    if error:  # a raw input is missing: this node fails, independent items go on
                        log.error("%s failed: %s", node.label, error)
                        records[id(node)] = Record(node.stage.name, node.item, key, "failed", error=error)
                        stop = stop or not self.partial
                        continue
                    if self.is_cached(node):
                        records[id(node)] = self._cached_record(node)
                        continue
                    if pool is None:
                        records[id(node)] = self._execute(node)
                        stop = stop or (records[id(node)].status == "failed" and not self.partial)
                    else:
                        running[pool.submit(_execute_in_worker, self._job(node))] = node
                if running and not progressed:
                    done, _ = wait(list(running), return_when=FIRST_COMPLETED)
                    for future in done:
                        node = running.pop(future)
                        records[id(node)] = future.result()
                        stop = stop or (records[id(node)].status == "failed" and not self.partial)
                elif not running and not progressed and pending:
                    raise RuntimeError("scheduler stalled: " + ", ".join(n.label for n in pending))
        finally:
            if pool is not None:
                pool.shutdown(cancel_futures=True)
        return [records[id(node)] for node in order]

    def _cached_record(self, node: Node) -> Record:
        log.info("%s cached (%s)", node.label, self.key(node))
        return Record(node.stage.name, node.item, self.key(node), "cached", path=str(self.output_dir(node)))

    def _job(self, node: Node) -> dict:
        return {
            "stage": node.stage, "item": node.item, "params": node.params, "key": self.key(node),
            "inputs": {k: str(v) for k, v in self.input_paths(node).items()},
            "input_keys": self._input_keys[id(node)],
            "seed": self.seed(node), "cache_dir": str(self.cache_dir), "device": self.device,
            "threads": max(1, (os.cpu_count() or 1) // self.workers),
        }

    def _execute(self, node: Node) -> Record:
        job = self._job(node)
        job["threads"] = 0  # in-process: leave torch's thread count alone
        return _execute_in_worker(job)


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


def _execute_in_worker(job: dict) -> Record:
    """Compute one node (in this process or a pool worker): lock, temp folder, run, atomic rename."""
    stage: Stage = job["stage"]
    cache_dir = Path(job["cache_dir"])
    key, item = job["key"], job["item"]
    final = cache_dir / stage.name / key
    label = f"{stage.name}[{item}]"
    if not logging.getLogger().handlers:  # a spawned pool worker: log like the parent's console
        logging.basicConfig(level=logging.INFO, format="[%(asctime)s][%(name)s][%(levelname)s] - %(message)s")
    if job["threads"]:
        import torch

        torch.set_num_threads(job["threads"])
    with key_lock(cache_dir, stage.name, key):
        if (final / MANIFEST).is_file():  # another process computed it while we waited
            log.info("%s computed by another process (%s)", label, key)
            return Record(stage.name, item, key, "cached", path=str(final))
        for stale in final.parent.glob(f".{key}.tmp-*"):
            shutil.rmtree(stale, ignore_errors=True)
        if final.exists():  # a folder without manifest is never trusted
            shutil.rmtree(final)
        tmp = final.parent / f".{key}.tmp-{os.getpid()}"
        tmp.mkdir(parents=True)
        ctx = Context(stage=stage.name, item=item, params=job["params"],
                      inputs={k: Path(v) for k, v in job["inputs"].items()}, out=tmp,
                      seed=job["seed"], device=job["device"], log=logging.getLogger(f"stages.{stage.name}"))
        started = time.time()
        log.info("%s running (%s)", label, key)
        try:
            metrics = stage.run(ctx) or {}
        except Exception as error:  # noqa: BLE001 - every failure becomes a record, never a cache entry
            shutil.rmtree(tmp, ignore_errors=True)
            message = str(error) if isinstance(error, StageError) else f"{type(error).__name__}: {error}"
            log.error("%s failed: %s", label, message)
            if not isinstance(error, StageError):
                log.debug("%s", traceback.format_exc())
            return Record(stage.name, item, key, "failed", seconds=time.time() - started,
                          error=message, traceback=traceback.format_exc())
        seconds = time.time() - started
        (tmp / METRICS).write_text(json.dumps(metrics, indent=2, default=float))
        manifest = {
            "key": key, "stage": stage.name, "item": item, "version": stage.version,
            "code_hash": stage.code_hash, "params": job["params"], "inputs": job["input_keys"],
            "seed": job["seed"], "seconds": seconds, "device": job["device"],
            "finished": datetime.now(timezone.utc).isoformat(), "versions": _versions(), "metrics": metrics,
        }
        (tmp / MANIFEST).write_text(json.dumps(manifest, indent=2, default=float))
        os.rename(tmp, final)
    log.info("%s done in %.1f s", label, seconds)
    return Record(stage.name, item, key, "ran", seconds=seconds, path=str(final))


def format_table(records: list[Record]) -> str:
    """A fixed-width summary table of a run or plan."""
    rows = [("stage", "item", "status", "seconds", "key")]
    rows += [(r.stage, r.item, r.status, f"{r.seconds:.1f}", r.key) for r in records]
    widths = [max(len(row[i]) for row in rows) for i in range(5)]
    lines = ["  ".join(cell.ljust(w) for cell, w in zip(row, widths)) for row in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    failures = [r for r in records if r.status in ("failed", "blocked")]
    for r in failures:
        lines.append(f"{r.status.upper()}: {r.stage}[{r.item}]: {r.error}")
    return "\n".join(lines)
