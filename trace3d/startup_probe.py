"""The child process of ``trace3d bench startup`` (:mod:`trace3d.bench.startup`): one pipeline step's work
before its first line, then its kernels, timed; prints one JSON line.

    python -m trace3d.startup_probe <command> <spawn time> [--server]

With ``--server`` the probe runs in a fork of the fork server (:mod:`trace3d.tooling.forkserver`,
``trace3d bench forkserver``): what the entry point does before the step's first line, in the child.

Outside :mod:`trace3d.bench` because it runs the ``trace3d`` entry point's own functions (:mod:`trace3d.cli`),
which imports the benchmarks; no step imports this module.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

HEAVY = ("torch", "numba", "scipy", "matplotlib", "sklearn", "pycolmap", "PIL", "cv2", "skimage", "tqdm",
         "yaml", "numpy")


def _first_line(command: str, spawn: float) -> dict:
    """In the child: the entry point's work and the step's imports; seconds since ``spawn``."""
    import importlib
    import logging

    from . import cli
    from .steps import step
    from .threads import limit_threads

    cli._entry_point_environment()
    cli.build_parser()
    cli._command_environment(argparse.Namespace(command=command, name=None, threads=None))
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    s = step(command)
    with limit_threads(None):
        if command not in cli.NO_KERNEL_COMMANDS:
            from .tooling.compiling import install

            install()
        importlib.import_module(s.module)
        for entry in s.entry:
            importlib.import_module(entry.split(":")[0])
    return {"wall_s": time.time() - spawn, "cpu_s": time.process_time(),
            "heavy": sorted(name for name in HEAVY if name in sys.modules)}


def _kernels(command: str) -> dict:
    """In the child, after :func:`_first_line`: every recorded kernel of the step's closure from the cache."""
    from .steps import step

    counts = {"loaded": 0, "compiled": 0, "failed": 0}
    wall, cpu = time.time(), time.process_time()
    if step(command).kernels:
        from .tooling.codehash import step_modules
        from .tooling.warm import read_manifest, warm_modules

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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="the child of `trace3d bench startup` (not for direct use)")
    parser.add_argument("command")
    parser.add_argument("spawn", type=float, help="the parent's time.time() just before it started this process")
    parser.add_argument("--server", action="store_true",
                        help="run the probe in a fork of the fork server of key `default` (TRACE3D_FORKSERVER)")
    args = parser.parse_args(argv)
    if args.server:
        from .tooling.forkclient import delegate

        status, how = delegate([args.command, repr(args.spawn)], entry="probe", key="default")
        if status is None:
            print(f"startup_probe: {how}", file=sys.stderr)
            return 1
        return status
    from .tooling import forkclient

    result = {**_probe(args.command, args.spawn), "forked": forkclient.CHILD is not None}
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
