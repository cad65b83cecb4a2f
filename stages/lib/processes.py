"""Worker processes that die with their parent: a killed run (kill -9, an out-of-memory kill, a cancelled
SLURM job) leaves no worker behind, busy or idle.

Linux only delivers the signal: `die_with_parent` asks the kernel (prctl PR_SET_PDEATHSIG) to SIGKILL this
process when the thread that started it ends. Pools are started from the thread that submits work, which
lives as long as the pool, so that thread's end is the parent's end. On other systems it does nothing.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import multiprocessing
import os
import signal
import sys
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from typing import Any, Callable

PR_SET_PDEATHSIG = 1  # linux/prctl.h


def die_with_parent() -> None:
    """SIGKILL this process when its parent dies (Linux); exit at once if the parent is already gone."""
    if not sys.platform.startswith("linux"):
        return
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    if libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
    parent = multiprocessing.parent_process()
    if parent is not None and os.getppid() != parent.pid:  # the parent died before prctl took effect
        os._exit(1)


def _start_worker(initializer: Callable[..., Any] | None, initargs: tuple) -> None:
    die_with_parent()
    if initializer is not None:
        initializer(*initargs)


def spawn_pool(workers: int, initializer: Callable[..., Any] | None = None, initargs: tuple = ()) -> ProcessPoolExecutor:
    """A pool of `workers` spawned processes (spawn, not fork: a forked child of a process that ran OpenMP
    can hang) that die with this process; `initializer(*initargs)` runs once in each."""
    standard_start_method()
    return ProcessPoolExecutor(workers, mp_context=get_context("spawn"), initializer=_start_worker,
                               initargs=(initializer, initargs))


def standard_start_method() -> None:
    """Make this process's start method one of the standard library's (spawn if it is another).

    A spawned child restores its parent's start method first: inside a joblib (loky) sweep worker that
    is "loky", which the child cannot restore, and every child would die at start.
    """
    if multiprocessing.get_start_method(allow_none=True) not in (None, *multiprocessing.get_all_start_methods()):
        multiprocessing.set_start_method("spawn", force=True)
