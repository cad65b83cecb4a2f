"""The `local_slurm_cluster` and `local_slurm_two_nodes` fixtures: throwaway SLURMs for the `cluster` tests
(local_slurm.py)."""
from __future__ import annotations

from typing import Iterator

import pytest

from tests.cluster.local_slurm import LocalSlurm, SlurmUnavailable, ensure_installed, local_slurm


@pytest.fixture(scope="module")
def local_slurm_cluster() -> Iterator[LocalSlurm]:
    """A running one-node SLURM (Debian packages installed when missing; skipped with the reason when they
    cannot be). Stopped whatever the test did: jobs cancelled, daemons ended, folder removed."""
    try:
        ensure_installed()
    except SlurmUnavailable as error:
        pytest.skip(str(error))
    with local_slurm() as cluster:
        yield cluster


@pytest.fixture(scope="module")
def local_slurm_two_nodes() -> Iterator[LocalSlurm]:
    """A running SLURM of two nodes on this machine, each with an equal share of its CPUs (as local_slurm_cluster)."""
    try:
        ensure_installed()
    except SlurmUnavailable as error:
        pytest.skip(str(error))
    with local_slurm(nodes=2) as cluster:
        yield cluster
