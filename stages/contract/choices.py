"""Enumerated settings: a config field typed with a `choices` Enum accepts only its values.

OmegaConf checks such a field whenever a config is composed (the command line, conf/*.yaml, a data file, a
sweep), so a wrong value stops the run at start with the valid values, e.g. "Invalid value 'sidecr', expected
one of [sidecar, model, auto] / full_key: bg_depth.provider". The members are `str`s equal to their values (str() and
f-strings give the value), and the pipeline hands stages the plain strings (`OmegaConf.to_container(...,
enum_to_str=True)`), so stage code and cache keys see "auto", never "DepthProvider.auto".
"""
from __future__ import annotations

import sys
from enum import Enum, StrEnum
from typing import Any, Iterable


def choices(name: str, values: Iterable[str]) -> type[StrEnum]:
    """A StrEnum named `name` whose members are `values` (each member's name is its value; str() and format()
    give the value), defined as if in the calling module (it pickles as `<module>.<name>`)."""
    return StrEnum(name, {value: value for value in values}, module=sys._getframe(1).f_globals["__name__"])


def plain(value: Any) -> Any:
    """`value` with every Enum member (also inside dicts, lists and tuples) replaced by its value: what
    `torch.load(weights_only=True)` and JSON readers can take back."""
    if isinstance(value, Enum):
        return value.value
    if isinstance(value, dict):
        return {key: plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(plain(item) for item in value)
    return value
