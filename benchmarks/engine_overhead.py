"""Engine overhead of a cached rerun of a 200-node graph (target: under 1 s).

    python -m benchmarks.engine_overhead [--nodes 200]
"""
from __future__ import annotations

import argparse
import importlib
import json
import tempfile
import time
from pathlib import Path

from stages.contract.inputs import Input, Inputs
from stages.engine.cache_keys import forget_hashes
from stages.engine.graph import Node, Stage
from stages.engine.scheduler import Engine


def write_value(ctx):
    """A toy stage: writes one small file, like a stage with a tiny output."""
    total = sum(int((path / "value.txt").read_text()) for path in ctx.inputs.values()) + ctx.params["i"]
    (ctx.out / "value.txt").write_text(str(total))
    return {"value": total}


def build(n: int, raw: Path) -> list[Node]:
    """A graph shaped like the pipeline: per-item chains of 4 stages fanning into variant nodes."""
    me = importlib.import_module("benchmarks.engine_overhead")  # importable by spawned workers
    stages = [Stage(f"s{k}", me.write_value, Inputs((Input("src", required=False),))) for k in range(4)]
    chains, nodes = [], []
    for item in range((n - 10) // 4):
        prev = None
        for k, stage in enumerate(stages):
            node = Node(stage, f"item{item}", {"i": item, "k": k}, {"src": prev} if prev else {})
            nodes.append(node)
            prev = node
        chains.append(prev)
    fan = Stage("variant", me.write_value, Inputs(per_object=(Input("src"),)))
    targets = [Node(fan, f"v{v}", {"i": v}, {f"src:{i}": c for i, c in enumerate(chains)}) for v in range(n - len(nodes))]
    return targets


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--nodes", type=int, default=200)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        cache = Path(tmp) / "cache"
        t0 = time.perf_counter()
        cold = Engine(cache).run(build(args.nodes, Path(tmp)))
        forget_hashes()  # as in a fresh process: hash code and files again
        t1 = time.perf_counter()
        warm = Engine(cache).run(build(args.nodes, Path(tmp)))
        t2 = time.perf_counter()
    assert all(r.status == "cached" for r in warm)
    print(json.dumps({"nodes": len(cold), "cold_run_s": round(t1 - t0, 3), "cached_rerun_s": round(t2 - t1, 3)}))


if __name__ == "__main__":
    main()
