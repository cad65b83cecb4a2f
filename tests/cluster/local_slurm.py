"""A throwaway SLURM on this machine: munged, slurmctld and slurmd started in the foreground as children of this
process, with every key, socket, config, state, spool and log file in one temporary folder.

    with local_slurm() as cluster:                   # or the `local_slurm_cluster` fixture (tests/cluster/)
        subprocess.run(["sbatch", ...], env=cluster.env)   # clients find the cluster through SLURM_CONF

One node by default: this machine under its own name. `local_slurm(nodes=2)` makes this machine several nodes
(n1, n2, ...), each its own slurmd (`slurmd -N`) on its own port with the machine's CPUs and memory shared out,
so that jobs land on different nodes as on a cluster (they share this machine's file system, as a cluster's
nodes share theirs).

On exit every job is cancelled, each daemon is ended by its pid (SIGTERM, then SIGKILL), any process still
carrying this cluster's SLURM_CONF in its environment (a job step's slurmstepd or its tasks) is killed by
pid, and the folder is removed. The daemons also die with the thread that started them (PR_SET_PDEATHSIG).
Nothing global is written; only the Debian packages themselves (installed by `ensure_installed` if missing:
slurmctld, slurmd, munge; their install leaves /etc/munge/munge.key, unused here) are.

Manual use: `python -m tests.cluster.local_slurm [NODES]` starts one, prints the SLURM_CONF to export, and stops
it on Enter or Ctrl-C.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

from stages.lib.processes import die_with_parent

PACKAGES = ("slurmctld", "slurmd", "munge")
PROGRAMS = ("slurmctld", "slurmd", "munged", "sbatch", "srun", "squeue", "sinfo", "scancel", "scontrol")
PARTITION = "local"
PR_SET_CHILD_SUBREAPER = 36  # linux/prctl.h
START_TIMEOUT_S = 60.0
STOP_TIMEOUT_S = 20.0


class SlurmUnavailable(RuntimeError):
    """The SLURM programs are missing and cannot be installed here (the message says why); tests skip."""


class SlurmStartError(RuntimeError):
    """A daemon exited or the node did not come up (the message holds the daemons' log tails)."""


@dataclass
class LocalSlurm:
    """A running cluster: its folder, slurm.conf, the environment its clients need, its nodes, its daemons."""

    folder: Path
    conf: Path
    env: dict[str, str]  # os.environ + SLURM_CONF: pass it to every client command and to the submitter
    nodes: list[str]
    cpus: int  # per node
    daemons: dict[str, subprocess.Popen] = field(default_factory=dict)  # munged, slurmctld, slurmd@<node>

    def client(self, *command: str, check: bool = True, timeout: float = 60) -> subprocess.CompletedProcess:
        """A SLURM client command (sinfo, squeue, scancel, scontrol, ...) against this cluster."""
        return subprocess.run(command, env=self.env, capture_output=True, text=True, check=check, timeout=timeout)

    def job_ids(self) -> list[str]:
        """The ids of the jobs the controller still has pending or running (an array task's own id)."""
        out = self.client("squeue", "--noheader", "--array", "--format=%A").stdout
        return [line.strip() for line in out.splitlines() if line.strip()]

    def node_state(self) -> str:
        """The nodes' state ("idle" when every node is idle; sinfo folds equal states into one line)."""
        return self.client("sinfo", "--noheader", "--format=%T", check=False).stdout.strip()

    def job_node(self, job_id: str) -> str:
        """The node a job ran on (its NodeList; jobs here take one node)."""
        out = self.client("scontrol", "--oneliner", "show", "job", job_id).stdout
        return dict(part.split("=", 1) for part in out.split() if "=" in part)["NodeList"]

    def log_tails(self, lines: int = 15) -> str:
        """The last lines of each daemon's log, for an error message."""
        parts = []
        for log in sorted((self.folder / "log").iterdir()):
            tail = log.read_text(errors="replace").splitlines()[-lines:]
            parts.append(f"--- {log.name}\n" + "\n".join(tail))
        return "\n".join(parts)


def missing_programs() -> list[str]:
    return [name for name in PROGRAMS if shutil.which(name) is None]


def ensure_installed() -> None:
    """Install the Debian packages when a program is missing (as root, with apt); SlurmUnavailable if that
    cannot be done. Services are not started by the install: a policy-rc.d denying starts is put in place
    for the install when the machine has none, and removed after."""
    if not sys.platform.startswith("linux"):
        raise SlurmUnavailable("a local SLURM needs Linux")
    if not missing_programs():
        return
    if os.geteuid() != 0 or shutil.which("apt-get") is None:
        raise SlurmUnavailable(f"{', '.join(missing_programs())} missing and cannot be installed here "
                               f"(needs root and apt-get: apt-get install -y {' '.join(PACKAGES)})")
    policy = Path("/usr/sbin/policy-rc.d")
    own_policy = not policy.exists()
    if own_policy:
        policy.write_text("#!/bin/sh\n# written by tests/cluster/local_slurm.py for one apt-get install\nexit 101\n")
        policy.chmod(0o755)
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    try:
        for command in (["apt-get", "update", "-qq"], ["apt-get", "install", "-y", "-qq", *PACKAGES]):
            done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=600)
            if done.returncode != 0:
                raise SlurmUnavailable(f"`{' '.join(command)}` failed: {done.stderr.strip()[-500:]}")
    finally:
        if own_policy:
            policy.unlink()
    if missing_programs():
        raise SlurmUnavailable(f"installed {' '.join(PACKAGES)} but {', '.join(missing_programs())} still missing")


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def node_line() -> tuple[str, int]:
    """This machine as a SLURM node (`slurmd -C`: its name, CPUs, sockets, cores, memory) and its CPU count."""
    done = subprocess.run(["slurmd", "-C"], capture_output=True, text=True, check=True)
    line = done.stdout.splitlines()[0]
    fields = dict(part.split("=", 1) for part in line.split())
    return line, int(fields["CPUs"])


def write_config(folder: Path, nodes: int = 1) -> tuple[Path, list[str], int]:
    """slurm.conf for one partition of `nodes` nodes on this machine (127.0.0.1), everything under `folder`;
    processes tracked by /proc (no cgroups), no accounting. One node is this machine as `slurmd -C` describes it;
    several are n1, n2, ..., each with its own slurmd port, spool, pid and log file and an equal share of the CPUs
    (at least one) and memory. Returns (path, node names, CPUs per node)."""
    line, cpus = node_line()
    machine = line.split()[0].split("=", 1)[1]
    settings = {
        "ClusterName": "localslurm",
        "SlurmctldHost": f"{machine}(127.0.0.1)",
        "SlurmctldPort": _free_port(),
        "SlurmdPort": _free_port(),
        "SlurmUser": "root",
        "SlurmdUser": "root",
        "AuthType": "auth/munge",
        "CredType": "cred/munge",
        "AuthInfo": f"socket={folder / 'munge' / 'munge.socket'}",
        "StateSaveLocation": folder / "state",
        "SlurmdSpoolDir": folder / "spool" / "%n",
        "SlurmctldPidFile": folder / "slurmctld.pid",
        "SlurmdPidFile": folder / "slurmd-%n.pid",
        "SlurmctldLogFile": folder / "log" / "slurmctld.log",
        "SlurmdLogFile": folder / "log" / "slurmd-%n.log",
        "PlugStackConfig": folder / "plugstack.conf",
        "ProctrackType": "proctrack/linuxproc",
        "TaskPlugin": "task/none",
        "JobAcctGatherType": "jobacct_gather/none",
        "AccountingStorageType": "accounting_storage/none",
        "SelectType": "select/cons_tres",
        "SelectTypeParameters": "CR_CPU",  # jobs share a node by CPU (one-CPU jobs run side by side)
        "MpiDefault": "none",
        "ReturnToService": 2,
        "KillWait": 5,  # seconds from a cancel's SIGTERM to SIGKILL
        "MinJobAge": 3600,  # finished jobs stay visible to scontrol (their submit, start and end times)
    }
    text = "".join(f"{name}={value}\n" for name, value in settings.items())
    if nodes == 1:
        names, per_node = [machine], cpus
        text += f"{line} NodeAddr=127.0.0.1 State=UNKNOWN\n"
    else:
        names, per_node = [f"n{i + 1}" for i in range(nodes)], max(1, cpus // nodes)
        memory = int(dict(part.split("=", 1) for part in line.split())["RealMemory"]) // nodes
        for name in names:
            text += (f"NodeName={name} NodeHostname={machine} NodeAddr=127.0.0.1 Port={_free_port()} "
                     f"CPUs={per_node} RealMemory={memory} State=UNKNOWN\n")
    for name in names:
        (folder / "spool" / name).mkdir(mode=0o700)
    text += f"PartitionName={PARTITION} Nodes={','.join(names)} Default=YES MaxTime=INFINITE State=UP\n"
    (folder / "plugstack.conf").write_text("")
    conf = folder / "slurm.conf"
    conf.write_text(text)
    return conf, names, per_node


def _start(name: str, command: list[str], folder: Path, env: dict[str, str]) -> subprocess.Popen:
    """A daemon in the foreground, its output in log/<name>.out, killed if this thread ends."""
    out = open(folder / "log" / f"{name}.out", "w")
    try:
        return subprocess.Popen(command, stdout=out, stderr=subprocess.STDOUT, env=env, cwd=folder,
                                preexec_fn=die_with_parent, start_new_session=True)
    finally:
        out.close()


def _wait_for(what: str, ready, cluster: LocalSlurm, timeout: float = START_TIMEOUT_S) -> None:
    deadline = time.monotonic() + timeout
    while not ready():
        dead = [name for name, process in cluster.daemons.items() if process.poll() is not None]
        if dead or time.monotonic() > deadline:
            why = f"{', '.join(dead)} exited" if dead else f"not after {timeout:.0f} s"
            raise SlurmStartError(f"local SLURM: {what}: {why}\n{cluster.log_tails()}")
        time.sleep(0.2)


def _end(process: subprocess.Popen) -> None:
    """SIGTERM the daemon by its pid, SIGKILL it if it is still there after STOP_TIMEOUT_S."""
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def adopt_orphans(on: bool) -> None:
    """Make this process the reaper of its orphaned descendants (prctl PR_SET_CHILD_SUBREAPER): slurmd
    starts each job step's slurmstepd as an orphan, and this machine's init does not reap them, so ended
    steps would stay as zombies."""
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    if libc.prctl(PR_SET_CHILD_SUBREAPER, int(on), 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_CHILD_SUBREAPER) failed")


def _stat(pid: int) -> tuple[str, str, int]:
    """(command name, state letter, parent pid) of a process, from /proc/<pid>/stat."""
    text = Path(f"/proc/{pid}/stat").read_text()
    name = text[text.index("(") + 1:text.rindex(")")]
    state, ppid = text[text.rindex(")") + 2:].split()[:2]
    return name, state, int(ppid)


def ended_children() -> list[int]:
    """Pids of this process's children that ended and wait to be reaped (zombies): job steps and job
    processes it adopted, and any child nobody waited for."""
    found = []
    for entry in Path("/proc").iterdir():
        try:
            if entry.name.isdigit() and _stat(int(entry.name))[1:] == ("Z", os.getpid()):
                found.append(int(entry.name))
        except (OSError, ValueError):
            continue
    return found


def _running(pid: int) -> bool:
    try:
        return _stat(pid)[1] != "Z"
    except (OSError, ValueError):
        return False


def reap_until_ended(pids: list[int], timeout: float = STOP_TIMEOUT_S) -> None:
    """Wait up to `timeout` until none of `pids` runs, reaping every ended child of this process meanwhile
    (once more after a last pause, for the processes that were still being handed over to it)."""
    deadline = time.monotonic() + timeout
    while True:
        for pid in ended_children():
            os.waitpid(pid, 0)
        if not any(_running(pid) for pid in pids) or time.monotonic() > deadline:
            break
        time.sleep(0.1)
    time.sleep(0.5)
    for pid in ended_children():
        os.waitpid(pid, 0)


def processes_of(conf: Path) -> list[int]:
    """Pids of the processes whose environment names this cluster's slurm.conf (daemons, job steps, job
    tasks, submitters), except this process and its ancestors."""
    marker = f"SLURM_CONF={conf}".encode()
    spared, pid = set(), os.getpid()
    while pid > 1:
        spared.add(pid)
        try:
            pid = _stat(pid)[2]
        except (OSError, ValueError):
            break
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) in spared:
            continue
        try:
            if marker in (entry / "environ").read_bytes().split(b"\0"):
                found.append(int(entry.name))
        except OSError:  # gone, or not ours to read
            continue
    return found


def stop(cluster: LocalSlurm) -> list[int]:
    """Cancel every job, end the daemons by pid, kill what still carries this cluster's SLURM_CONF, and
    reap the ended children of this process. Returns the pids of the leftovers that had to be killed."""
    slurmds = [name for name in cluster.daemons if name.startswith("slurmd@")]
    if "slurmctld" in cluster.daemons and slurmds:
        try:
            cluster.client("scancel", f"--partition={PARTITION}", check=False, timeout=20)
            deadline = time.monotonic() + 30
            while cluster.job_ids() and time.monotonic() < deadline:
                time.sleep(0.5)
        except (subprocess.SubprocessError, OSError):
            pass  # the controller is not answering: its jobs' processes are killed below
    for name in (*slurmds, "slurmctld", "munged"):
        if name in cluster.daemons:
            _end(cluster.daemons[name])
    leftovers = processes_of(cluster.conf)
    for pid in leftovers:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    reap_until_ended(leftovers)
    return leftovers


@contextmanager
def local_slurm(keep: bool = False, nodes: int = 1) -> Iterator[LocalSlurm]:
    """A running local SLURM of `nodes` nodes (installing the Debian packages first when missing); on exit,
    whatever happened inside, its jobs are cancelled, its daemons ended and its folder removed (kept
    when `keep`)."""
    ensure_installed()
    folder = Path(tempfile.mkdtemp(prefix="local-slurm-"))
    for sub in ("state", "spool", "log"):
        (folder / sub).mkdir(mode=0o700)
    (folder / "munge").mkdir()
    (folder / "munge").chmod(0o755)  # munged wants its socket's folder searchable by every user
    folder.chmod(0o755)
    conf, names, cpus = write_config(folder, nodes)
    cluster = LocalSlurm(folder, conf, {**os.environ, "SLURM_CONF": str(conf)}, names, cpus)
    adopt_orphans(True)
    try:
        munge_key = folder / "munge" / "munge.key"
        munge_key.touch(mode=0o600)
        munge_key.write_bytes(os.urandom(1024))
        munge_socket = folder / "munge" / "munge.socket"
        cluster.daemons["munged"] = _start("munged", [
            "munged", "--foreground", f"--key-file={munge_key}", f"--socket={munge_socket}",
            f"--pid-file={folder / 'munge' / 'munged.pid'}", f"--log-file={folder / 'log' / 'munged.log'}",
            f"--seed-file={folder / 'munge' / 'munged.seed'}"], folder, cluster.env)
        _wait_for("munged's socket", munge_socket.exists, cluster)
        cluster.daemons["slurmctld"] = _start("slurmctld", ["slurmctld", "-D", "-f", str(conf)], folder,
                                              cluster.env)
        for name in names:
            cluster.daemons[f"slurmd@{name}"] = _start(f"slurmd@{name}", ["slurmd", "-D", "-N", name, "-f", str(conf)],
                                                       folder, cluster.env)
        _wait_for("nodes idle", lambda: cluster.node_state() == "idle", cluster)
        yield cluster
    finally:
        stop(cluster)
        adopt_orphans(False)
        if not keep:
            shutil.rmtree(folder, ignore_errors=True)


def main() -> None:
    with local_slurm(nodes=int(sys.argv[1]) if len(sys.argv) > 1 else 1) as cluster:
        print(f"SLURM up: nodes {', '.join(cluster.nodes)} ({cluster.cpus} CPUs each), partition {PARTITION}\n"
              f"  export SLURM_CONF={cluster.conf}\n  sinfo; srun -N1 hostname\n"
              f"daemon logs in {cluster.folder / 'log'}; press Enter (or Ctrl-C) to stop and remove it")
        try:
            input()
        except (KeyboardInterrupt, EOFError):
            pass
    print("stopped; folder removed")


if __name__ == "__main__":
    main()
