"""``trace3d bench startup``: what every pipeline job pays before its step's first useful line.

Every Snakemake job starts a fresh ``trace3d <step>``. For each step that a rule runs, this starts a
fresh Python (``python -m trace3d.startup_probe <command>``, ``--rounds`` times) that does what
the ``trace3d`` entry point does before the step's own work, and times it from the parent's spawn:

    first_line   the interpreter, the entry point (process settings, the parser, logging, thread limits,
                 numba's compile listener where the step runs kernels), the step's handler module and
                 the modules of the library functions it runs (:attr:`trace3d.steps.Step.entry`): what
                 is loaded when the step's entry function starts, i.e. when it can log its first line
    kernels      then every cached numba kernel of the step's code (its import closure,
                 :func:`trace3d.tooling.codehash.step_modules`) at every recorded signature
                 (``kernel_signatures.json``) loaded from ``NUMBA_CACHE_DIR``: an upper bound on the
                 kernels the step calls, which numba loads lazily, at their first call

Wall seconds are from the spawn to the point; CPU seconds are the child's user + system time up to the
point (``time.process_time``, interpreter start included). The median round of each is reported, with
the heavy libraries the first line has loaded (torch, numba, scipy, matplotlib, ...) and the machine's
load average before and after (wall seconds depend on it; CPU seconds much less). A kernel the cache
lacks is compiled (``compiled`` > 0; run ``python -m trace3d.tooling.warm`` first).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path


def pipeline_commands() -> list[str]:
    """The commands a Snakemake rule runs (:data:`trace3d.steps.STEPS` with rules)."""
    from ..steps import STEPS

    return [s.command for s in STEPS if s.rules]


def _spawn(command: str) -> dict:
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    spawn = time.time()
    proc = subprocess.run([sys.executable, "-m", "trace3d.startup_probe", command, repr(spawn)],
                          capture_output=True, text=True, env=env, timeout=600)
    if proc.returncode != 0:
        from ..errors import Trace3DError

        raise Trace3DError(f"bench startup: the probe of {command!r} failed (exit {proc.returncode}): "
                           f"{proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else 'no message'}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _median(rounds: list[dict], part: str, key: str) -> float:
    return round(statistics.median(r[part][key] for r in rounds), 3)


def run_bench(rounds: int = 3, commands: list[str] | None = None) -> dict:
    """Probe every pipeline command (or ``commands``) ``rounds`` times; medians per command."""
    from ..tooling.cputarget import describe
    from ..errors import Trace3DError

    known = pipeline_commands()
    commands = list(commands or known)
    unknown = [c for c in commands if c not in known]
    if unknown:
        raise Trace3DError(f"bench startup: {unknown} are not pipeline steps; choose from {', '.join(known)}.")
    if rounds < 1:
        raise Trace3DError(f"bench startup: --rounds must be >= 1, got {rounds}.")
    load_before = os.getloadavg()
    out = {}
    for command in commands:
        runs = [_spawn(command) for _ in range(rounds)]
        out[command] = {
            "first_line": {"wall_s": _median(runs, "first_line", "wall_s"),
                           "cpu_s": _median(runs, "first_line", "cpu_s")},
            "kernels": {"wall_s": _median(runs, "kernels", "wall_s"), "cpu_s": _median(runs, "kernels", "cpu_s"),
                        **{k: runs[-1]["kernels"][k] for k in ("loaded", "compiled", "failed")}},
            "heavy": runs[-1]["heavy"],
            "rounds_cpu_s": [round(r["first_line"]["cpu_s"], 3) for r in runs],
        }
    return {"cpu": describe(), "python": sys.version.split()[0], "rounds": rounds,
            "numba_cache": os.environ.get("NUMBA_CACHE_DIR"), "loadavg_before": load_before,
            "loadavg_after": os.getloadavg(), "commands": out}
