"""Two toy stages and a driver that runs them in a process of its own, for the cache's fault tests
(tests/test_cache_faults.py) and its checks (tests/test_cache_verify.py).

`payload[item]` writes `bytes` bytes to payload.bin (after TOY_SLEEP seconds, not part of its key) and returns
`metrics_bytes` bytes of metrics; `checksum[item]` reads its payload and writes their sum. Each node that runs appends
its label to the file named by TOY_COUNT_FILE. The driver (`python -m tests.factories.toy_cache CACHE ITEMS [options]`)
runs checksum for each item with the engine and prints one `label status` line per node; `--fsize N` limits the files it
writes to N bytes (RLIMIT_FSIZE: a disk that fills), `--kill-at-rename` kills it with SIGKILL when the engine renames
the first temporary folder into its entry (after every file of it is written).
"""
from __future__ import annotations

import argparse
import os
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from stages.contract.inputs import Input, Inputs
from stages.engine.graph import Node, Stage
from stages.engine.scheduler import Engine

if TYPE_CHECKING:
    from stages.engine.context import Context

ROOT = Path(__file__).resolve().parents[2]


def _count(ctx: Context) -> None:
    with open(os.environ["TOY_COUNT_FILE"], "a") as handle:
        handle.write(f"{ctx.stage}[{ctx.item}]\n")


def payload(ctx: Context) -> dict:
    """Write params["bytes"] bytes of a pattern to payload.bin; metrics of params["metrics_bytes"] bytes."""
    _count(ctx)
    time.sleep(float(os.environ.get("TOY_SLEEP", "0")))
    (ctx.out / "payload.bin").write_bytes(bytes(range(256)) * (ctx.params["bytes"] // 256))
    return {"filler": "x" * ctx.params.get("metrics_bytes", 0)}


def checksum(ctx: Context) -> dict:
    """Write the sum of the upstream payload's bytes to sum.txt."""
    _count(ctx)
    total = sum((Path(ctx.inputs["payload"]) / "payload.bin").read_bytes())
    (ctx.out / "sum.txt").write_text(str(total))
    return {"sum": total}


PAYLOAD = Stage("payload", payload)
CHECKSUM = Stage("checksum", checksum, Inputs((Input("payload"),)))


def targets(items: list[str], size: int = 4096, metrics_bytes: int = 0) -> list[Node]:
    """checksum[item] <- payload[item] for each item."""
    return [Node(CHECKSUM, item, {}, {"payload": Node(PAYLOAD, item, {"bytes": size, "metrics_bytes": metrics_bytes})})
            for item in items]


def _kill_at_rename(frame, event: str, function) -> None:
    """A profiler hook: SIGKILL this process when it calls os.rename (the engine's commit of an entry)."""
    if event == "c_call" and function is os.rename:
        os.kill(os.getpid(), signal.SIGKILL)


def main() -> None:
    """The driver: run checksum for each item; print `label status` per node."""
    parser = argparse.ArgumentParser()
    parser.add_argument("cache")
    parser.add_argument("items")
    parser.add_argument("--fsize", type=int, default=0)
    parser.add_argument("--kill-at-rename", action="store_true")
    parser.add_argument("--sleep", type=float, default=0.0)
    parser.add_argument("--metrics-bytes", type=int, default=0)
    args = parser.parse_args()
    if args.fsize:
        resource.setrlimit(resource.RLIMIT_FSIZE, (args.fsize, args.fsize))
    if args.kill_at_rename:
        sys.setprofile(_kill_at_rename)
    os.environ["TOY_SLEEP"] = str(args.sleep)
    outcomes = Engine(args.cache).run(targets(args.items.split(","), metrics_bytes=args.metrics_bytes))
    for outcome in outcomes:
        print(outcome.label, outcome.status, outcome.error.replace("\n", " "), flush=True)


def start_driver(cache: Path, items: str, *options: str) -> subprocess.Popen:
    """The driver started in a process of its own (stdout piped, text)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.Popen([sys.executable, "-m", "tests.factories.toy_cache", str(cache), items, *options],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, cwd=ROOT)


def statuses(output: str) -> dict[str, str]:
    """{label: status} from the driver's output."""
    return {line.split()[0]: line.split()[1] for line in output.splitlines() if line.strip()}


if __name__ == "__main__":  # the stages' module must be tests.factories.toy_cache, not __main__: the same keys
    from tests.factories.toy_cache import main as main_of_module

    main_of_module()
