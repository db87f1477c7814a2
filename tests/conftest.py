"""Process settings for the test run, made here because importing trace3d makes none (see
trace3d/__init__.py): sleeping OpenMP waits (torch's idle workers otherwise spin and steal the cores
numba's kernels need) and numba's compile cache in the checkout, so that only the first run in a
clone compiles.  Both must be set before torch and numba are imported, which happens when pytest
imports the test modules, after this file.  An explicit value in the environment is respected.

`make test` runs the suite on two pytest-xdist workers (``-n 2 --dist loadgroup``): each worker is a
process of its own that runs this file, with its own temporary folders (``tmp_path``); they share the
numba cache, which ``python -m trace3d.tooling.warm`` fills before pytest starts, so that the workers only
load kernels (two processes that save different specializations of one kernel at once can leave
numba's index pointing one of them at the other's machine code: trace3d/tooling/warm.py).  The tests that run
a whole DAG through Snakemake (each with
``--cores 2``, as a user's run; the SLURM test's cluster has 2 CPUs) are in the ``xdist_group``
"whole_dag": one worker runs them one after another while the other runs the rest, so no two of them
compete for the cores and run into their time limits.  The SLURM test (group "slurm") runs the same
room through the cluster, whose jobs run on the node's 2 CPUs while the test's process mostly waits on
the executor's status polls (2-22 s apart): it starts on the other worker, beside the whole-DAG group,
instead of adding its waits to that worker's queue.

Subprocesses that compute (a whole DAG, a fit, a cold compile) run without a time limit of their own:
their wall time on a loaded 2-core machine is several times that on a quiet one (a fresh-clone run
beside other work failed two tests on 600 s and 900 s limits that took 3.5 min together when quiet),
and a limit that fires because the machine is busy says nothing about the code; CI's job limit is
the guard against a hang. Only quick commands (``--help``, a dry run) keep a limit."""

import atexit
import os
import re
import shutil
import socket
import tempfile
from pathlib import Path

import pytest

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("NUMBA_CACHE_DIR", str(Path(__file__).resolve().parent.parent / ".numba_cache"))
# the CPU target the entry points compile for (512-bit vectors on AVX-512 CPUs), so that the tests
# run the code the pipeline runs; imports llvmlite only, not numba
from trace3d.tooling.cputarget import set_wide_vectors  # noqa: E402
# compiled kernels in the cache's subfolder for this code (trace3d.tooling.codehash.key_numba_cache); stdlib only
from trace3d.tooling.codehash import key_numba_cache  # noqa: E402

set_wide_vectors()
key_numba_cache()


def _slurm_controller_down() -> bool:
    """Whether SLURM's client (``scontrol``) is installed but no controller listens where its
    slurm.conf says (or there is no slurm.conf): a connection attempt of at most 0.5 s."""
    if shutil.which("scontrol") is None:
        return False
    conf = Path(os.environ.get("SLURM_CONF", "/etc/slurm/slurm.conf"))
    try:
        text = conf.read_text()
    except OSError:
        return True
    host = re.search(r"^\s*(?:SlurmctldHost|ControlMachine)\s*=\s*([^\s(#]+)(?:\(([^)\s]+)\))?", text, re.M | re.I)
    port = re.search(r"^\s*SlurmctldPort\s*=\s*(\d+)", text, re.M | re.I)
    if host is None:
        return True
    try:
        socket.create_connection((host.group(2) or host.group(1), int(port.group(1)) if port else 6817),
                                 timeout=0.5).close()
    except OSError:
        return True
    return False


# Snakemake loads its SLURM executor plugin (pinned for the cluster profile) at every start, and the plugin
# runs `scontrol show config` to word a help text: with SLURM's client installed but no controller running
# that call waits ~9 s, at each of the suite's ~45 Snakemake runs. Then (and only then: tests/workflow/test_slurm.py
# skips without a controller) an `scontrol` that fails at once goes first on PATH for the test processes.
if _slurm_controller_down():
    _stub = Path(tempfile.mkdtemp(prefix="trace3d-tests-bin-"))
    atexit.register(shutil.rmtree, _stub, True)
    (_stub / "scontrol").write_text("#!/bin/sh\n# tests/conftest.py: no SLURM controller runs here\nexit 1\n")
    (_stub / "scontrol").chmod(0o755)
    os.environ["PATH"] = f"{_stub}{os.pathsep}{os.environ.get('PATH', '')}"


@pytest.fixture
def single_numba_thread():
    """Run a test's numba kernels on one thread (restored afterwards)."""
    import numba

    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    yield
    numba.set_num_threads(threads)


def pytest_collection_modifyitems(config, items):
    """Under pytest-xdist (``make test``), the tests of an ``xdist_group`` (the whole-DAG runs) go first:
    the scheduler hands a group to one worker when it reaches the group's first test, so the longest
    unit starts at once while the other worker takes the short tests, instead of starting halfway
    through the run and finishing alone.  The order is the same in every worker (xdist checks that);
    without xdist nothing changes."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        items.sort(key=_group_rank)


GROUP_ORDER = ("whole_dag", "slurm")  # the scheduler's first unit goes to the first worker, the second to the other


def _group_rank(item) -> int:
    marker = item.get_closest_marker("xdist_group")
    if marker is None:
        return len(GROUP_ORDER) + 1
    name = marker.args[0] if marker.args else marker.kwargs.get("name")
    return GROUP_ORDER.index(name) if name in GROUP_ORDER else len(GROUP_ORDER)
