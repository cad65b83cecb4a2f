"""Cut-and-Splat entry point: compose the Hydra config, build the stage graph, run it with the cache.

    python dag.py                              # the default pipeline on the embedded sample
    python dag.py run.action=plan              # what is cached and what would run
    python dag.py run.action=gc                # list cache entries no current config reaches (+ run.gc_apply=true)
    python dag.py run.action=predict predict.source=PHOTOS   # the config's detector on photos or a video
    python dag.py run.action=verify            # read back every cache entry, list the bad ones (+ run.verify_apply=true)
    python dag.py run.action=graph             # the stage graph as Mermaid text (+ run.graph_status=true: cached)
    python dag.py +experiment=ablation         # the paper's ablation as a Hydra sweep, then report.md
"""
from __future__ import annotations

import stages  # noqa: F401  (first: sets OMP_WAIT_POLICY before torch loads libgomp, see stages/__init__.py)

import json
import logging
import os
import shutil
import sys
from dataclasses import asdict
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig

from stages.app.config import accept_data_file, check_settings, check_values, register
from stages.app.graph_view import mermaid
from stages.app.pipeline import build_graph
from stages.app.preflight import check_inputs
from stages.app.summary import data_line, plan_report, run_report, summarise
from stages.engine.cache_verify import timed_verify, verify_report
from stages.engine.scheduler import Engine
from stages.lib.device import choose_device
from stages.lib.file_checks import MAX_PIXELS_ENV

log = logging.getLogger("dag")
CONF = Path(__file__).resolve().parent / "conf"
register()


@hydra.main(version_base=None, config_path="conf", config_name="config")
def main(cfg: DictConfig) -> None:
    base = Path(hydra.utils.get_original_cwd())
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    cache_dir = Path(cfg.run.cache_dir) if Path(cfg.run.cache_dir).is_absolute() else base / cfg.run.cache_dir
    try:
        check_settings(cfg)
        os.environ[MAX_PIXELS_ENV] = str(cfg.run.max_image_pixels)  # the readers' limit, here and in the workers
        device = choose_device(cfg.run.device)
        engine = Engine(cache_dir, global_seed=int(cfg.run.seed), workers=int(cfg.run.workers),
                        strict=bool(cfg.run.strict), device=device, reseed=None if cfg.run.reseed is None else tuple(map(str, cfg.run.reseed)))
        graph = build_graph(cfg, base, device)
        targets = graph.targets(cfg.run.until)
        check_values(engine.closure(targets))
    except (ValueError, FileNotFoundError) as error:  # a setting or path of the config: nothing has run
        log.error("%s", error)
        sys.exit(2)
    notes = [] if cfg.data.test_sets else ["no test sets: eval skipped"]

    if cfg.run.action == "gc":
        garbage = engine.garbage(engine.reachable_keys(targets))
        for path in garbage:
            print(("removing " if cfg.run.gc_apply else "unreached ") + str(path))
            if cfg.run.gc_apply:
                shutil.rmtree(path) if path.is_dir() else path.unlink()
        print(f"{len(garbage)} cache entries {'removed' if cfg.run.gc_apply else 'unreached (run.gc_apply=true removes them)'}")
        return
    if cfg.run.action == "verify":
        checks, seconds = timed_verify(cache_dir, bool(cfg.run.verify_apply))
        (run_dir / "verify.json").write_text(json.dumps([asdict(c) for c in checks], indent=2, default=str))
        print(verify_report(checks, seconds, bool(cfg.run.verify_apply)))
        sys.exit(1 if any(c.status == "bad" and not c.removed for c in checks) else 0)
    if cfg.run.action == "graph":
        text = mermaid(graph, engine.plan(targets) if cfg.run.graph_status else None)
        (run_dir / "graph.mmd").write_text(text + "\n")
        print(text)
        return
    problems = check_inputs(graph, [o.name for o in cfg.data.objects])
    if cfg.run.action == "predict":
        from stages.app.predict import predict_action  # torch and the detector load for this action only

        sys.exit(predict_action(cfg, engine, graph, problems, base, device, list(HydraConfig.get().overrides.task)))
    if cfg.run.action == "plan":
        outcomes = engine.plan(targets, problems)
        (run_dir / "plan.json").write_text(json.dumps([asdict(r) for r in outcomes], indent=2))
        print(plan_report(outcomes, problems, notes, run_dir / "plan.json", data_line(graph.nodes)))
        return
    for message in problems.values():
        log.error("input problem: %s", message)
    if problems and cfg.run.strict:
        log.error("run.strict: %d input problems, nothing was run (without strict, the run goes on without "
                  "the bad files)", len(problems))
        sys.exit(1)

    print(data_line(graph.nodes), flush=True)
    outcomes = engine.run(targets, problems)
    summary = summarise(outcomes, cfg, problems, notes)
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    print(run_report(summary, outcomes, run_dir / "summary.json"))
    if summary["failed"] and HydraConfig.get().mode != RunMode.MULTIRUN:
        sys.exit(1)


if __name__ == "__main__":
    sys.argv = accept_data_file(sys.argv, CONF, Path.cwd())
    main()
