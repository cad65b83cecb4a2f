"""The engine's worker processes ("lanes"): their logging, and torch threads that follow the busy lanes.

With `run.workers` = W > 1 the engine runs nodes in a pool of W spawned processes, each on cores // W
torch threads. A node alone while the other lanes idle (the sample's fifth splat, the last minutes of a
run) would leave cores unused. A stage whose outputs are the same bits for any thread count
(`Stage.elastic_threads`; splat_train: its C++ backward sums gradients in a fixed order) may take them:
at every step of its progress loop it reads the shared count of busy lanes and runs on
cores // busy threads, giving them back as soon as another node starts.

Workers also write their log lines to the parent's log files (the run's dag.log), not only to the
console: without that, a run with workers > 1 logged none of its nodes' progress there.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from multiprocessing import get_context
from typing import Any, Iterable, Iterator

from stages.engine.context import Context

LOG_FORMAT = "[%(asctime)s][%(name)s][%(levelname)s] - %(message)s"  # Hydra's, as in the parent's dag.log
_busy_lanes: Any = None  # this worker's view of the shared count (set by init_worker); None in the parent


def busy_lanes_counter() -> Any:
    """A shared integer (spawn context, no lock: one writer, the engine) counting the busy lanes."""
    return get_context("spawn").RawValue("i", 0)


def parent_log_files() -> list[str]:
    """Paths of the file handlers on this process's root logger (Hydra's <run dir>/dag.log)."""
    return [h.baseFilename for h in logging.getLogger().handlers if isinstance(h, logging.FileHandler)]


def init_worker(busy_lanes: Any, log_files: list[str]) -> None:
    """Pool initializer: keep the shared busy-lane count; log to the console and to the parent's files."""
    global _busy_lanes
    _busy_lanes = busy_lanes
    root = logging.getLogger()
    if not root.handlers:
        logging.basicConfig(level=logging.INFO, format=LOG_FORMAT)
    for path in log_files:
        handler = logging.FileHandler(path, mode="a")
        handler.setFormatter(logging.Formatter(LOG_FORMAT))
        root.addHandler(handler)


def share_of_cores(cores: int, busy: int) -> int:
    """Torch threads for one of `busy` lanes on `cores` cores (at least 1)."""
    return max(1, cores // max(1, busy))


def follow_busy_lanes(iterable: Iterable, cores: int) -> Iterator:
    """Yield from iterable; before each item set torch's threads to this lane's share of the cores."""
    import torch

    for item in iterable:
        if _busy_lanes is not None:
            threads = share_of_cores(cores, _busy_lanes.value)
            if threads != torch.get_num_threads():
                torch.set_num_threads(threads)
        yield item


@dataclass
class ElasticContext(Context):
    """A Context whose progress loops follow the busy lanes (for stages with elastic_threads)."""

    cores: int = 1

    def progress(self, iterable: Iterable, **kwargs) -> Iterable:
        """The Context's progress bar, with torch threads rebalanced at every step."""
        return follow_busy_lanes(super().progress(iterable, **kwargs), self.cores)
