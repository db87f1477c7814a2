"""Process settings for the test run, made here because importing trace3d makes none (see
trace3d/__init__.py): sleeping OpenMP waits (torch's idle workers otherwise spin and steal the cores
numba's kernels need) and numba's compile cache in the checkout, so that only the first run in a
clone compiles.  Both must be set before torch and numba are imported, which happens when pytest
imports the test modules, after this file.  An explicit value in the environment is respected."""

import os
from pathlib import Path

import pytest

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("NUMBA_CACHE_DIR", str(Path(__file__).resolve().parent.parent / ".numba_cache"))
# the CPU target the entry points compile for (512-bit vectors on AVX-512 CPUs), so that the tests
# run the code the pipeline runs; imports llvmlite only, not numba
from trace3d.cputarget import set_wide_vectors  # noqa: E402
# compiled kernels in the cache's subfolder for this code (trace3d.codehash.key_numba_cache); stdlib only
from trace3d.codehash import key_numba_cache  # noqa: E402

set_wide_vectors()
key_numba_cache()


@pytest.fixture
def single_numba_thread():
    """Run a test's numba kernels on one thread (restored afterwards)."""
    import numba

    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    yield
    numba.set_num_threads(threads)
