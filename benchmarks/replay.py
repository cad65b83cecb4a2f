"""Replay cache entries with another checkout's code: does a refactor keep a stage's behaviour (issue 29)?

    python -m benchmarks.replay --tree /path/to/old/checkout ENTRY [ENTRY ...] [--set key=value ...]

ENTRY is a cache entry (`<cache>/<stage>/<key>/`). For each, the stage of the other checkout (`--tree`, e.g.
`git archive <commit> | tar -x -C /tmp/old`) runs on the entry's own inputs (the upstream entries its
manifest names, still in the cache), settings and seed, into a temporary folder; every file it writes is then
compared with the entry's. Settings the other checkout does not know are dropped and listed (a refactor's new
settings at their defaults must mean "as before"); `--set` overrides one (e.g. `num_images=40`, then only
the files both wrote are compared). JSON files that differ are narrowed to the keys that differ (timings
differ on every run). A stage's code runs in a child process whose `stages` package is the other
checkout's; nothing of this checkout is imported there. Prints a markdown table (stage, item, key, files
compared, identical, what differs).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from benchmarks.lib.settings import add_set_option

NOT_OUTPUTS = {"manifest.json", "metrics.json"}  # written by the engine, not by the stage


def resolve_inputs(entry: Path, recorded: dict[str, str]) -> dict[str, str]:
    """The entry's recorded inputs as paths: upstream entries (or paths inside them) through input_path, raw
    files as recorded. (Imported here: the child, whose `stages` is the other checkout's, must not load it.)"""
    from stages.engine.cache_entry import input_path

    return {name: str(input_path(entry, name) or value) for name, value in recorded.items()}


def json_differences(a: object, b: object, path: str = "") -> list[str]:
    """Paths (`a.b[2]`) at which two parsed JSON documents differ, leaves first."""
    if isinstance(a, dict) and isinstance(b, dict):
        return [d for k in sorted(set(a) | set(b)) for d in
                (json_differences(a.get(k), b.get(k), f"{path}.{k}" if path else str(k)) if k in a and k in b
                 else [f"{path}.{k}" if path else str(k)])]
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in json_differences(x, y, f"{path}[{i}]")]
    return [] if a == b else [path or "(root)"]


def compare(replayed: Path, entry: Path) -> dict:
    """Files the replay wrote that the entry also holds: how many, how many byte-identical, what differs."""
    digest = lambda p: hashlib.sha256(p.read_bytes()).hexdigest()  # noqa: E731
    files = sorted(p.relative_to(replayed) for p in replayed.rglob("*") if p.is_file() and p.name not in NOT_OUTPUTS)
    differing, missing = {}, [str(f) for f in files if not (entry / f).is_file()]
    for name in (f for f in files if (entry / f).is_file()):
        if digest(replayed / name) == digest(entry / name):
            continue
        if name.suffix == ".json":
            keys = json_differences(json.loads((replayed / name).read_text()), json.loads((entry / name).read_text()))
            differing[str(name)] = sorted({k.split("[")[0] for k in keys})[:8]
        else:
            differing[str(name)] = ["bytes"]
    return {"files": len(files) - len(missing), "identical": len(files) - len(missing) - len(differing),
            "differing": differing, "not_in_entry": missing}


def replay_in_child(tree: Path, job: dict) -> dict:
    """Runs one stage with `tree`'s code (this file as a script, with PYTHONPATH=tree); the child's report."""
    with tempfile.NamedTemporaryFile("w", suffix=".json", delete=False) as handle:
        json.dump(job, handle)
    env = {**os.environ, "PYTHONPATH": str(tree)}
    # -P: the script's own folder (this checkout's benchmarks/) stays off the child's import path
    done = subprocess.run([sys.executable, "-P", __file__, "--child", handle.name], env=env, cwd=tree,
                          capture_output=True, text=True)
    os.unlink(handle.name)
    if done.returncode != 0:
        raise RuntimeError(f"{job['entry']}: the replay failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def child(job_file: str) -> None:
    """In the child: the other checkout's stage runs on the job's inputs; prints the settings it dropped."""
    import dataclasses
    import importlib
    import logging

    logging.basicConfig(level=logging.WARNING)
    job = json.loads(Path(job_file).read_text())
    try:  # the floor plan (issue 54): a stage's room holds its run and its spec, the engine is a package
        module = importlib.import_module(f"stages.{job['stage']}.run")
        spec = importlib.import_module(f"stages.{job['stage']}.spec")
        context = importlib.import_module("stages.engine.context").Context
    except ModuleNotFoundError:  # before it: stages/<stage>.py beside stages/context.py
        module = importlib.import_module(f"stages.{job['stage']}")
        context = importlib.import_module("stages.context").Context
        try:
            spec = importlib.import_module(f"stages.specs.{job['stage']}")
        except ModuleNotFoundError:  # checkouts before stages/specs/ kept the config in the stage module
            spec = module
    configs = [v for v in vars(spec).values() if isinstance(v, type) and dataclasses.is_dataclass(v)
               and v.__module__ == spec.__name__ and v.__name__.endswith("Config")]
    params, dropped = dict(job["params"]), []
    if configs:
        known = {f.name for f in dataclasses.fields(configs[0])}
        dropped = sorted(set(params) - known)
        params = {k: v for k, v in params.items() if k in known}
    module.run(context(stage=job["stage"], item=job["item"], params=params, inputs=job["inputs"],
                       out=Path(job["out"]), seed=job["seed"]))
    print(json.dumps({"dropped": dropped}))


def main() -> None:
    if len(sys.argv) == 3 and sys.argv[1] == "--child":
        child(sys.argv[2])
        return
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("entries", type=Path, nargs="+", help="cache entries (<cache>/<stage>/<key>)")
    parser.add_argument("--tree", type=Path, required=True, help="the other checkout's root folder")
    add_set_option(parser, "the replayed stage's settings")
    args = parser.parse_args()
    print("| stage | item | key | files | identical | differs (JSON: keys) | settings dropped |")
    print("|---|---|---|---|---|---|---|")
    for entry in args.entries:
        manifest = json.loads((entry / "manifest.json").read_text())
        with tempfile.TemporaryDirectory(prefix="replay-") as out:
            job = {"entry": str(entry), "stage": manifest["stage"], "item": manifest["item"],
                   "params": {**manifest["params"], **dict(args.set)}, "seed": manifest["seed"], "out": out,
                   "inputs": resolve_inputs(entry, manifest["inputs"])}
            dropped = replay_in_child(args.tree.resolve(), job)["dropped"]
            found = compare(Path(out), entry)
        extra = [f"only the replay wrote {len(found['not_in_entry'])} files"] if found["not_in_entry"] else []
        differs = "; ".join([f"{name}: {', '.join(keys)}" for name, keys in found["differing"].items()] + extra) or "-"
        print(f"| {manifest['stage']} | {manifest['item']} | {entry.name} | {found['files']} | {found['identical']} "
              f"| {differs} | {', '.join(dropped) or '-'} |", flush=True)


if __name__ == "__main__":
    main()
