"""Cut-and-Splat entry point: compose the Hydra config, build the stage graph, run it with the cache.

    python dag.py                              # the default pipeline on the embedded sample
    python dag.py run.action=plan              # what is cached and what would run
    python dag.py run.action=gc                # list cache entries no current config reaches (+ run.gc_apply=true)
    python dag.py +experiment=ablation         # the paper's ablation as a Hydra sweep, then report.md
"""
from __future__ import annotations

import stages  # noqa: F401  (first: sets OMP_WAIT_POLICY before torch loads libgomp, see stages/__init__.py)

import json
import logging
import shutil
import sys
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from stages.config import register
from stages.engine import Engine, Record, format_table
from stages.pipeline import build_graph, reseeded_stages

log = logging.getLogger("dag")
register()


def choose_device(requested: str) -> str:
    """"cuda" when asked for or (auto) when a GPU is present, else "cpu"."""
    if requested == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if requested == "cuda" and not torch.cuda.is_available():
        raise ValueError("run.device=cuda but no CUDA GPU is available; use run.device=auto or cpu")
    return requested


def summarise(records: list[Record], cfg: DictConfig) -> dict:
    """The run summary: one row per node, plus the eval metrics of this configuration."""
    evals = {}
    for record in records:
        if record.stage == "eval" and record.status in ("ran", "cached"):
            evals[record.item] = json.loads((Path(record.path) / "metrics.json").read_text())
    stage_seconds: dict[str, float] = {}
    for record in records:
        if record.path and record.status in ("ran", "cached"):
            manifest = Path(record.path) / "manifest.json"
            if manifest.is_file():
                seconds = json.loads(manifest.read_text()).get("seconds", 0.0)
                stage_seconds[record.stage] = stage_seconds.get(record.stage, 0.0) + seconds
    return {
        "variant": OmegaConf.to_container(cfg.variant, resolve=True),
        "config": OmegaConf.to_container(cfg, resolve=True),
        "records": [record.__dict__ for record in records],
        "eval": evals,
        "compute_seconds_by_stage": stage_seconds,
        "failed": [f"{r.stage}[{r.item}]: {r.error}" for r in records if r.status == "failed"],
    }


@hydra.main(version_base=None, config_path="conf", config_name="config")
def main(cfg: DictConfig) -> None:
    base = Path(hydra.utils.get_original_cwd())
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    cache_dir = Path(cfg.run.cache_dir) if Path(cfg.run.cache_dir).is_absolute() else base / cfg.run.cache_dir
    engine = Engine(cache_dir, global_seed=int(cfg.run.seed), workers=int(cfg.run.workers),
                    partial=bool(cfg.run.partial), device=choose_device(cfg.run.device),
                    reseed=reseeded_stages(cfg.run.reseed))
    graph = build_graph(cfg, base)
    targets = graph.targets(cfg.run.until)

    if cfg.run.action == "plan":
        records = engine.plan(targets)
        print(format_table(records))
        (run_dir / "plan.json").write_text(json.dumps([r.__dict__ for r in records], indent=2))
        return
    if cfg.run.action == "gc":
        garbage = engine.garbage(engine.reachable_keys(targets))
        for path in garbage:
            print(("removing " if cfg.run.gc_apply else "unreached ") + str(path))
            if cfg.run.gc_apply:
                shutil.rmtree(path) if path.is_dir() else path.unlink()
        print(f"{len(garbage)} cache entries {'removed' if cfg.run.gc_apply else 'unreached (run.gc_apply=true removes them)'}")
        return
    if cfg.run.action != "run":
        raise ValueError(f"run.action must be run, plan or gc, not {cfg.run.action!r}")

    records = engine.run(targets)
    summary = summarise(records, cfg)
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    print(format_table(records))
    for item, metrics in summary["eval"].items():
        print(f"{item}: box AP {metrics['bbox']['AP']:.1f}  mask AP {metrics['segm']['AP']:.1f}")
    print(f"summary: {run_dir / 'summary.json'}")
    if summary["failed"] and HydraConfig.get().mode != RunMode.MULTIRUN:
        sys.exit(1)


if __name__ == "__main__":
    main()
