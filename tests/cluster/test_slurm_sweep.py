"""A sweep on a real SLURM, submitted through Hydra's submitit launcher (hydra/launcher=submitit_slurm_cluster)
to a throwaway one-node cluster this test starts (tests/cluster/local_slurm.py): the smoke DAG, variants
full and no_placement x run.seed 0 and 1, one shared run.cache_dir.

- every job completes; every key of the shared stages (sample .. planes) is computed by exactly one job
  (the jobs' logs, their summaries and the cache's manifests agree); each job's own compose, train_maskrcnn
  and eval ran once;
- the same sweep on Hydra's local joblib launcher, its cache seeded with a copy of the cluster cache's
  shared-stage entries (so it recomputes only each job's compose, train_maskrcnn and eval), gives the
  same keys and the same results: every output file of those nodes byte-identical (images, annotations,
  model weights, predictions), their JSON equal but for timings;
- a job cancelled (scancel) while one of its nodes writes its temporary folder leaves that folder and no
  cache entry; resubmitted, it computes the node again, finishes, and the cache holds no temporary folder
  and no entry without manifest.json.

Run on demand: `python -m pytest -m cluster` (5.5 minutes on 2 cores; installs the Debian packages
slurmctld, slurmd and munge when missing). Its timings are logged: add --log-cli-level=INFO to see them.
"""
from __future__ import annotations

import json
import logging
import shutil
import subprocess
import time
from collections import Counter
from datetime import datetime
from pathlib import Path

import pytest

from stages.engine.cache_entry import MANIFEST
from tests.cluster.local_slurm import LocalSlurm
from tests.cluster.sweeps import SHARED, SWEEP_TIMEOUT_S, Job, dag_command, node_outputs, run_sweep

pytestmark = pytest.mark.cluster
log = logging.getLogger(__name__)

PER_JOB = ("compose", "dataset", "train_maskrcnn", "eval")  # follow the job's variant and seed
SWEEP = ("variant=full,no_placement", "run.seed=0,1")
SLURM = ("hydra/launcher=submitit_slurm_cluster", "hydra.launcher.partition=local", "hydra.launcher.cpus_per_task=1",
         "hydra.launcher.mem_gb=4", "hydra.launcher.timeout_min=30")
LOCAL = ("hydra/launcher=local_two_jobs",)  # two jobs side by side, as the cluster's two CPUs run them
# The cancelled job: another seed, a detector trained long enough for the cancel to land while it trains.
# scancel sends SIGTERM to every process of the job, then SIGKILL after KillWait (5 s here). submitit makes
# the job's main process ignore SIGTERM, but a DataLoader worker dies of it and its stage fails at once (its
# temporary folder removed, the job ending before the SIGKILL): without loader workers (not part of the key)
# the SIGKILL lands mid-stage and leaves the temporary folder a killed job leaves.
CANCELLED = ("variant=full", "run.seed=2", "train_maskrcnn.epochs=10", "train_maskrcnn.loader_workers=0")
CANCELLED_STAGE = "train_maskrcnn"


def cache_entries(cache: Path) -> list[Path]:
    """Every folder in the cache except lock files: finished entries and temporary folders."""
    return [entry for stage in cache.iterdir() if stage.is_dir() for entry in stage.iterdir()
            if not entry.name.endswith(".lock")]


def scheduler_times(cluster: LocalSlurm) -> list[dict[str, datetime]]:
    """Submit, start and end time of every completed job the controller knows (1 s resolution), in start
    order, once none is left in the queue (a job whose result is back may still be completing)."""
    deadline = time.monotonic() + 60
    while cluster.job_ids() and time.monotonic() < deadline:
        time.sleep(0.5)
    out = cluster.client("scontrol", "--oneliner", "show", "job").stdout
    jobs = []
    for line in out.splitlines():
        fields = dict(part.split("=", 1) for part in line.split() if "=" in part)
        if fields.get("JobState") == "COMPLETED":
            jobs.append({name: datetime.fromisoformat(fields[f"{name.capitalize()}Time"])
                         for name in ("submit", "start", "end")} | {"id": fields["JobId"]})
    return sorted(jobs, key=lambda job: job["start"])


def timings(cluster: LocalSlurm, jobs: list[Job], wall: float) -> dict:
    """Seconds per job (scheduler start to end), the scheduler's overhead (from submission, or from the
    end of the job whose CPU it took, to start) and from a job's start to its first log line."""
    sched = scheduler_times(cluster)
    assert len(sched) == len(jobs), f"{len(sched)} completed jobs for {len(jobs)} summaries"
    seconds = [(job["end"] - job["start"]).total_seconds() for job in sched]
    waits = []
    for job in sched:
        freed = [other["end"] for other in sched if other["end"] <= job["start"]]
        ready = max([job["submit"], *freed])
        waits.append((job["start"] - ready).total_seconds())
    first_start = min(job["start"] for job in sched)
    python_start = min(job.first_log_time() for job in jobs)
    return {"sweep_wall_s": round(wall, 1), "jobs": len(sched), "job_s": seconds,
            "scheduler_overhead_s": waits, "start_to_first_log_s": (python_start - first_start).total_seconds()}


def test_sweep_on_slurm_computes_each_shared_key_once_and_matches_the_local_launcher(local_slurm_cluster, tmp_path):
    cluster, cache = local_slurm_cluster, tmp_path / "cache"
    jobs, wall = run_sweep(*SWEEP, *SLURM, sweep_dir=tmp_path / "slurm_sweep", cache=cache, env=cluster.env)
    check_each_shared_key_computed_once(jobs, cache)
    waited = sum(job.log.count("computed by another process") for job in jobs)  # found done after waiting
    measured = timings(cluster, jobs, wall) | {"waited_for_another_job": waited}
    log.info("cluster sweep: %s", json.dumps(measured))
    (tmp_path / "timings.json").write_text(json.dumps(measured, indent=2))
    check_local_launcher_gives_the_same_results(jobs, cache, tmp_path, cluster.env)
    check_cancelled_job_leaves_no_half_output(cluster, cache, tmp_path)


def check_each_shared_key_computed_once(jobs: list[Job], cache: Path) -> None:
    """Every job completed; each shared key was computed by one job (logs, summaries and manifests agree);
    each job's own nodes ran once."""
    assert sorted(job.name for job in jobs) == [("full", 0), ("full", 1), ("no_placement", 0), ("no_placement", 1)]
    for job in jobs:
        variant = job.name[0]
        assert job.summary["failed"] == [], job.folder
        assert set(job.summary["eval"]) == {f"{variant}@test_a", f"{variant}@test_b"}, job.folder
    shared = jobs[0].keys(SHARED)
    assert {stage for stage, _ in shared} == set(SHARED)
    assert all(job.keys(SHARED) == shared for job in jobs)  # reseeding left the shared stages' keys alone
    ran = Counter(node for job in jobs for node in job.ran())
    assert {(stage, key): ran[(stage, key)] for (stage, _), key in shared.items()} == \
        {(stage, key): 1 for (stage, _), key in shared.items()}  # the logs
    statuses = Counter((r["stage"], r["key"], r["status"]) for job in jobs for r in job.summary["outcomes"])
    assert all(statuses[(stage, key, "ran")] == 1 for (stage, _), key in shared.items())  # the summaries
    own = [(stage, key) for job in jobs for (stage, _), key in job.keys(PER_JOB).items()]
    assert len(set(own)) == len(own) and all(ran[node] == 1 for node in own)
    for stage in SHARED:  # the manifests: one finished entry per shared key, nothing else
        keys = {key for (name, _), key in shared.items() if name == stage}
        assert {entry.name for entry in (cache / stage).iterdir() if not entry.name.endswith(".lock")} == keys, stage
        assert all(json.loads((cache / stage / key / MANIFEST).read_text())["key"] == key for key in keys)


def check_local_launcher_gives_the_same_results(jobs: list[Job], cache: Path, tmp_path: Path,
                                                env: dict[str, str]) -> None:
    """The same sweep on the joblib launcher, its cache seeded with the cluster cache's shared-stage entries:
    the same keys, and each job's own nodes give the same files."""
    local_cache = tmp_path / "local_cache"
    for stage in SHARED:
        shutil.copytree(cache / stage, local_cache / stage, ignore=shutil.ignore_patterns("*.lock"))
    local_jobs, wall = run_sweep(*SWEEP, *LOCAL, sweep_dir=tmp_path / "local_sweep", cache=local_cache, env=env)
    log.info("local sweep from the shared entries: %.1f s", wall)
    by_name = {job.name: job for job in jobs}
    assert sorted(by_name) == sorted(job.name for job in local_jobs)
    for job in local_jobs:
        twin = by_name[job.name]
        assert job.summary["failed"] == [] and job.keys(SHARED + PER_JOB) == twin.keys(SHARED + PER_JOB), job.name
        assert {r["status"] for r in job.summary["outcomes"] if r["stage"] in SHARED} == {"cached"}
        assert {r["status"] for r in job.summary["outcomes"] if r["stage"] in PER_JOB} == {"ran"}
        for (stage, _), key in job.keys(PER_JOB).items():  # the same datasets, weights, predictions, metrics
            assert node_outputs(local_cache / stage / key) == node_outputs(cache / stage / key), (job.name, stage)


def check_cancelled_job_leaves_no_half_output(cluster: LocalSlurm, cache: Path, tmp_path: Path) -> None:
    """A job cancelled while it computes a node leaves that node's temporary folder and no entry; submitted
    again it computes the node, finishes, and the cache holds no temporary folder or entry without manifest."""
    cancelled_dir = tmp_path / "cancelled_sweep"
    cancelled_dir.mkdir()
    with open(cancelled_dir / "launcher.out", "w") as out:
        launcher = subprocess.Popen(dag_command(*CANCELLED, *SLURM, sweep_dir=cancelled_dir, cache=cache),
                                    cwd=tmp_path, env=cluster.env, stdout=out, stderr=subprocess.STDOUT)
    try:
        tmp_folder = wait_for_temp_folder(cache / CANCELLED_STAGE, launcher)
        key, owner = tmp_folder.name[1:].split(".tmp-")  # .<key>.tmp-<host>-<pid>
        pid = owner.rsplit("-", 1)[1]
        job_id = slurm_job_of(int(pid))
        cluster.client("scancel", job_id)
        deadline = time.monotonic() + 60
        while (Path(f"/proc/{pid}").exists() or job_id in cluster.job_ids()) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not Path(f"/proc/{pid}").exists() and job_id not in cluster.job_ids(), f"job {job_id} still there"
        assert tmp_folder.is_dir() and not (cache / CANCELLED_STAGE / key).exists()  # killed mid-stage
    finally:  # with no accounting (sacct) here, submitit cannot see the cancel: it would wait for ever
        launcher.terminate()
        launcher.wait(30)
    (resubmitted,), _ = run_sweep(*CANCELLED, *SLURM, sweep_dir=tmp_path / "resubmitted_sweep", cache=cache,
                                  env=cluster.env)
    assert resubmitted.summary["failed"] == [] and (CANCELLED_STAGE, key) in resubmitted.ran()
    assert not tmp_folder.exists()
    assert [entry for entry in cache_entries(cache) if not (entry / MANIFEST).is_file()] == []
    log.info("cancelled job %s while it computed %s %s; the resubmitted job computed it again", job_id,
             CANCELLED_STAGE, key)


def wait_for_temp_folder(stage_dir: Path, launcher: subprocess.Popen, timeout: float = SWEEP_TIMEOUT_S) -> Path:
    """The first temporary folder `.<key>.tmp-<host>-<pid>` a job creates in a stage's cache folder (a node being
    computed)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        found = sorted(stage_dir.glob(".*.tmp-*"))
        if found:
            return found[0]
        assert launcher.poll() is None, "the sweep ended before any node started"
        time.sleep(0.1)
    raise AssertionError(f"no node started in {timeout:.0f} s")


def slurm_job_of(pid: int) -> str:
    """The SLURM job id of a job's process (its environment's SLURM_JOB_ID)."""
    variables = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
    environ = dict(item.split(b"=", 1) for item in variables if b"=" in item)
    return environ[b"SLURM_JOB_ID"].decode()
