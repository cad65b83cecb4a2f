"""One dataset's shards composed on two nodes of a SLURM cluster (issue 56): a sweep of two jobs that train two
detectors on the same composed dataset (the smoke DAG at 12 images in 6 shards of 2; train_maskrcnn.epochs=1,2),
submitted through Hydra's submitit launcher to a throwaway cluster of two one-CPU nodes on this machine
(tests/cluster/local_slurm.py), one shared run.cache_dir.

- the two jobs run on the two nodes and complete;
- every shard of the dataset is computed once, and the two nodes share the shards out (each job takes the next
  shard no other job holds; both reach compose together, as each waits for the last shared node upstream);
- the dataset that joins the shards equals, file for file, the one a single process on this machine makes from the
  same upstream entries (its card names the test set's folder in the cache, which differs).

Run on demand: `python -m pytest -m cluster tests/cluster/test_slurm_shards.py` (under a minute on 2 cores).
"""
from __future__ import annotations

import json
import logging
import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest

from tests.cluster.local_slurm import LocalSlurm
from tests.cluster.sweeps import JOB, RUNNING, SHARED, node_outputs, run_sweep
from tests.factories.configs import ROOT

pytestmark = pytest.mark.cluster
log = logging.getLogger(__name__)

SHARDS = ("compose.num_images=12", "compose.shard_size=2")  # 6 shards of one dataset
SWEEP = ("train_maskrcnn.epochs=1,2",)  # two jobs, one dataset
SLURM = ("hydra/launcher=submitit_slurm_cluster", "hydra.launcher.partition=local", "hydra.launcher.cpus_per_task=1",
         "hydra.launcher.mem_gb=4", "hydra.launcher.timeout_min=30")


def slurm_jobs_ran(sweep_dir: Path) -> dict[str, list[tuple[str, str]]]:
    """(stage, key) of the nodes each SLURM job computed, by job id (an array task's `<array>_<task>`), from its
    submitit logs."""
    ran = {}
    for folder in sorted((sweep_dir / ".submitit").iterdir()):
        logs = sorted(folder.glob("*_log.*")) if folder.is_dir() else []
        if logs:
            text = "".join(path.read_text(errors="replace") for path in logs)
            ran[folder.name] = [(stage, key) for stage, _, key in RUNNING.findall(text)]
    return ran


def test_a_datasets_shards_are_shared_out_over_two_nodes(local_slurm_two_nodes: LocalSlurm, tmp_path):
    cluster, cache, sweep_dir = local_slurm_two_nodes, tmp_path / "cache", tmp_path / "slurm_sweep"
    jobs, wall = run_sweep(*SHARDS, *SWEEP, *SLURM, sweep_dir=sweep_dir, cache=cache, env=cluster.env)
    assert len(jobs) == 2 and all(job.summary["failed"] == [] for job in jobs)
    ran = slurm_jobs_ran(sweep_dir)
    nodes = {job_id: cluster.job_node(job_id) for job_id in ran}
    assert sorted(nodes.values()) == sorted(cluster.nodes), nodes  # one job on each node

    shards = {key for job in jobs for (stage, _), key in job.keys(("compose",)).items()}
    assert len(shards) == 6 and all(set(job.keys(("compose",)).values()) == shards for job in jobs)
    computed = Counter(key for steps in ran.values() for stage, key in steps if stage == "compose")
    assert computed == Counter({key: 1 for key in shards})  # each shard once, over both jobs
    by_node = {nodes[job_id]: sorted(key for stage, key in steps if stage == "compose")
               for job_id, steps in ran.items()}
    log.info("shards by node: %s (sweep %.0f s)", json.dumps(by_node), wall)
    assert all(by_node.values()), f"one node composed every shard: {by_node}"

    (dataset_key,) = {job.keys(("dataset",))[("dataset", "full")] for job in jobs}
    local_cache = tmp_path / "local_cache"  # one process, from the same upstream entries
    for stage in SHARED:
        shutil.copytree(cache / stage, local_cache / stage, ignore=shutil.ignore_patterns("*.lock"))
    done = subprocess.run([sys.executable, str(ROOT / "dag.py"), *JOB, *SHARDS, "run.until=dataset",
                           f"run.cache_dir={local_cache}", f"hydra.run.dir={tmp_path / 'local_run'}"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert node_outputs(local_cache / "dataset" / dataset_key) == node_outputs(cache / "dataset" / dataset_key)
