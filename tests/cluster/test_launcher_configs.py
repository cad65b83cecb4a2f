"""The SLURM launcher configs compose and give the sbatch script a user expects: the GPU one asks for GPUs on a
partition. No cluster needed: submitit writes the script it would submit (its executor only asks that an `srun`
be on the PATH: a stand-in that is never run)."""
from __future__ import annotations

import os

import pytest
import submitit
from hydra_plugins.hydra_submitit_launcher.config import BaseQueueConf
from omegaconf import OmegaConf

from tests.factories.configs import compose_cfg


def sbatch_script(launcher, folder) -> str:
    """The sbatch script submitit would submit for these launcher settings (mapped the way the Hydra plugin
    maps them: max_num_timeout to the executor, the shared parameters as they are, the others `slurm_`-prefixed)."""
    params = OmegaConf.to_container(launcher, resolve=True)
    shared = set(OmegaConf.structured(BaseQueueConf).keys())
    executor = submitit.AutoExecutor(folder=folder, cluster="slurm", slurm_max_num_timeout=params["max_num_timeout"])
    executor.update_parameters(**{name if name in shared else f"slurm_{name}": value for name, value in params.items()
                                  if name not in ("_target_", "submitit_folder", "max_num_timeout")})
    return executor._executor._make_submission_file_text("python -m job", "0")


@pytest.fixture(autouse=True)
def srun_on_path(tmp_path, monkeypatch):
    """An `srun` on the PATH (submitit 1.5.4's executor refuses to be built without one; nothing runs it)."""
    folder = tmp_path / "bin"
    folder.mkdir()
    srun = folder / "srun"
    srun.write_text("#!/bin/sh\nexit 1\n")
    srun.chmod(0o755)
    monkeypatch.setenv("PATH", f"{folder}{os.pathsep}{os.environ.get('PATH', '')}")


def test_gpu_launcher_asks_for_gpus_on_a_partition(tmp_path):
    cfg = compose_cfg(["+experiment=ablation", "hydra/launcher=submitit_slurm_gpu"], hydra_config=True)
    launcher = cfg.hydra.launcher
    assert launcher._target_.endswith("SlurmLauncher")
    script = sbatch_script(launcher, tmp_path)
    for line in ("--gpus-per-node=1", "--partition=gpu", "--cpus-per-task=8", "--mem=32GB", "--time=240"):
        assert f"#SBATCH {line}\n" in script, line

    cfg = compose_cfg(["+experiment=ablation", "hydra/launcher=submitit_slurm_gpu", "hydra.launcher.partition=a100",
                       "hydra.launcher.gpus_per_node=2"], hydra_config=True)
    script = sbatch_script(cfg.hydra.launcher, tmp_path)
    assert "#SBATCH --gpus-per-node=2\n" in script and "#SBATCH --partition=a100\n" in script


def test_cpu_launcher_asks_for_no_gpu(tmp_path):
    cfg = compose_cfg(["+experiment=ablation", "hydra/launcher=submitit_slurm_cluster"], hydra_config=True)
    script = sbatch_script(cfg.hydra.launcher, tmp_path)
    assert "#SBATCH --cpus-per-task=8\n" in script and "gpu" not in script and "--partition" not in script
