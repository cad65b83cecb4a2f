"""The graph's parts: a stage declaration (Stage), a node (one stage applied to one item, with its settings and
inputs) and a reference to a path inside an upstream node's output (Ref). The engine (stages/engine/scheduler.py)
keys, plans and runs them."""
from __future__ import annotations

import functools
import importlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from stages.contract.errors import StageError
from stages.contract.inputs import Inputs
from stages.engine.cache_keys import module_closure_hash
from stages.engine.machine import FACTS
from stages.engine.settings import typed_settings

if TYPE_CHECKING:
    from stages.engine.context import Context

@dataclass(frozen=True)
class Stage:
    """A stage declaration: its name, the function that runs it, the inputs it reads (stages/contract/inputs.py: a
    node given other names is refused) and a version, the deliberate way to re-key the stage when its code
    did not change (e.g. a dependency changed its results).

    run: the function, or "module:function", imported only when a node of the stage runs (so a graph is built,
    keyed and planned without loading the libraries the stage computes with).
    elastic_threads: its outputs are the same bits for any torch thread count, so in a worker pool it may use the
    cores of idle lanes (stages/engine/worker_lanes.py); not in the key.
    machine: the facts of the machine its outputs depend on (names of stages/engine/machine.py FACTS), in the key.
    config: the dataclass of its settings; a node's are checked against it once, at start (Node.settings).
    """

    name: str
    run: Callable[[Context], dict | None] | str
    inputs: Inputs = Inputs()
    version: str = "1"
    elastic_threads: bool = False
    machine: tuple[str, ...] = ()
    config: type | None = None

    def __post_init__(self) -> None:
        """ValueError naming an unknown machine fact."""
        unknown = sorted(set(self.machine) - set(FACTS))
        if unknown:
            raise ValueError(f"stage {self.name}: unknown machine facts {unknown}; known: {list(FACTS)}")

    @property
    def module(self) -> str:
        """The name of the module that holds the stage's function."""
        return self.run.partition(":")[0] if isinstance(self.run, str) else self.run.__module__

    def function(self) -> Callable[[Context], dict | None]:
        """The stage's function (imported here when `run` names it)."""
        if not isinstance(self.run, str):
            return self.run
        module, _, name = self.run.partition(":")
        return getattr(importlib.import_module(module), name)

    @property
    def code_hash(self) -> str:
        """Hash of the normalised code of the stage's module and every `stages.*` module it imports (cache_keys.py)."""
        return module_closure_hash(self.module)


@dataclass(frozen=True)
class Ref:
    """An input that is a path inside an upstream node's output folder ('' = the folder itself)."""

    node: "Node"
    subpath: str = ""


@dataclass(eq=False)
class Node:
    """One stage applied to one item, with its config slice and named inputs.

    inputs map a name to an upstream Node (its output folder), a Ref (a path inside it) or a Path
    (a raw file or folder, hashed by content). optional maps some input names to a group (e.g. the
    inputs of one object of a fan-in stage): when an input of a group cannot be had (its upstream node
    failed, or its raw file is bad), the engine leaves out every input of that group and runs the node
    on the rest, unless the engine is strict. seed_item: the item whose seed the node takes (default: its
    own), so that two variants draw the same random numbers (a paired comparison).
    """

    stage: Stage
    item: str
    params: dict[str, Any] = field(default_factory=dict)
    inputs: dict[str, "Node | Ref | Path"] = field(default_factory=dict)
    optional: dict[str, str] = field(default_factory=dict)
    seed_item: str = ""

    def __post_init__(self) -> None:
        """ValueError when the inputs are not what the stage declares, or an optional one is not an input."""
        self.stage.inputs.check(self.label, self.inputs)
        stray = sorted(set(self.optional) - set(self.inputs))
        if stray:
            raise ValueError(f"{self.label}: optional {stray} are not among its inputs")

    @property
    def label(self) -> str:
        return f"{self.stage.name}[{self.item}]"

    @functools.cached_property
    def settings(self) -> Any:
        """The node's params typed as its stage's config class, checked once (stages/engine/settings.py
        typed_settings: StageError naming a wrong setting); None for a stage that declares none."""
        return None if self.stage.config is None else typed_settings(self.stage.config, self.stage.name, self.params)

    def upstream(self) -> list["Node"]:
        """The nodes this node reads from, in input order."""
        deps = []
        for value in self.inputs.values():
            if isinstance(value, Node):
                deps.append(value)
            elif isinstance(value, Ref):
                deps.append(value.node)
        return deps


def settings_problems(nodes: list[Node]) -> dict[int, str]:
    """{id(node): what is wrong} of the nodes whose settings their stage's config class refuses (Node.settings):
    the one check of every node's settings, made before anything runs."""
    problems = {}
    for node in nodes:
        try:
            node.settings
        except StageError as error:
            problems[id(node)] = str(error)
    return problems
