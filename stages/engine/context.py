"""The object a stage function receives from the DAG engine, and its progress reports."""
from __future__ import annotations

import logging
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator, TypeVar

from tqdm.auto import tqdm

from stages.engine.settings import typed_settings

PROGRESS_EVERY_S = 30.0  # without a terminal: one line per loop at most this often
Settings = TypeVar("Settings")


class LoggedProgress:
    """A progress report for logs (no terminal): one log line every `every_s` seconds, with the count, the
    total, the elapsed time and what `set_postfix` last gave (e.g. the loss), instead of redrawn bars."""

    def __init__(self, iterable: Iterable, log: logging.Logger, desc: str, total: int | None = None,
                 initial: int = 0, every_s: float = PROGRESS_EVERY_S):
        self.iterable, self.log, self.desc, self.every_s = iterable, log, desc, every_s
        self.total = total if total is not None else (len(iterable) if hasattr(iterable, "__len__") else None)
        self.count = initial
        self.postfix = ""

    def set_postfix(self, **values: Any) -> None:
        """Show these values (e.g. loss=...) in the next line."""
        self.postfix = ", ".join(f"{key}={value}" for key, value in values.items())

    def __iter__(self) -> Iterator:
        started = last = time.monotonic()
        for item in self.iterable:
            yield item
            self.count += 1
            now = time.monotonic()
            if now - last >= self.every_s:
                last = now
                of = f" / {self.total}" if self.total else ""
                self.log.info("%s: %d%s after %.0f s%s", self.desc, self.count, of, now - started,
                              f" ({self.postfix})" if self.postfix else "")


@dataclass
class Context:
    """Everything one stage run may use; the engine owns all I/O around it.

    stage:  stage name (e.g. "sfm").
    item:   which item of the fan-out (object name, background id, variant, ...).
    params: the stage's config slice as plain JSON types (hashed into the cache key).
    inputs: named inputs: output folders of upstream nodes (or paths inside them) and raw files.
    out:    an empty temporary folder; the stage writes its outputs here and nowhere else.
    seed:   derived from (global seed, stage, item; a node's seed_item stands for its item when set): independent
            of worker count and order.
    device: "cuda" when a GPU is present (and allowed), else "cpu".
    settings: the node's typed settings, checked once at start by the engine (an instance of its stage's
            <Name>Config, `Node.settings`); None for a Context made by hand: `typed` checks and builds them.
    left_out: {group: why} of the optional inputs the engine left out because they could not be had (a
            fan-in stage runs on the objects and photos that remain; stages/contract/fan_in.py names the groups).
    """

    stage: str
    item: str
    params: dict[str, Any]
    inputs: dict[str, Path]
    out: Path
    seed: int = 0
    device: str = "cpu"
    left_out: dict[str, str] = field(default_factory=dict)
    log: logging.Logger = field(default_factory=lambda: logging.getLogger("stages"))
    settings: Any = None

    def typed(self, config: type[Settings]) -> Settings:
        """The stage's settings as its `config` class: those the engine checked at start, or, in a Context made by
        hand (tests, benchmarks), `params` checked and built here once (StageError naming a wrong setting)."""
        if not isinstance(self.settings, config):
            self.settings = typed_settings(config, self.stage, self.params)
        return self.settings

    def progress(self, iterable: Iterable, **kwargs) -> Iterable:
        """Wrap a long loop in a progress report labelled with the stage and item: a bar on a terminal, else
        (logs, CI, a sweep's job) a LoggedProgress line every PROGRESS_EVERY_S seconds."""
        kwargs.setdefault("desc", f"{self.stage}[{self.item}]")
        if not sys.stderr.isatty():
            return LoggedProgress(iterable, self.log, kwargs["desc"], kwargs.get("total"), kwargs.get("initial", 0))
        kwargs.setdefault("leave", False)
        kwargs.setdefault("mininterval", 2.0)
        return tqdm(iterable, **kwargs)
