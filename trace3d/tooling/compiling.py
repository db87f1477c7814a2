"""The first run's numba compilation, made visible: a notice before it and progress bars that leave it out.

Numba compiles the kernels on their first call and keeps them in ``NUMBA_CACHE_DIR``; a cache hit
fires no compile event, so the first ``numba:compile`` event of a process means the cache is cold.
:func:`install` (called by the CLI) logs one notice when that happens, and counts the seconds spent
compiling; :func:`track` makes a tqdm bar skip those seconds, so that its rate and ETA are the
iterations' own (a bar that counted a 3-minute compile into its first iterations promised hours).
"""

from __future__ import annotations

import logging
import os
import threading
import time
import weakref

log = logging.getLogger("trace3d")

# Minutes a cold cache costs the 2DGS fit (its render, backward and Adam kernels) on the 2-core box:
# almost 3 min before its first iteration (issue 34). Other steps compile a subset of these.
FIRST_RUN_MINUTES = 3

_lock = threading.Lock()
_bars: "weakref.WeakSet" = weakref.WeakSet()
_state = {"installed": False, "announced": False, "depth": 0, "start": 0.0, "seconds": 0.0}


def _on_start() -> None:
    with _lock:
        if _state["depth"] == 0:
            _state["start"] = time.time()  # tqdm's clock
            if not _state["announced"]:
                _state["announced"] = True
                cache = os.environ.get("NUMBA_CACHE_DIR", "numba's __pycache__ folders")
                log.info("compiling kernels (first run only, about %d min; later runs load them from %s)",
                         FIRST_RUN_MINUTES, cache)
        _state["depth"] += 1


def _on_end() -> None:
    with _lock:
        _state["depth"] = max(_state["depth"] - 1, 0)
        if _state["depth"] == 0:
            spent = time.time() - _state["start"]
            _state["seconds"] += spent
            for bar in list(_bars):  # the compile happened inside the bar's current iteration: skip it
                bar.start_t += spent
                bar.last_print_t += spent


def install() -> None:
    """Listen to numba's compile events (once per process)."""
    with _lock:
        if _state["installed"]:
            return
        _state["installed"] = True
    from numba.core import event

    class _CompileListener(event.Listener):
        def on_start(self, ev) -> None:  # noqa: ARG002 - numba's signature
            _on_start()

        def on_end(self, ev) -> None:  # noqa: ARG002
            _on_end()

    event.register("numba:compile", _CompileListener())


def check_cache_folder() -> None:
    """Refuse (one sentence) a ``NUMBA_CACHE_DIR`` this process cannot write: numba would then quietly
    keep its kernels beside the sources (or nowhere) and compile them again in every run, while the
    notice above named the folder as the cache."""
    cache = os.environ.get("NUMBA_CACHE_DIR")
    if not cache:
        return
    import tempfile

    from ..errors import Trace3DError
    from ..io import os_error_sentence

    try:
        os.makedirs(cache, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=cache, prefix=".write-test-"):
            pass
    except OSError as exc:
        if exc.filename is None:
            exc.filename = cache
        reason = os_error_sentence(exc).split("; nothing was written")[0]
        raise Trace3DError(f"NUMBA_CACHE_DIR cannot hold the compiled kernels ({reason}); point NUMBA_CACHE_DIR at a "
                           f"writable folder, or unset it.") from exc


def compile_seconds() -> float:
    """Seconds this process has spent compiling kernels (0 when every kernel came from the cache)."""
    return float(_state["seconds"])


def track(bar):
    """Make the tqdm ``bar``'s rate and ETA leave out the time spent compiling kernels; returns ``bar``."""
    if not getattr(bar, "disable", True):
        _bars.add(bar)
    return bar
