"""The object a stage function receives from the DAG engine."""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

from tqdm.auto import tqdm


@dataclass
class Context:
    """Everything one stage run may use; the engine owns all I/O around it.

    stage:  stage name (e.g. "sfm").
    item:   which item of the fan-out (object name, background id, variant, ...).
    params: the stage's config slice as plain JSON types (hashed into the cache key).
    inputs: named inputs: output folders of upstream nodes (or paths inside them) and raw files.
    out:    an empty temporary folder; the stage writes its outputs here and nowhere else.
    seed:   derived from (global seed, stage, item): independent of worker count and order.
    device: "cuda" when a GPU is present (and allowed), else "cpu".
    left_out: {group: why} of the optional inputs the engine left out because they could not be had (a
            fan-in stage runs on the objects and photos that remain; stages/fan_in.py names the groups).
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

    def progress(self, iterable: Iterable, **kwargs) -> Iterable:
        """Wrap a long loop in a progress bar labelled with the stage and item."""
        kwargs.setdefault("desc", f"{self.stage}[{self.item}]")
        kwargs.setdefault("leave", False)
        kwargs.setdefault("mininterval", 2.0)
        return tqdm(iterable, **kwargs)

