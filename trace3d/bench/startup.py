"""``trace3d bench startup``: what every pipeline job pays before its step's first useful line.

Every Snakemake job starts a fresh ``trace3d <step>``. For each step that a rule runs, this starts a
fresh Python (``python -m trace3d.bench.startup --probe <command>``, ``--rounds`` times) that does what
the ``trace3d`` entry point does before the step's own work, and times it from the parent's spawn:

    first_line   the interpreter, the entry point (process settings, the parser, logging, thread limits,
                 numba's compile listener where the step runs kernels), the step's handler module and
                 the modules of the library functions it runs (:attr:`trace3d.steps.Step.entry`): what
                 is loaded when the step's entry function starts, i.e. when it can log its first line
    kernels      then every cached numba kernel of the step's code (its import closure,
                 :func:`trace3d.codehash.step_modules`) at every recorded signature
                 (``kernel_signatures.json``) loaded from ``NUMBA_CACHE_DIR``: an upper bound on the
                 kernels the step calls, which numba loads lazily, at their first call

Wall seconds are from the spawn to the point; CPU seconds are the child's user + system time up to the
point (``time.process_time``, interpreter start included). The median round of each is reported, with
the heavy libraries the first line has loaded (torch, numba, scipy, matplotlib, ...) and the machine's
load average before and after (wall seconds depend on it; CPU seconds much less). A kernel the cache
lacks is compiled (``compiled`` > 0; run ``python -m trace3d.warm`` first).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

HEAVY = ("torch", "numba", "scipy", "matplotlib", "sklearn", "pycolmap", "PIL", "cv2", "skimage", "tqdm",
         "yaml", "numpy")


def pipeline_commands() -> list[str]:
    """The commands a Snakemake rule runs (:data:`trace3d.steps.STEPS` with rules)."""
    from ..steps import STEPS

    return [s.command for s in STEPS if s.rules]


def _first_line(command: str, spawn: float) -> dict:
    """In the child: the entry point's work and the step's imports; seconds since ``spawn``."""
    import importlib
    import logging

    from .. import cli
    from ..steps import step
    from ..threads import limit_threads

    cli._entry_point_environment()
    cli.build_parser()
    cli._command_environment(argparse.Namespace(command=command, name=None, threads=None))
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    s = step(command)
    with limit_threads(None):
        if command not in cli.NO_KERNEL_COMMANDS:
            from ..compiling import install

            install()
        importlib.import_module(s.module)
        for entry in s.entry:
            importlib.import_module(entry.split(":")[0])
    return {"wall_s": time.time() - spawn, "cpu_s": time.process_time(),
            "heavy": sorted(name for name in HEAVY if name in sys.modules)}


def _kernels(command: str) -> dict:
    """In the child, after :func:`_first_line`: every recorded kernel of the step's closure from the cache."""
    from ..steps import step

    counts = {"loaded": 0, "compiled": 0, "failed": 0}
    wall, cpu = time.time(), time.process_time()
    if step(command).kernels:
        from ..codehash import step_modules
        from ..warm import read_manifest, warm_modules

        manifest = read_manifest()
        modules = [m for m in step_modules(command) if m in manifest]
        for row in warm_modules(modules, manifest)["kernels"]:
            state = row[3].split(":")[0]
            counts[state] = counts.get(state, 0) + 1
    return {**counts, "wall_s": time.time() - wall, "cpu_s": time.process_time() - cpu}


def _probe(command: str, spawn: float) -> dict:
    first = _first_line(command, spawn)
    heavy = first.pop("heavy")
    return {"first_line": first, "kernels": _kernels(command), "heavy": heavy}


def _spawn(command: str) -> dict:
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    spawn = time.time()
    proc = subprocess.run([sys.executable, "-m", "trace3d.bench.startup", "--probe", command, "--spawn", repr(spawn)],
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
    from ..cputarget import describe
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="the child of `trace3d bench startup` (not for direct use)")
    parser.add_argument("--probe", required=True)
    parser.add_argument("--spawn", type=float, required=True)
    args = parser.parse_args(argv)
    result = _probe(args.probe, args.spawn)
    sys.stdout.flush()
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
