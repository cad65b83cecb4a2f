"""The DAG engine on toy stages: caching, invalidation, crash safety, locking, failures."""
from __future__ import annotations

import importlib
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import textwrap
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import pytest

from stages.contract.errors import StageError
from stages.contract.inputs import Input, Inputs
from stages.engine.cache_entry import of_this_machine, key_lock
from stages.engine.cache_keys import derive_seed, forget_hashes
from stages.engine.graph import Node, Ref, Stage
from stages.engine.scheduler import Engine

TOY_MODULE = textwrap.dedent(
    """
    import json, logging, os, time
    from pathlib import Path

    VERSION_MARK = {mark!r}

    def _count(ctx):
        log = Path(os.environ["TOY_COUNT_FILE"])
        with open(log, "a") as handle:
            handle.write(ctx.stage + "\\n")

    def source(ctx):
        _count(ctx)
        (ctx.out / "value.txt").write_text(str(ctx.params["n"]) + VERSION_MARK)
        return {{"n": ctx.params["n"]}}

    def double(ctx):
        _count(ctx)
        n = int((ctx.inputs["src"] / "value.txt").read_text().rstrip(VERSION_MARK))
        time.sleep(float(os.environ.get("TOY_SLEEP", "0")))
        (ctx.out / "value.txt").write_text(str(2 * n * ctx.params["factor"]))
        return {{"value": 2 * n * ctx.params["factor"]}}

    def typed(ctx):
        _count(ctx)
        (ctx.out / "settings.txt").write_text(type(ctx.settings).__name__ + " " + str(ctx.settings.factor))

    def from_file(ctx):
        _count(ctx)
        (ctx.out / "copy.txt").write_text(ctx.inputs["raw"].read_text())

    def broken(ctx):
        _count(ctx)
        raise ValueError("bad thing in " + ctx.item)

    def gather(ctx):
        _count(ctx)
        (ctx.out / "gathered.json").write_text(json.dumps({{"inputs": sorted(ctx.inputs), "left_out": ctx.left_out}}))

    def empty_slot(ctx):
        _count(ctx)
        from stages.contract.errors import EmptyInput
        (ctx.out / "partial.txt").write_text("dropped")
        raise EmptyInput("room.mp4 gives 3 frames for 5 slots")

    def warn(ctx):
        _count(ctx)
        logging.getLogger("toy").warning("suspicious input in %s", ctx.item)

    def finished_elsewhere(ctx):
        _count(ctx)
        final = ctx.out.parent / ctx.out.name.split(".tmp-")[0].lstrip(".")  # as another machine would, meanwhile
        final.mkdir()
        (final / "manifest.json").write_text(json.dumps({{"warnings": [], "by": "elsewhere"}}))

    def threads_per_step(ctx):
        import torch
        flags = Path(os.environ["TOY_FLAG_DIR"])
        seen, after_other = [], 0
        for _ in ctx.progress(range(1000)):
            seen.append(torch.get_num_threads())
            (flags / "started").touch()
            after_other += (flags / "other_done").exists()
            if after_other > 5:
                break
            time.sleep(0.02)
        (ctx.out / "threads.json").write_text(json.dumps(seen))

    def short_beside(ctx):
        flags = Path(os.environ["TOY_FLAG_DIR"])
        deadline = time.time() + 60
        while not (flags / "started").exists() and time.time() < deadline:
            time.sleep(0.02)
        time.sleep(0.3)
        logging.getLogger("toy").info("short job of %s done", ctx.item)
        (flags / "other_done").touch()
    """
)


def load_toy(tmp_path: Path, mark: str = "", name: str = "toy_stages"):
    """Write the toy stage module (with a code mark) and import it fresh."""
    (tmp_path / f"{name}.py").write_text(TOY_MODULE.format(mark=mark))
    if str(tmp_path) not in sys.path:
        sys.path.insert(0, str(tmp_path))
    sys.modules.pop(name, None)
    importlib.invalidate_caches()
    forget_hashes()
    return importlib.import_module(name)


TOY_INPUTS = {"double": Inputs((Input("src"),)), "typed": Inputs((Input("src"),)),
              "from_file": Inputs((Input("raw", raw="file"),)),
              "gather": Inputs(per_object=(Input("src"), Input("raw", raw="file")))}


def toy_stage(toy, name: str, **kwargs) -> Stage:
    """The toy module's function `name` as a stage, with the inputs it reads."""
    return Stage(name, getattr(toy, name), TOY_INPUTS.get(name, Inputs()), **kwargs)


def graph(toy, factor: int = 3, n: int = 5):
    src = Node(toy_stage(toy, "source"), "a", {"n": n})
    dbl = Node(toy_stage(toy, "double"), "a", {"factor": factor}, {"src": src})
    return src, dbl


def counts(path: Path) -> list[str]:
    return path.read_text().split() if path.exists() else []


@pytest.fixture
def count_file(tmp_path, monkeypatch):
    path = tmp_path / "count.txt"
    monkeypatch.setenv("TOY_COUNT_FILE", str(path))
    return path


def test_rerun_with_same_config_recomputes_nothing(tmp_path, count_file):
    toy = load_toy(tmp_path)
    engine = Engine(tmp_path / "cache")
    first = engine.run([graph(toy)[1]])
    assert [r.status for r in first] == ["ran", "ran"]
    second = Engine(tmp_path / "cache").run([graph(toy)[1]])
    assert [r.status for r in second] == ["cached", "cached"]
    assert counts(count_file) == ["source", "double"]
    out = Path(second[1].path)
    assert (out / "value.txt").read_text() == "30"
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["metrics"] == {"value": 30} and manifest["params"]["factor"] == 3
    assert json.loads((out / "metrics.json").read_text()) == {"value": 30}  # the engine writes a stage's metrics


def test_downstream_config_change_reruns_only_downstream(tmp_path, count_file):
    toy = load_toy(tmp_path)
    Engine(tmp_path / "cache").run([graph(toy, factor=3)[1]])
    outcomes = Engine(tmp_path / "cache").run([graph(toy, factor=4)[1]])
    assert [r.status for r in outcomes] == ["cached", "ran"]
    assert (Path(outcomes[1].path) / "value.txt").read_text() == "40"
    outcomes = Engine(tmp_path / "cache").run([graph(toy, n=6, factor=4)[1]])
    assert [r.status for r in outcomes] == ["ran", "ran"]


def test_code_change_reruns_stage(tmp_path, count_file):
    toy = load_toy(tmp_path, mark="")
    Engine(tmp_path / "cache").run([graph(toy)[1]])
    toy = load_toy(tmp_path, mark="#")
    outcomes = Engine(tmp_path / "cache").run([graph(toy)[1]])
    assert [r.status for r in outcomes] == ["ran", "ran"]


def test_raw_file_hashed_by_content_not_path_or_mtime(tmp_path, count_file):
    toy = load_toy(tmp_path)
    a, b = tmp_path / "a.txt", tmp_path / "sub" / "b.txt"
    b.parent.mkdir()
    a.write_text("hello")
    b.write_text("hello")
    stage = toy_stage(toy, "from_file")
    key_a = Engine(tmp_path / "cache").key(Node(stage, "x", {}, {"raw": a}))
    key_b = Engine(tmp_path / "cache").key(Node(stage, "x", {}, {"raw": b}))
    assert key_a == key_b
    os.utime(a, (1, 1))
    assert Engine(tmp_path / "cache").key(Node(stage, "x", {}, {"raw": a})) == key_a
    a.write_text("hello!")
    assert Engine(tmp_path / "cache").key(Node(stage, "x", {}, {"raw": a})) != key_a


def test_ref_input_reads_path_inside_upstream(tmp_path, count_file):
    toy = load_toy(tmp_path)
    src = Node(toy_stage(toy, "source"), "a", {"n": 2})
    copy = Node(toy_stage(toy, "from_file"), "a", {}, {"raw": Ref(src, "value.txt")})
    outcomes = Engine(tmp_path / "cache").run([copy])
    assert (Path(outcomes[1].path) / "copy.txt").read_text() == "2"


def test_failure_is_reported_not_cached_and_independent_items_continue(tmp_path, count_file):
    toy = load_toy(tmp_path)
    bad = Node(toy_stage(toy, "broken"), "obj1")
    after_bad = Node(toy_stage(toy, "double"), "obj1", {"factor": 1}, {"src": bad})
    good = graph(toy)[1]
    outcomes = Engine(tmp_path / "cache").run([after_bad, good])
    status = {(r.stage, r.item): r for r in outcomes}
    assert status[("broken", "obj1")].status == "failed"
    assert "bad thing in obj1" in status[("broken", "obj1")].error
    assert status[("double", "obj1")].status == "blocked"
    assert status[("double", "a")].status == "ran"
    assert not list((tmp_path / "cache" / "broken").glob("*/manifest.json"))
    again = Engine(tmp_path / "cache").run([after_bad])
    assert again[0].status == "failed"  # retried, never cached as success


def test_strict_stops_after_a_failure(tmp_path, count_file):
    toy = load_toy(tmp_path)
    bad = Node(toy_stage(toy, "broken"), "obj1")
    outcomes = Engine(tmp_path / "cache", strict=True).run([bad, graph(toy)[1]])
    assert [r.status for r in outcomes] == ["failed", "blocked", "blocked"]


@dataclass
class ToySettings:
    """The toy `typed` stage's settings; `built` counts the instances that passed the value check."""

    factor: int = 1
    built: ClassVar[int] = 0

    def __post_init__(self) -> None:
        if self.factor < 0:
            raise ValueError(f"typed: factor must be >= 0, got {self.factor}")
        ToySettings.built += 1


def test_settings_are_checked_once_at_start_and_the_stage_gets_them_typed(tmp_path, count_file):
    """A value out of range or of the wrong type fails its node before anything runs, in a plan and in a run, naming
    the setting; the other nodes run, and each gets its settings typed, checked once for the plan, the run and the
    stage together."""
    toy = load_toy(tmp_path)
    src = Node(toy_stage(toy, "source"), "a", {"n": 5})
    stage = toy_stage(toy, "typed", config=ToySettings)
    nodes = [Node(stage, item, {"factor": factor}, {"src": src}) for item, factor in (("a", 3), ("b", -1), ("c", "x"))]
    ToySettings.built = 0
    engine = Engine(tmp_path / "cache")
    plan = {o.item: o for o in engine.plan(nodes) if o.stage == "typed"}
    assert plan["a"].status == "would-run"
    assert plan["b"].status == "bad-input" and plan["b"].error == "settings: typed: factor must be >= 0, got -1"
    assert plan["c"].status == "bad-input" and "(full key: typed.factor)" in plan["c"].error
    outcomes = {o.item: o for o in engine.run(nodes) if o.stage == "typed"}
    assert outcomes["a"].status == "ran" and outcomes["b"].status == outcomes["c"].status == "failed"
    assert counts(count_file) == ["source", "typed"]  # the two wrong nodes never started
    assert (engine.output_dir(nodes[0]) / "settings.txt").read_text() == "ToySettings 3"
    assert ToySettings.built == 1


def test_plan_and_garbage(tmp_path, count_file):
    toy = load_toy(tmp_path)
    engine = Engine(tmp_path / "cache")
    target = graph(toy)[1]
    assert [r.status for r in engine.plan([target])] == ["would-run", "would-run"]
    engine.run([target])
    Engine(tmp_path / "cache").run([graph(toy, factor=9)[1]])
    engine = Engine(tmp_path / "cache")
    target = graph(toy)[1]
    assert [r.status for r in engine.plan([target])] == ["cached", "cached"]
    garbage = engine.garbage(engine.reachable_keys([target]))
    assert len(garbage) == 1 and garbage[0].parent.name == "double"


def test_seeds_depend_on_stage_and_item_only():
    assert derive_seed(0, "compose", "full") == derive_seed(0, "compose", "full")
    assert derive_seed(0, "compose", "full") != derive_seed(0, "compose", "no_aug")
    assert derive_seed(0, "compose", "full") != derive_seed(1, "compose", "full")


def test_missing_raw_input_fails_that_item_only(tmp_path, count_file):
    toy = load_toy(tmp_path)
    (tmp_path / "ok.txt").write_text("7")
    missing = Node(toy_stage(toy, "from_file"), "x", {}, {"raw": tmp_path / "nope.mp4"})
    after = Node(toy_stage(toy, "double"), "x", {"factor": 1}, {"src": missing})
    fine = Node(toy_stage(toy, "from_file"), "y", {}, {"raw": tmp_path / "ok.txt"})
    with pytest.raises(StageError, match="nope.mp4"):
        Engine(tmp_path / "cache").key(missing)
    plan = Engine(tmp_path / "cache").plan([after, fine])
    assert [r.status for r in plan] == ["bad-input", "blocked", "would-run"]
    assert "nope.mp4" in plan[0].error and plan[1].error == "upstream failed: from_file[x]"
    outcomes = Engine(tmp_path / "cache").run([after, fine])
    assert [r.status for r in outcomes] == ["failed", "blocked", "ran"]
    assert "nope.mp4" in outcomes[0].error


DRIVER = textwrap.dedent(
    """
    import sys
    sys.path.insert(0, {toy_dir!r})
    import toy_stages
    from stages.contract.inputs import Input, Inputs
    from stages.engine.graph import Node, Stage
    from stages.engine.scheduler import Engine
    src = Node(Stage("source", toy_stages.source), "a", {{"n": 5}})
    dbl = Node(Stage("double", toy_stages.double, Inputs((Input("src"),))), "a", {{"factor": 3}}, {{"src": src}})
    outcomes = Engine({cache!r}).run([dbl])
    print(",".join(r.status for r in outcomes))
    """
)


def start_driver(tmp_path: Path, sleep: float) -> subprocess.Popen:
    script = tmp_path / f"driver_{time.monotonic_ns()}.py"
    script.write_text(DRIVER.format(toy_dir=str(tmp_path), cache=str(tmp_path / "cache")))
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]), TOY_SLEEP=str(sleep))
    return subprocess.Popen([sys.executable, str(script)], env=env, stdout=subprocess.PIPE, text=True)


def wait_for_count(path: Path, name: str, n: int, timeout: float = 30.0) -> None:
    deadline = time.time() + timeout
    while counts(path).count(name) < n:
        assert time.time() < deadline, f"{name} did not start"
        time.sleep(0.05)


def test_sigkill_mid_stage_leaves_nothing_trusted(tmp_path, count_file):
    load_toy(tmp_path)
    proc = start_driver(tmp_path, sleep=30)
    wait_for_count(count_file, "double", 1)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not list((tmp_path / "cache" / "double").glob("*/manifest.json"))
    assert list((tmp_path / "cache" / "double").glob(".*.tmp-*"))  # the half output is there, untrusted
    rerun = start_driver(tmp_path, sleep=0)
    out, _ = rerun.communicate(timeout=60)
    assert out.strip() == "cached,ran"
    assert not list((tmp_path / "cache" / "double").glob(".*.tmp-*"))


def test_two_processes_compute_a_key_once(tmp_path, count_file):
    load_toy(tmp_path)
    Engine(tmp_path / "cache").run([graph(load_toy(tmp_path))[0]])  # source cached already
    first = start_driver(tmp_path, sleep=2)
    wait_for_count(count_file, "double", 1)
    second = start_driver(tmp_path, sleep=2)
    outs = sorted(p.communicate(timeout=60)[0].strip() for p in (first, second))
    assert outs == ["cached,cached", "cached,ran"]
    assert counts(count_file).count("double") == 1


def test_a_node_another_process_computes_waits_while_the_other_nodes_run(tmp_path, count_file):
    toy = load_toy(tmp_path)
    raw = tmp_path / "raw.txt"
    raw.write_text("x")
    computed_elsewhere = Node(toy_stage(toy, "source"), "a", {"n": 1})
    independent = Node(toy_stage(toy, "from_file"), "b", {}, {"raw": raw})
    engine = Engine(tmp_path / "cache")
    key = engine.key(computed_elsewhere)
    result = {}
    with key_lock(tmp_path / "cache", "source", key):  # as a sweep job beside this one would hold it
        thread = threading.Thread(target=lambda: result.update(outcomes=engine.run([computed_elsewhere, independent])))
        thread.start()
        wait_for_count(count_file, "from_file", 1)
        assert counts(count_file) == ["from_file"] and thread.is_alive()
    thread.join(timeout=30)
    assert counts(count_file) == ["from_file", "source"]
    assert [r.status for r in result["outcomes"]] == ["ran", "ran"]


def test_worker_pool_matches_serial_run(tmp_path, count_file):
    toy = load_toy(tmp_path)
    targets = [Node(toy_stage(toy, "double"), f"i{i}", {"factor": i},
                    {"src": Node(toy_stage(toy, "source"), f"i{i}", {"n": i})}) for i in range(4)]
    outcomes = Engine(tmp_path / "pool", workers=2).run(targets)
    assert all(r.status == "ran" for r in outcomes)
    values = sorted(int((Path(r.path) / "value.txt").read_text()) for r in outcomes if r.stage == "double")
    assert values == [0, 2, 8, 18]


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="needs two cores")
@pytest.mark.parametrize("elastic", [True, False])
def test_an_elastic_stage_takes_the_cores_of_idle_lanes(tmp_path, monkeypatch, elastic):
    """Two lanes: the elastic node runs on half the cores beside the short node, on all once alone; a
    node of another stage keeps its half; the workers' log lines reach the parent's log file."""
    toy = load_toy(tmp_path)
    monkeypatch.setenv("TOY_FLAG_DIR", str(tmp_path))
    log_file = tmp_path / "dag.log"
    handler = logging.FileHandler(log_file)
    logging.getLogger().addHandler(handler)
    try:
        outcomes = Engine(tmp_path / "cache", workers=2).run([
            Node(toy_stage(toy, "threads_per_step", elastic_threads=elastic), "long"),
            Node(toy_stage(toy, "short_beside"), "short")])
    finally:
        logging.getLogger().removeHandler(handler)
        handler.close()
    assert [r.status for r in outcomes] == ["ran", "ran"]
    seen = json.loads((Path(outcomes[0].path) / "threads.json").read_text())
    cores = os.cpu_count()
    assert seen[0] == cores // 2
    assert seen[-1] == (cores if elastic else cores // 2)
    logged = log_file.read_text()
    assert "short job of short done" in logged and "threads_per_step[long] done in" in logged


def gather_graph(toy, raw: Path):
    """gather[all] reading source[a] (good), broken[b] (fails) and a raw file, each an optional group."""
    good = Node(toy_stage(toy, "source"), "a", {"n": 1})
    bad = Node(toy_stage(toy, "broken"), "b")
    inputs = {"src:a": good, "src:b": bad, "raw:c": raw}
    groups = {"src:a": "item a", "src:b": "item b", "raw:c": "item c"}
    return Node(toy_stage(toy, "gather"), "all", {}, inputs, groups)


def test_a_fan_in_node_runs_without_the_groups_that_failed(tmp_path, count_file):
    toy = load_toy(tmp_path)
    raw = tmp_path / "c.txt"
    raw.write_text("c")
    outcomes = {r.label: r for r in Engine(tmp_path / "cache").run([gather_graph(toy, raw)])}
    gathered = outcomes["gather[all]"]
    assert gathered.status == "ran" and outcomes["broken[b]"].status == "failed"
    assert gathered.left_out == {"item b": "broken[b] failed"}
    written = json.loads((Path(gathered.path) / "gathered.json").read_text())
    assert written == {"inputs": ["raw:c", "src:a"], "left_out": gathered.left_out}
    assert json.loads((Path(gathered.path) / "manifest.json").read_text())["left_out"] == gathered.left_out
    again = {r.label: r for r in Engine(tmp_path / "cache").run([gather_graph(toy, raw)])}["gather[all]"]
    assert again.status == "cached" and again.key == gathered.key and again.left_out == gathered.left_out
    full = Node(toy_stage(toy, "gather"), "all", {}, {"src:a": Node(toy_stage(toy, "source"), "a", {"n": 1})},
                {"src:a": "item a"})
    assert Engine(tmp_path / "cache").key(full) != gathered.key  # a partial result is never taken for a full one


def test_a_bad_raw_input_fails_its_reader_at_once_and_is_left_out_of_a_fan_in(tmp_path, count_file):
    toy = load_toy(tmp_path)
    raw = tmp_path / "c.txt"
    raw.write_text("c")
    reader = Node(toy_stage(toy, "from_file"), "c", {}, {"raw": raw})
    bad = {raw: f"{raw}: truncated"}
    outcomes = {r.label: r for r in Engine(tmp_path / "cache").run([reader, gather_graph(toy, raw)], bad)}
    assert outcomes["from_file[c]"].status == "failed" and outcomes["from_file[c]"].error == f"{raw}: truncated"
    assert outcomes["gather[all]"].left_out["item c"] == f"{raw}: truncated"
    assert "from_file" not in counts(count_file)
    plan = {r.label: r for r in Engine(tmp_path / "cache").plan([reader, gather_graph(toy, raw)], bad)}
    assert plan["from_file[c]"].status == "bad-input" and plan["broken[b]"].status == "would-run"
    assert plan["gather[all]"].status == "would-run" and list(plan["gather[all]"].left_out) == ["item c"]


def empty_graph(toy):
    """A frame slot whose stage finds it empty, a node that needs it, and a fan-in that reads it with another item."""
    slot = Node(toy_stage(toy, "empty_slot"), "room#3")
    after = Node(toy_stage(toy, "double"), "room#3", {"factor": 1}, {"src": slot})
    gather = Node(toy_stage(toy, "gather"), "all", {}, {"src:a": Node(toy_stage(toy, "source"), "a", {"n": 1}),
                                                        "src:room#3": slot},
                  {"src:a": "photo a", "src:room#3": "photo room#3"})
    return [after, gather]


def test_an_empty_slot_is_an_outcome_cached_like_a_result_and_what_needs_it_is_empty_too(tmp_path, count_file):
    """A stage raising EmptyInput: the node is empty (not failed), its outcome is a cache entry holding only the
    reason (a rerun and a plan read it, the stage is not called again), a node that needs it is empty for the same
    reason (not blocked), and a fan-in runs without its group, even when strict."""
    toy = load_toy(tmp_path)
    why = "room.mp4 gives 3 frames for 5 slots"
    outcomes = {r.label: r for r in Engine(tmp_path / "cache").run(empty_graph(toy))}
    slot = outcomes["empty_slot[room#3]"]
    assert (slot.status, slot.error) == ("empty", why) and slot.path
    assert sorted(p.name for p in Path(slot.path).iterdir()) == ["manifest.json", "metrics.json"]
    assert json.loads((Path(slot.path) / "manifest.json").read_text())["empty"] == why
    assert (outcomes["double[room#3]"].status, outcomes["double[room#3]"].error) == ("empty", why)
    assert outcomes["gather[all]"].status == "ran"
    assert outcomes["gather[all]"].left_out == {"photo room#3": f"empty_slot[room#3] empty: {why}"}
    for engine in (Engine(tmp_path / "cache"), Engine(tmp_path / "cache", strict=True)):
        again = {r.label: r for r in engine.run(empty_graph(toy))}
        assert [again[label].status for label in outcomes] == ["empty", "empty", "cached", "cached"]
        assert again["empty_slot[room#3]"].error == again["double[room#3]"].error == why
    plan = {r.label: r.status for r in Engine(tmp_path / "cache").plan(empty_graph(toy))}
    assert plan == {"empty_slot[room#3]": "empty", "double[room#3]": "empty", "source[a]": "cached",
                    "gather[all]": "cached"}
    assert counts(count_file).count("empty_slot") == 1 and "double" not in counts(count_file)


def test_strict_leaves_nothing_out(tmp_path, count_file):
    toy = load_toy(tmp_path)
    raw = tmp_path / "c.txt"
    raw.write_text("c")
    outcomes = {r.label: r for r in Engine(tmp_path / "cache", strict=True).run([gather_graph(toy, raw)])}
    assert outcomes["gather[all]"].status == "blocked" and "gather" not in counts(count_file)


def test_warnings_of_a_cached_node_are_shown_again(tmp_path, count_file):
    toy = load_toy(tmp_path)
    node = Node(toy_stage(toy, "warn"), "x")
    first = Engine(tmp_path / "cache").run([node])[0]
    assert first.status == "ran" and first.warnings == ["suspicious input in x"]
    second = Engine(tmp_path / "cache").run([Node(toy_stage(toy, "warn"), "x")])[0]
    assert second.status == "cached" and second.warnings == ["suspicious input in x"]
    assert counts(count_file) == ["warn"]


def test_a_node_is_refused_inputs_its_stage_did_not_declare(tmp_path):
    toy = load_toy(tmp_path)
    src = Node(toy_stage(toy, "source"), "a", {"n": 1})
    with pytest.raises(ValueError, match=r"double\[a\]: undeclared inputs \['scr'\] \(declared: \['src'\]\); "
                                         r"required inputs \['src'\] missing"):
        Node(toy_stage(toy, "double"), "a", {"factor": 1}, {"scr": src})
    with pytest.raises(ValueError, match=r"inputs \['src'\] take an upstream output, not a file"):
        Node(toy_stage(toy, "double"), "a", {"factor": 1}, {"src": tmp_path / "value.txt"})
    with pytest.raises(ValueError, match=r"undeclared inputs \['other:x'\]"):
        Node(toy_stage(toy, "gather"), "all", {}, {"src:a": src, "other:x": src})
    with pytest.raises(ValueError, match=r"optional \['raw:c'\] are not among its inputs"):
        Node(toy_stage(toy, "gather"), "all", {}, {"src:a": src}, {"raw:c": "photo c"})


def test_a_key_another_machine_finished_meanwhile_is_taken_as_cached(tmp_path, count_file):
    """On a file system whose locks hold per machine, two machines may compute one key: the second one's
    rename finds the entry done, drops its own temp folder and reads the entry as cached."""
    toy = load_toy(tmp_path)
    [outcome] = Engine(tmp_path / "cache").run([Node(toy_stage(toy, "finished_elsewhere"), "x")])
    assert outcome.status == "cached" and json.loads((Path(outcome.path) / "manifest.json").read_text())["by"] == "elsewhere"
    assert [p.name for p in Path(outcome.path).parent.iterdir() if ".tmp-" in p.name] == []


def test_only_temp_folders_of_this_machine_are_stale_to_the_holder_of_their_key():
    host = socket.gethostname()
    assert of_this_machine(f".abc.tmp-{host}-{2 ** 22 + 7}")
    assert of_this_machine(f".abc.tmp-{host}-{os.getpid()}")  # written under the lock: whoever holds it now, not us
    assert not of_this_machine(f".abc.tmp-other-node-{2 ** 22 + 7}")  # another machine's


def test_a_stage_version_is_the_deliberate_way_to_rekey_it(tmp_path):
    toy = load_toy(tmp_path)
    keys = [Engine(tmp_path / "cache").key(Node(Stage("source", toy.source, version=version), "a", {"n": 1}))
            for version in ("1", "1", "2")]
    assert keys[0] == keys[1] != keys[2]
