"""The Hydra config of a run, composed the way dag.py composes it, and dag.py itself run as a user runs it."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from stages.app.config import register

ROOT = Path(__file__).resolve().parents[2]
CONF = ROOT / "conf"
REAL = ROOT.parent / "shared" / "real"  # real captures beside the repository (absent in a user's clone)


def compose_cfg(overrides: list[str], hydra_config: bool = False):
    """conf/config.yaml with `overrides` (Hydra's override syntax), checked against the schema."""
    register()
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF), version_base=None):
        return compose("config", overrides=overrides, return_hydra_config=hydra_config)


def composition_error(overrides: list[str]) -> str:
    """What Hydra says when it refuses to compose the config with `overrides` (its error and the cause)."""
    try:
        compose_cfg(overrides)
    except Exception as error:  # noqa: BLE001 - Hydra wraps OmegaConf's ValidationError
        return f"{error}\n{error.__cause__}"
    raise AssertionError(f"the config composed with {overrides}")


def run_dag(*overrides: str, cwd: Path, timeout: float = 900) -> tuple[subprocess.CompletedProcess, dict | None]:
    """`python dag.py <overrides>` started in `cwd` (run folder cwd/run); its process and summary.json."""
    command = [sys.executable, str(ROOT / "dag.py"), *overrides, f"hydra.run.dir={cwd}/run"]
    done = subprocess.run(command, cwd=cwd, capture_output=True, text=True, timeout=timeout)
    summary_path = cwd / "run" / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.is_file() else None
    return done, summary
