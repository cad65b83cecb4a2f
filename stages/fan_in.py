"""Fan-in inputs: a stage that reads one upstream output per object and per background photo.

The engine hands a stage a flat dict of named inputs; a fan-in stage gets one input per (kind, item),
e.g. the planes of background photo bg0003. This module owns how those inputs are named: the pipeline
builds them with `fan_in`, the stage reads them back with `fanned`. A dataset generator declares the
kinds it reads as an `InputKinds`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Mapping, TypeVar

from stages.context import StageError

Value = TypeVar("Value")

OBJECT_KINDS = ("sfm", "splat", "object")  # per object: sfm, splat_train and extract (the object) outputs
PHOTO_KINDS = ("background", "depth", "planes")  # per photo: the photo, its bg_depth and planes outputs


@dataclass(frozen=True)
class InputKinds:
    """The upstream outputs a stage reads for every object (of OBJECT_KINDS) and every photo (of PHOTO_KINDS)."""

    per_object: tuple[str, ...]
    per_photo: tuple[str, ...]

    def __post_init__(self) -> None:
        unknown = sorted(set(self.per_object) - set(OBJECT_KINDS)) + sorted(set(self.per_photo) - set(PHOTO_KINDS))
        if unknown:
            raise ValueError(f"unknown input kinds {unknown}; per object: {OBJECT_KINDS}, per photo: {PHOTO_KINDS}")


def input_name(kind: str, item: str) -> str:
    """The name of the input of one kind for one item (object name or photo id)."""
    return f"{kind}:{item}"


def fan_in(items: Mapping[str, Mapping[str, Value]], kinds: Iterable[str]) -> dict[str, Value]:
    """Named inputs of the given kinds for every item; items: {item: {kind: upstream node or path}}."""
    kinds = tuple(kinds)
    return {input_name(kind, item): values[kind] for item, values in items.items() for kind in kinds}


def fanned(inputs: Mapping[str, Value], kind: str) -> dict[str, Value]:
    """{item: input} of the inputs of one kind, sorted by item."""
    prefix = input_name(kind, "")
    return dict(sorted((name[len(prefix):], value) for name, value in inputs.items() if name.startswith(prefix)))


def per_object(inputs: Mapping[str, Value], names: Iterable[str], kinds: Iterable[str],
               stage: str) -> list[dict[str, Value]]:
    """{kind: input} of each object in `names` order; StageError naming the inputs that are missing."""
    names, kinds = list(names), tuple(kinds)
    found = {kind: fanned(inputs, kind) for kind in kinds}
    missing = [input_name(kind, name) for name in names for kind in kinds if name not in found[kind]]
    if missing:
        raise StageError(f"{stage}: inputs {missing} missing (objects in config: {names})")
    return [{kind: found[kind][name] for kind in kinds} for name in names]
