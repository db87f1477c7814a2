"""The process's CPU thread budget: ``trace3d --threads N`` (Snakemake passes ``{threads}``).

:func:`limit_threads` is called by the CLI's entry point, never on import.  Inside it

* torch's intra-op threads are ``N`` (``torch.set_num_threads``; training lowers them further with
  ``TrainParams.torch_threads``, since its heavy work runs in numba);
* numba's parallel kernels use ``N`` threads (``numba.set_num_threads``; when numba is not imported
  yet, ``NUMBA_NUM_THREADS=N`` also sizes its pool);
* OpenMP / BLAS runtimes not started yet, and child processes, see ``OMP_NUM_THREADS``,
  ``MKL_NUM_THREADS`` and ``OPENBLAS_NUM_THREADS`` = ``N``;
* :func:`thread_limit` returns ``N``, which the library's own thread pools read (pycolmap's
  ``num_threads: -1`` in the ``poses`` step becomes ``N``).

Everything is restored when the block ends, so in-process callers (tests) are unaffected.
"""

from __future__ import annotations

import contextlib
import os
import sys
from typing import Iterator

from .errors import ConfigError

ENV_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")

_limit: int | None = None


def thread_limit() -> int | None:
    """The thread budget set by :func:`limit_threads` (``trace3d --threads``), else None (all cores)."""
    return _limit


def resolve_threads(requested: int) -> int:
    """A library thread-count parameter where -1 means "all": the budget when one is set, else -1."""
    if requested > 0:
        return requested if _limit is None else min(requested, _limit)
    return _limit if _limit is not None else requested


@contextlib.contextmanager
def limit_threads(count: int | None) -> Iterator[None]:
    """Run the block with at most ``count`` CPU threads in torch, numba and OpenMP (None: unchanged)."""
    global _limit
    if count is None:
        yield
        return
    if count < 1:
        raise ConfigError(f"--threads must be >= 1, got {count}.")
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    if count > 4 * cores:  # thousands of OpenMP / numba threads crash the process instead of running
        raise ConfigError(f"--threads {count} is more than 4 x the {cores} cores this process may use; give at most "
                          f"{4 * cores} (usually the number of cores).")
    saved_env = {k: os.environ.get(k) for k in (*ENV_VARS, "NUMBA_NUM_THREADS")}
    saved_limit = _limit
    for key in ENV_VARS:
        os.environ[key] = str(count)
    if "numba" not in sys.modules:
        os.environ["NUMBA_NUM_THREADS"] = str(count)
    import numba
    import torch

    saved_torch, saved_numba = torch.get_num_threads(), numba.get_num_threads()
    torch.set_num_threads(count)
    numba.set_num_threads(min(count, numba.config.NUMBA_NUM_THREADS))
    _limit = count
    try:
        yield
    finally:
        _limit = saved_limit
        torch.set_num_threads(saved_torch)
        numba.set_num_threads(min(saved_numba, numba.config.NUMBA_NUM_THREADS))
        for key, value in saved_env.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


@contextlib.contextmanager
def torch_threads(count: int) -> Iterator[None]:
    """Run the block with ``count`` torch intra-op threads (0: unchanged), restoring the setting after."""
    import torch

    previous = torch.get_num_threads()
    if count > 0 and count != previous:
        torch.set_num_threads(count)
    try:
        yield
    finally:
        if torch.get_num_threads() != previous:
            torch.set_num_threads(previous)
