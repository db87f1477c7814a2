"""The whole-DAG tests' jobs start from a fork server (trace3d/tooling/forkserver.py, docs/performance.md).

Each of their ``trace3d`` jobs would otherwise import torch and its step and load its kernels again
(2-3 s of CPU a job). The tests of the xdist groups ``whole_dag`` and ``slurm`` (tests/conftest.py) run
with ``TRACE3D_FORKSERVER`` naming a folder of servers: the one ``make test`` started for the run
(``TRACE3D_TEST_FORKSERVER``), else one started for this pytest session (its process; stopped at the end).
``TRACE3D_TEST_FORKSERVER=off`` runs them without one (what the measurements in docs/performance.md compare).
The jobs of a SLURM allocation run in-process whatever the variable says (the server declines them:
their work must stay inside the job), so the SLURM test's cluster jobs run in-process while its local
reference run uses the servers: the two runs' equal files are also the server's equal bytes.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pytest

USING = ("whole_dag", "slurm")


@pytest.fixture(scope="session")
def forkserver_folder():
    """The folder of the servers the whole-DAG tests use (None: off)."""
    given = os.environ.get("TRACE3D_TEST_FORKSERVER")
    if given == "off":
        yield None
        return
    if given:
        yield given
        return
    from trace3d.tooling.forkserver import start, stop

    folder = Path(tempfile.mkdtemp(prefix="trace3d-fork-")) / "servers"  # short: a socket path has 108 bytes
    start(folder, ("1", "1-spin", "2"))
    try:
        yield str(folder)
    finally:
        stop(folder)


@pytest.fixture(autouse=True)
def _whole_dag_forkserver(request, monkeypatch):
    marker = request.node.get_closest_marker("xdist_group")
    name = (marker.args[0] if marker.args else marker.kwargs.get("name")) if marker else None
    if name in USING:
        folder = request.getfixturevalue("forkserver_folder")
        if folder:
            monkeypatch.setenv("TRACE3D_FORKSERVER", folder)
