"""Fan-in inputs: a stage that reads one upstream output per object and per background photo.

The engine hands a stage a flat dict of named inputs; a fan-in stage gets one input per (kind, item),
e.g. the planes of background photo bg0003. This module owns how those inputs are named: the pipeline
builds them with `fan_in`, the stage reads them back with `fanned`. A dataset generator declares the
kinds it reads in its `INPUTS` (stages/contract/inputs.py: `per_object` of OBJECT_KINDS, `per_photo` of PHOTO_KINDS).

The inputs of one item form a group (`groups`, named "object <name>" or "photo <id>"): when one of them
cannot be had, the engine leaves out the whole group and the stage goes on with the other items, told
why in `Context.left_out` (`left_out_items` adds the configured objects that got no input at all).
"""
from __future__ import annotations

from typing import Iterable, Mapping, TypeVar

from stages.contract.errors import StageError

Value = TypeVar("Value")

OBJECT_KINDS = ("sfm", "splat", "object")  # per object: sfm, splat_train and extract (the object) outputs
PHOTO_KINDS = ("background", "depth", "planes")  # per photo: the photo, its bg_depth and planes outputs


def check_kinds(object_kinds: Iterable[str], photo_kinds: Iterable[str]) -> None:
    """ValueError naming fan-in kinds that are not of OBJECT_KINDS (per object) or PHOTO_KINDS (per photo)."""
    unknown = sorted(set(object_kinds) - set(OBJECT_KINDS)) + sorted(set(photo_kinds) - set(PHOTO_KINDS))
    if unknown:
        raise ValueError(f"unknown input kinds {unknown}; per object: {OBJECT_KINDS}, per photo: {PHOTO_KINDS}")


def input_name(kind: str, item: str) -> str:
    """The name of the input of one kind for one item (object name or photo id)."""
    return f"{kind}:{item}"


def fan_in(items: Mapping[str, Mapping[str, Value]], kinds: Iterable[str]) -> dict[str, Value]:
    """Named inputs of the given kinds for every item; items: {item: {kind: upstream node or path}}."""
    kinds = tuple(kinds)
    return {input_name(kind, item): values[kind] for item, values in items.items() for kind in kinds}


def group_name(role: str, item: str) -> str:
    """The name of the group of inputs of one item: role "object" or "photo"."""
    return f"{role} {item}"


def groups(items: Mapping[str, Mapping[str, Value]], kinds: Iterable[str], role: str) -> dict[str, str]:
    """{input name: group name} of the inputs `fan_in(items, kinds)` makes (Node.optional)."""
    return {input_name(kind, item): group_name(role, item) for item in items for kind in kinds}


def fanned(inputs: Mapping[str, Value], kind: str) -> dict[str, Value]:
    """{item: input} of the inputs of one kind, sorted by item."""
    prefix = input_name(kind, "")
    return dict(sorted((name[len(prefix):], value) for name, value in inputs.items() if name.startswith(prefix)))


def per_object(inputs: Mapping[str, Value], names: Iterable[str], kinds: Iterable[str],
               stage: str) -> dict[str, dict[str, Value]]:
    """{name: {kind: input}} of the objects in `names` (in that order) that have their inputs; objects with
    none are left out. StageError when an object has only some of its kinds, or no object is left."""
    names, kinds = list(names), tuple(kinds)
    found = {kind: fanned(inputs, kind) for kind in kinds}
    present = {name: {kind: found[kind][name] for kind in kinds if name in found[kind]} for name in names}
    partial = [input_name(kind, name) for name, got in present.items() if got for kind in kinds if kind not in got]
    if partial:
        raise StageError(f"{stage}: inputs {partial} missing (objects in config: {names})")
    present = {name: got for name, got in present.items() if got}
    if not present:
        raise StageError(f"{stage}: no object has its inputs (objects in config: {names}); see the failures above")
    return present


def left_out_items(left_out_groups: Mapping[str, str], names: Iterable[str], present: Iterable[str]) -> dict[str, str]:
    """{group: why} of what a fan-in stage runs without: the engine's `Context.left_out`, plus the objects of
    `names` not in `present` that the engine did not leave out (no input was given)."""
    missing = {group_name("object", name): "no input given" for name in names if name not in set(present)}
    return {**missing, **left_out_groups}
