"""The graph of a configuration drawn as Mermaid text (`python dag.py run.action=graph`): one box per stage with
how many nodes it fans out to, an arrow where a stage reads another's output, and, given a plan, how many of each
stage's nodes are cached. GitHub renders the text in a ```mermaid block (the README's picture of the DAG)."""
from __future__ import annotations

from typing import Iterable

from stages.app.pipeline import FAN_OUT, ORDER, Graph
from stages.engine.cache_entry import Outcome


def stage_label(stage: str, count: int, cached: int | None = None) -> str:
    """A stage's box: its name, its fan-out ("5 objects": one node each) and, when known, how many nodes are
    cached."""
    noun = FAN_OUT.get(stage)
    parts = [stage] + ([f"{count} {noun}{'s' * (count != 1)}"] if noun else [])
    if cached is not None:
        parts.append(f"{cached}/{count} cached")
    return "<br/>".join(parts)


def mermaid(graph: Graph, plan: Iterable[Outcome] | None = None) -> str:
    """Mermaid flowchart text of `graph` ({stage: nodes}); with `plan` (Engine.plan's outcomes), each box also says
    how many of its nodes are cached and is styled `cached` when all are, `partly` when some are."""
    stages = [stage for stage in ORDER if graph.nodes.get(stage)]
    cached: dict[str, int] | None = None
    if plan is not None:
        cached = dict.fromkeys(stages, 0)
        for outcome in plan:
            cached[outcome.stage] += outcome.status in ("cached", "empty")  # empty: nothing left to compute either
    lines = ["flowchart LR"]
    for stage in stages:
        count = len(graph.nodes[stage])
        lines.append(f'    {stage}["{stage_label(stage, count, None if cached is None else cached[stage])}"]')
    edges = dict.fromkeys((upstream.stage.name, stage) for stage in stages for node in graph.nodes[stage]
                          for upstream in node.upstream())
    lines += [f"    {source} --> {target}" for source, target in edges]
    if cached is not None:
        lines += ["    classDef cached fill:#d4edda,stroke:#28a745", "    classDef partly fill:#fff3cd,stroke:#ffc107"]
        for stage in stages:
            done, count = cached[stage], len(graph.nodes[stage])
            if done:
                lines.append(f"    class {stage} {'cached' if done == count else 'partly'}")
    return "\n".join(lines)
