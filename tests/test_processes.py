"""Workers die with their parent: a run killed with SIGKILL while its workers are busy leaves none behind, for
the engine's pool, compose's pool and the detector's DataLoader workers (stages/lib/processes.py)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

WORKLOADS = textwrap.dedent(
    """
    import os, time
    from pathlib import Path

    import torch

    def mark():
        (Path(os.environ["PID_DIR"]) / str(os.getpid())).touch()

    def busy_stage(ctx):
        mark()
        time.sleep(120)

    def setup():
        return None

    def busy_image(state, index, images_dir):
        mark()
        time.sleep(120)

    class SlowBatches(torch.utils.data.Dataset):
        def __len__(self):
            return 1000

        def __getitem__(self, index):
            mark()
            time.sleep(1.0)
            return index
    """
)

PARENTS = {  # a parent process whose workers are busy when it is killed, and how many workers it starts
    "engine": (textwrap.dedent(
        """
        import workloads
        from stages.engine.graph import Node, Stage
        from stages.engine.scheduler import Engine
        nodes = [Node(Stage("busy", workloads.busy_stage), f"item{k}") for k in range(2)]
        Engine(CACHE, workers=2).run(nodes)
        """), 2),
    "compose": (textwrap.dedent(
        """
        import workloads
        from pathlib import Path
        from stages.lib.composition.dataset import generate
        list(generate(workloads.setup, (), workloads.busy_image, 4, Path(CACHE) / "images", 2))
        """), 2),
    "detector_loader": (textwrap.dedent(
        """
        import time, workloads
        from stages.train_maskrcnn.run import batch_stream
        for batch in batch_stream(workloads.SlowBatches(), range(1000), 1):
            time.sleep(10.0)
        """), 1),
}


def alive(pid: int) -> bool:
    """Whether process `pid` runs (a zombie waiting for its reaper does not)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def wait_until(condition, timeout: float, what: str) -> None:
    deadline = time.time() + timeout
    while not condition():
        assert time.time() < deadline, what
        time.sleep(0.2)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("pool", list(PARENTS))
def test_workers_die_when_their_parent_is_killed(tmp_path, pool):
    source, workers = PARENTS[pool]
    (tmp_path / "workloads.py").write_text(WORKLOADS)
    pid_dir = tmp_path / "pids"
    pid_dir.mkdir()
    script = tmp_path / "parent.py"
    body = textwrap.indent(source, "    ")  # spawned workers import this script: it runs only as __main__
    script.write_text(f"CACHE = {str(tmp_path / 'cache')!r}\nif __name__ == '__main__':\n{body}")
    env = dict(os.environ, PID_DIR=str(pid_dir), PYTHONPATH=f"{tmp_path}{os.pathsep}{ROOT}")
    parent = subprocess.Popen([sys.executable, str(script)], env=env, cwd=tmp_path)
    pids: list[int] = []
    try:
        wait_until(lambda: len(list(pid_dir.iterdir())) >= workers, 120, f"{pool}: workers did not start")
        pids = [int(p.name) for p in pid_dir.iterdir()]
        assert parent.pid not in pids and all(alive(pid) for pid in pids)
        parent.send_signal(signal.SIGKILL)
        parent.wait()
        wait_until(lambda: not any(alive(pid) for pid in pids), 20, f"{pool}: workers outlived their parent")
    finally:
        parent.kill()
        for pid in (pid for pid in pids if alive(pid)):  # the workers this test started, should it fail
            os.kill(pid, signal.SIGKILL)
