"""The CPU target numba compiles the kernels for: 512-bit vectors on AVX-512 CPUs.

The render, loss and glue kernels are written as 16-lane float32 loops (one 16x16 tile row), which is
one AVX-512 register.  For the Intel CPUs that have AVX-512 (Skylake-SP and later Xeons, Ice Lake,
Rocket Lake, Sapphire Rapids, ...) LLVM's CPU models carry the tuning flag ``prefer-256-bit``, so
numba, which compiles for the host's CPU model, splits each such loop into two 256-bit halves.  With
the flag removed (``-prefer-256-bit`` in ``NUMBA_CPU_FEATURES``) the same loops use the 512-bit
registers, and a render's forward + backward and a training iteration get markedly faster on an Intel
Xeon with AVX-512 (``trace3d bench fit``; the figures are in docs/performance.md).  AMD's Zen 4 model
has no such flag, and CPUs without AVX-512 have nothing to widen.

The values do not change: the kernels allow no reassociation (``fastmath={"nsz"}``), so LLVM may
change how many lanes one instruction handles but not the order or rounding of any operation (a test
compares renders and gradients compiled both ways bit for bit).

Like ``OMP_WAIT_POLICY``, this is a process setting that the entry points make (:func:`trace3d.cli.main`,
which every Snakemake rule runs, and ``tests/conftest.py``), never the import of the library: it must be in the
environment before numba creates its code generator, and it applies to every numba function in the
process.  An explicit ``NUMBA_CPU_NAME`` or ``NUMBA_CPU_FEATURES`` is respected, and so is
``NUMBA_ENABLE_AVX=0``.
"""

from __future__ import annotations

import os
import platform
from typing import MutableMapping

WIDEN = "-prefer-256-bit"

# the value this process's entry point put into NUMBA_CPU_FEATURES (None: it set nothing)
_set_here: str | None = None


def _llvm():
    """llvmlite's binding with the native target initialised (None where that fails)."""
    try:
        import llvmlite.binding as ll

        ll.initialize_native_target()
        return ll
    except (ImportError, RuntimeError):
        return None


def host_features():
    """LLVM's feature map of this CPU (a dict with ``flatten()``, the form numba uses), or None where
    LLVM cannot tell."""
    ll = _llvm()
    try:
        return None if ll is None else ll.get_host_cpu_features()
    except RuntimeError:
        return None


def wide_vector_features() -> str | None:
    """``NUMBA_CPU_FEATURES`` for this CPU with 512-bit vectors preferred, or None when the CPU has no
    AVX-512 (nothing to widen) or LLVM cannot read its features."""
    features = host_features()
    if not features or not features.get("avx512f"):
        return None
    return f"{features.flatten()},{WIDEN}"


def set_wide_vectors(environ: MutableMapping[str, str] | None = None) -> str | None:
    """Put :func:`wide_vector_features` into ``NUMBA_CPU_FEATURES`` unless the environment already names
    a CPU target (``NUMBA_CPU_NAME``, ``NUMBA_CPU_FEATURES``) or disables AVX (``NUMBA_ENABLE_AVX=0``).
    Returns the value set, else None.  Call it before numba is imported."""
    global _set_here
    env = os.environ if environ is None else environ
    if "NUMBA_CPU_NAME" in env or "NUMBA_CPU_FEATURES" in env or env.get("NUMBA_ENABLE_AVX", "1").strip() == "0":
        return None
    value = wide_vector_features()
    if value is not None:
        env["NUMBA_CPU_FEATURES"] = value
        if environ is None:
            _set_here = value
    return value


def set_here() -> str | None:
    """The value :func:`set_wide_vectors` put into this process's environment (None if it set none)."""
    return _set_here


def describe() -> dict:
    """What the benchmarks record about the CPU: its model name, LLVM's name for it, whether it has
    AVX-512 and whether numba's kernels prefer 512-bit vectors in this process."""
    model = platform.processor() or None
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    model = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    import numba

    ll = _llvm()
    llvm_name = os.environ.get("NUMBA_CPU_NAME") or (None if ll is None else ll.get_host_cpu_name())
    avx512 = bool((host_features() or {}).get("avx512f"))
    in_use = numba.config.CPU_FEATURES or ""  # what numba's code generator reads
    return {"model": model, "llvm_cpu": llvm_name, "avx512": avx512,
            "prefer_512_bit": avx512 and WIDEN in in_use.split(",")}
