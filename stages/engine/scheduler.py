"""The DAG engine: the nodes' cache keys and a scheduler (the graph's parts, Stage, Node and Ref:
stages/engine/graph.py).

A node is one stage applied to one item (an object, a background photo, a variant). Its cache key is
the sha256 of: the stage name and version, the hash of the stage's code (stages/engine/cache_keys.py: its module
and every `stages.*` module it imports, as syntax trees), the canonical JSON of its config slice, its seed,
the keys of its upstream nodes, the content hashes of its raw input files and the machine facts the stage
declares (stages/engine/machine.py: the device, the CPU kernels' results). Each node is computed as a cache entry
(stages/engine/cache_entry.py: a per-key file lock, a temporary folder renamed with `manifest.json` when complete);
a node whose key another process is computing waits until this process has nothing else to run (two sweep jobs
train two splats side by side instead of one waiting for the other's). A node whose stage finds nothing to compute
(stages/contract/errors.py EmptyInput) is empty, not failed, and so are the nodes that need it.
"""
from __future__ import annotations

import logging
import os
from concurrent.futures import FIRST_COMPLETED, Future, wait
from pathlib import Path
from typing import Mapping

from stages.contract.errors import StageError
from stages.engine.cache_entry import (Job, Outcome, cached_outcome, compute_node, entry_problem, is_whole, key_busy,
                                       unreached_entries)
from stages.engine.cache_keys import canonical_json, content_hash, derive_seed, sha256_hex
from stages.engine.graph import Node, Ref, settings_problems
from stages.engine.machine import machine_facts
from stages.engine.worker_lanes import busy_lanes_counter, init_worker, parent_log_files, share_of_cores
from stages.lib.processes import spawn_pool

log = logging.getLogger(__name__)


# ------------------------------------------------------------------------------------------ engine

UNUSABLE = ("failed", "blocked", "bad-input")  # outcome statuses whose outputs a downstream node cannot read


class Engine:
    """Runs a graph of nodes against a content-addressed cache folder."""

    def __init__(self, cache_dir: str | Path, *, global_seed: int = 0, workers: int = 1,
                 strict: bool = False, device: str = "cpu", reseed: tuple[str, ...] | None = None,
                 machine: Mapping[str, str] | None = None):
        """strict: stop at the first failure and never leave optional inputs out (default: independent
        items go on, and a node runs without the optional inputs that failed).
        machine: the machine facts of the keys (default: this process's on `device`, stages/engine/machine.py).
        reseed: the stages whose seeds follow global_seed; the others keep the seeds of global seed 0
        (and so their cached outputs). None: every stage follows global_seed."""
        self.cache_dir = Path(cache_dir)
        self.global_seed = global_seed
        self.reseed = None if reseed is None else frozenset(reseed)
        self.workers = max(1, workers)
        self.strict = strict
        self.device = device
        self.machine = dict(machine) if machine is not None else machine_facts(device)
        self._keys: dict[int, str] = {}
        self._input_keys: dict[int, dict[str, str]] = {}  # per node: what each input contributed to its key
        self._left_out: dict[int, dict[str, str]] = {}  # per node: {group: why} of the optional inputs left out
        self._failed_roots: dict[int, list[str]] = {}  # per blocked node: the failed nodes it waited for

    # keys and paths -------------------------------------------------------------------------------
    def _used_inputs(self, node: Node) -> dict[str, "Node | Ref | Path"]:
        """The node's inputs minus those of its left-out groups."""
        left_out = self._left_out.get(id(node), {})
        return {name: value for name, value in node.inputs.items() if node.optional.get(name) not in left_out}

    def key(self, node: Node) -> str:
        """The node's cache key (memoised per engine run): of the inputs it uses."""
        cached = self._keys.get(id(node))
        if cached is not None:
            return cached
        inputs = {}
        for name, value in sorted(self._used_inputs(node).items()):
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
        if node.stage.machine:
            payload["machine"] = {fact: self.machine[fact] for fact in node.stage.machine}
        key = sha256_hex(canonical_json(payload).encode())[:20]
        self._keys[id(node)] = key
        self._input_keys[id(node)] = inputs
        return key

    def seed(self, node: Node) -> int:
        """The node's seed: from the global seed if its stage is reseeded, else from global seed 0."""
        follows = self.reseed is None or node.stage.name in self.reseed
        return derive_seed(self.global_seed if follows else 0, node.stage.name, node.seed_item or node.item)

    def output_dir(self, node: Node) -> Path:
        return self.cache_dir / node.stage.name / self.key(node)

    def is_cached(self, node: Node) -> bool:
        """Whether the node's cache entry is there and whole (stages/engine/cache_entry.py: entry_problem)."""
        return is_whole(self.output_dir(node))

    def input_paths(self, node: Node) -> dict[str, Path]:
        """Concrete paths of the inputs a node uses (upstream outputs must exist)."""
        paths = {}
        for name, value in self._used_inputs(node).items():
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

    def _reset(self) -> None:
        """Forget the keys and left-out inputs of a previous run or plan (upstream outcomes may differ)."""
        for memo in (self._keys, self._input_keys, self._left_out, self._failed_roots):
            memo.clear()

    def _admit(self, node: Node, outcomes: dict[int, Outcome], bad_inputs: Mapping[Path, str],
               problems: Mapping[int, str]) -> Outcome | None:
        """None when the node can run, leaving out the optional groups whose inputs cannot be had or are empty (also
        when strict: an empty input is no failure); else its outcome: failed (its settings are wrong: `problems`,
        settings_problems; a raw input of its own is bad, or its key cannot be computed), blocked, or empty (a node
        it needs is empty: nothing to compute, for the same reason)."""
        if id(node) in problems:
            return Outcome(node.stage.name, node.item, "?", "failed", error=f"settings: {problems[id(node)]}")
        lacking: dict[str, tuple[str | None, str]] = {}  # input name -> (failed upstream nodes or None, why)
        empty: dict[str, tuple[str, str]] = {}  # input name -> (empty upstream node, why it is empty)
        for name, value in node.inputs.items():
            if isinstance(value, (Node, Ref)):
                dep = value if isinstance(value, Node) else value.node
                outcome = outcomes[id(dep)]
                if outcome.status == "empty":
                    empty[name] = (dep.label, outcome.error)
                elif outcome.status in UNUSABLE:
                    roots = ", ".join(self._failed_roots.get(id(dep), [dep.label]))
                    why = f"{dep.label} {outcome.status}" + (f" ({roots} failed)" if roots != dep.label else "")
                    lacking[name] = (roots, why)
            elif Path(value) in bad_inputs:
                lacking[name] = (None, bad_inputs[Path(value)])
        required = {name: found for name, found in lacking.items() if self.strict or name not in node.optional}
        own = [why for roots, why in required.values() if roots is None]
        if own:
            return Outcome(node.stage.name, node.item, "?", "failed", error="; ".join(own))
        if required:
            self._failed_roots[id(node)] = list(dict.fromkeys(roots for roots, _ in required.values()))
            return Outcome(node.stage.name, node.item, "?", "blocked",
                          error=f"upstream failed: {', '.join(self._failed_roots[id(node)])}")
        needed = [why for name, (_, why) in empty.items() if name not in node.optional]
        if needed:
            return Outcome(node.stage.name, node.item, "?", "empty", error=needed[0])
        left_out = {}
        for name, (_, why) in lacking.items():
            left_out.setdefault(node.optional[name], why)
        for name, (label, why) in empty.items():
            left_out.setdefault(node.optional[name], f"{label} empty: {why}")
        if left_out:
            self._left_out[id(node)] = left_out
        key, error = self.key_or_error(node)
        if error:
            return Outcome(node.stage.name, node.item, key, "failed", error=error)
        return None

    def plan(self, targets: list[Node], bad_inputs: Mapping[Path, str] | None = None) -> list[Outcome]:
        """What a run would do, without running anything. bad_inputs: {raw input path: what is wrong}."""
        self._reset()
        outcomes: dict[int, Outcome] = {}
        order = self.closure(targets)
        problems = settings_problems(order)
        for node in order:
            outcome = self._admit(node, outcomes, bad_inputs or {}, problems)
            if outcome is not None and outcome.status == "failed":
                outcome.status = "bad-input"
            elif outcome is None and self.is_cached(node):  # cached, or empty (its outcome cached)
                outcome = cached_outcome(node.stage.name, node.item, self.key(node), self.output_dir(node),
                                       self._left_out.get(id(node), {}))
            elif outcome is None:
                outcome = Outcome(node.stage.name, node.item, self.key(node), "would-run",
                                path=str(self.output_dir(node)), left_out=self._left_out.get(id(node), {}),
                                distrusted=entry_problem(self.output_dir(node)) or "")
            outcomes[id(node)] = outcome
        return list(outcomes.values())

    def reachable_keys(self, targets: list[Node]) -> set[tuple[str, str]]:
        return {(n.stage.name, self.key(n)) for n in self.closure(targets)}

    def garbage(self, keep: set[tuple[str, str]]) -> list[Path]:
        """Cache entries (and stale temp folders) whose (stage, key) is not in `keep`."""
        return unreached_entries(self.cache_dir, keep)

    # running ------------------------------------------------------------------------------------
    def run(self, targets: list[Node], bad_inputs: Mapping[Path, str] | None = None) -> list[Outcome]:
        """Run every node the targets need; returns one outcome per node (cached/ran/empty/failed/blocked).

        bad_inputs: {raw input path: what is wrong} found before the run (stages/app/preflight.py): a node
        reading one fails at once, a node that reads it as an optional input runs without its group.
        """
        self._reset()
        order = self.closure(targets)
        problems = settings_problems(order)
        for node in order:
            if id(node) in problems:
                log.error("%s: settings: %s", node.label, problems[id(node)])
        outcomes: dict[int, Outcome] = {}
        pending = list(order)
        running: dict[Future, Node] = {}
        stop = False
        wait_for: Node | None = None  # a node another process computes, run (waiting on its lock) when idle
        pool, busy_lanes = None, None  # busy_lanes: pool workers executing a node (elastic stages read it)
        if self.workers > 1:
            busy_lanes = busy_lanes_counter()
            pool = spawn_pool(self.workers, init_worker, (busy_lanes, parent_log_files()))
        try:
            while pending or running:
                if busy_lanes is not None:  # submitted nodes beyond the lanes wait in the pool's queue
                    busy_lanes.value = min(len(running), self.workers)
                progressed, deferred = False, []
                for node in list(pending):
                    if any(id(d) not in outcomes for d in node.upstream()):
                        continue
                    if stop:
                        outcome = Outcome(node.stage.name, node.item, "?", "blocked",
                                        error="run stopped after a failure (strict)")
                    else:
                        outcome = self._admit(node, outcomes, bad_inputs or {}, problems)
                    if outcome is None and self.is_cached(node):
                        outcome = self._cached_outcome(node)
                    if outcome is None and node is not wait_for and key_busy(self.cache_dir, node.stage.name,
                                                                            self.key(node)):
                        deferred.append(node)  # another process (a sweep job beside this one) computes it
                        continue
                    pending.remove(node)
                    progressed = True
                    if outcome is None and pool is not None:
                        running[pool.submit(compute_node, self._job(node))] = node
                        continue
                    outcomes[id(node)] = outcome if outcome is not None else self._execute(node)
                    stop = stop or self._failure_stops(outcomes[id(node)])
                if deferred and not progressed and (not running or len(running) < self.workers):
                    wait_for = deferred[0]  # nothing else to do here: wait for it, then read it from the cache
                elif running and not progressed:
                    done, _ = wait(list(running), return_when=FIRST_COMPLETED)
                    for future in done:
                        node = running.pop(future)
                        outcomes[id(node)] = future.result()
                        stop = stop or self._failure_stops(outcomes[id(node)])
                elif not running and not progressed and pending:
                    raise RuntimeError("scheduler stalled: " + ", ".join(n.label for n in pending))
        finally:
            if pool is not None:
                pool.shutdown(cancel_futures=True)
        return [outcomes[id(node)] for node in order]

    def _failure_stops(self, outcome: Outcome) -> bool:
        """Log a failed outcome; True when it stops the run (strict)."""
        if outcome.status == "failed":
            log.error("%s failed: %s", outcome.label, outcome.error)
        return self.strict and outcome.status == "failed"

    def _cached_outcome(self, node: Node) -> Outcome:
        """The outcome of a node found whole in the cache: cached, or empty (nothing to compute)."""
        outcome = cached_outcome(node.stage.name, node.item, self.key(node), self.output_dir(node),
                               self._left_out.get(id(node), {}))
        log.info("%s %s (%s)", node.label, outcome.status, self.key(node))
        return outcome

    def _job(self, node: Node, threads: int | None = None) -> Job:
        """The node as a Job; threads: torch's thread count (None: this pool worker's share of the cores)."""
        cores = os.cpu_count() or 1
        return Job(stage=node.stage, item=node.item, params=node.params, key=self.key(node),
                   code_hash=node.stage.code_hash, inputs={k: str(v) for k, v in self.input_paths(node).items()},
                   input_keys=self._input_keys[id(node)], left_out=self._left_out.get(id(node), {}),
                   seed=self.seed(node), cache_dir=str(self.cache_dir), device=self.device,
                   threads=share_of_cores(cores, self.workers) if threads is None else threads, cores=cores,
                   settings=node.settings)

    def _execute(self, node: Node) -> Outcome:
        return compute_node(self._job(node, threads=0))  # in-process: leave torch's thread count alone
