"""What a stage reads: every stage module declares its named inputs as `INPUTS`, an `Inputs`.

The engine refuses a node whose inputs the stage did not declare (a misspelt name fails when the graph is
built, not deep inside a run), and preflight (stages/app/preflight.py) checks each user file by the `raw` kind its
input declares. A dataset generator also declares fan-in inputs, one per object (`per_object`) and one per
background photo (`per_photo`), and the dataset stage one per shard (`per_shard`), named `<kind>:<item>`
(stages/contract/fan_in.py).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

RAW_KINDS = ("file", "capture", "video", "photo", "depth_sidecar", "intrinsics", "testset", "trained_model",
             "depth_model")


@dataclass(frozen=True)
class Input:
    """One input of a stage.

    raw: when a user's file or folder may be given here, what preflight checks it as (one of RAW_KINDS:
    "capture" a video or folder of photos, "video" a background video, "photo", "depth_sidecar", "intrinsics" a
    photo's K JSON,
    "testset" a COCO folder, "trained_model" a .ply/.splat, "depth_model" (stages/lib/depth/models.py), "file"
    anything that exists);
    "" = only an upstream stage's output. required: a node must be given it.
    """

    name: str
    raw: str = ""
    required: bool = True

    def __post_init__(self) -> None:
        if ":" in self.name:
            raise ValueError(f"input name {self.name!r}: ':' separates a fan-in kind from its item")
        if self.raw and self.raw not in RAW_KINDS:
            raise ValueError(f"input {self.name!r}: raw kind {self.raw!r} is not one of {RAW_KINDS}")


@dataclass(frozen=True)
class Inputs:
    """A stage's declared inputs: named ones, and fan-in kinds read once per object, once per photo and once per
    shard of a generated dataset."""

    named: tuple[Input, ...] = ()
    per_object: tuple[Input, ...] = ()
    per_photo: tuple[Input, ...] = ()
    per_shard: tuple[Input, ...] = ()

    @property
    def object_kinds(self) -> tuple[str, ...]:
        """Names of the per-object fan-in kinds."""
        return tuple(i.name for i in self.per_object)

    @property
    def photo_kinds(self) -> tuple[str, ...]:
        """Names of the per-photo fan-in kinds."""
        return tuple(i.name for i in self.per_photo)

    def find(self, name: str) -> Input | None:
        """The declaration of an input name (a fan-in name `<kind>:<item>` by its kind), or None."""
        kind, fanned, _ = name.partition(":")
        declared = self.per_object + self.per_photo + self.per_shard if fanned else self.named
        return next((i for i in declared if i.name == kind), None)

    def check(self, label: str, given: Mapping[str, Any]) -> None:
        """ValueError naming what is wrong with the inputs given to a node `label`: names not declared, a user
        file given to an input that takes only upstream outputs, or required inputs missing."""
        undeclared = sorted(name for name in given if self.find(name) is None)
        wrong_raw = sorted(name for name, value in given.items()
                           if isinstance(value, Path) and name not in undeclared and not self.find(name).raw)
        missing = sorted(i.name for i in self.named if i.required and i.name not in given)
        problems = ([f"undeclared inputs {undeclared} (declared: {self.declared_names()})"] if undeclared else []) + \
                   ([f"inputs {wrong_raw} take an upstream output, not a file"] if wrong_raw else []) + \
                   ([f"required inputs {missing} missing"] if missing else [])
        if problems:
            raise ValueError(f"{label}: " + "; ".join(problems))

    def declared_names(self) -> list[str]:
        """The declared names, fan-in kinds as `<kind>:<item>`."""
        return [i.name for i in self.named] + [f"{i.name}:<item>" for i in
                                                self.per_object + self.per_photo + self.per_shard]
