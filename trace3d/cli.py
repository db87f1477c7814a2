"""``trace3d <step>``: one subcommand per pipeline step, plus ``trace3d bench <name>`` and ``trace3d describe``.

The steps' flags, help and handlers come from the registry, :mod:`trace3d.steps`.

Thin by design: parse flags, call the library, write outputs atomically (into a temporary sibling
that is renamed at the end).  Errors caused by the input are printed as one sentence and exit 2.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from pathlib import Path

from .errors import Trace3DError
from .steps import BY_COMMAND, STEPS, handler

log = logging.getLogger("trace3d")


# Commands whose inner loop alternates short parallel regions with short serial parts (the lifting's
# fast step: five numba regions in about 2.5 ms): there, waking sleeping workers for every region
# costs about 45 us each, so their workers spin for about half a millisecond before sleeping.
# (The steps' own flag: Step.spin in trace3d.steps.)
SPIN_COMMANDS = {(s.command, None) for s in STEPS if s.spin} | {("bench", "lift"), ("bench", "lift-forms")}
# Commands that run no numba kernel: no compile listener (trace3d.tooling.compiling), so no numba import.
NO_KERNEL_COMMANDS = {s.command for s in STEPS if not s.kernels} | {"describe", "progress", "verify"}


def _entry_point_environment() -> None:
    """Process settings of the ``trace3d`` command, made here rather than on import of the library.

    ``OMP_WAIT_POLICY=PASSIVE``: OpenMP threads that spin while waiting (the GNU default) steal the
    CPU from numba's and torch's workers on a busy machine; sleeping waits halved forward + backward
    wall time on the 2-core box (docs/performance.md).  It takes effect only if set before torch and
    numba load their OpenMP runtime, which the step handlers import lazily, after this call.  An
    explicit value in the environment is respected.  Numba's compile cache is ``NUMBA_CACHE_DIR`` when
    set (the Makefile and the rules point it at the checkout's ``.numba_cache/``), in its subfolder named
    by a hash of the kernels' code and everything they import (:func:`trace3d.tooling.codehash.key_numba_cache`:
    numba itself would load a kernel compiled before a helper in another file changed), else numba's
    default (``__pycache__`` beside the sources).

    ``NUMBA_CPU_FEATURES`` with 512-bit vectors preferred on AVX-512 CPUs (:mod:`trace3d.tooling.cputarget`:
    LLVM's Intel models split the kernels' 16-lane loops into two 256-bit halves otherwise), unless the
    environment names a CPU target already.
    """
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from .tooling.codehash import key_numba_cache
    from .tooling.cputarget import set_wide_vectors

    set_wide_vectors()
    key_numba_cache()


def _command_environment(args: argparse.Namespace) -> None:
    """``GOMP_SPINCOUNT=10000`` for the commands in :data:`SPIN_COMMANDS` only (an explicit value in the
    environment is respected): workers spin about 0.5 ms after a parallel region before they sleep
    (PASSIVE alone: not at all), which took the default room's lift iteration from 3.2 to 2.7 ms
    (docs/lifting.md). The rules give the lift step both cores, so the spinning takes no core from
    another job. Called after parsing, before any handler imports torch or numba."""
    if (args.command, getattr(args, "name", None)) in SPIN_COMMANDS:
        os.environ.setdefault("GOMP_SPINCOUNT", "10000")


# ----------------------------------------------------------------------------------------------
# handlers: the steps' own are trace3d.steps.<command>.run (imported when their command runs, so that
# `trace3d --help` is fast); the benchmarks and the registry's description are here
# ----------------------------------------------------------------------------------------------


OUTPUT_FLAGS = ("out", "objects", "plot")  # a step's arguments that name what it writes
TEXT_FLAGS = ("params", "spec", "label", "view", "point", "patch_params", "kind", "small", "large")


def step_inputs(args: argparse.Namespace) -> list[Path]:
    """The paths a step reads: its arguments' values that name an existing file or folder (its outputs,
    ``--out``, ``--objects`` and ``--plot``, and its text arguments left out)."""
    out = []
    for name, value in vars(args).items():
        if name in OUTPUT_FLAGS or name in TEXT_FLAGS or name in ("command", "func", "verbose", "threads"):
            continue
        for item in value if isinstance(value, list) else [value]:
            if isinstance(item, str) and item and os.path.exists(item):
                out.append(Path(item))
    return out


def _run_step(args: argparse.Namespace) -> None:
    """Run the step ``args.command`` (its handler module's ``run``): its inputs are checked against their
    manifests first, and every folder it writes must be its own (:mod:`trace3d.io`)."""
    from .io import check_file_outputs, step_outputs, verify_inputs

    inputs = step_inputs(args)
    check_file_outputs([v for k in OUTPUT_FLAGS if isinstance(v := getattr(args, k, None), str) and v], inputs)
    verify_inputs(inputs)
    with step_outputs(args.command, inputs, BY_COMMAND[args.command].rules):
        handler(args.command)(args)


def _cmd_verify(args: argparse.Namespace) -> None:
    """``trace3d verify <tree>``: every step output under the tree against its manifest."""
    from .io import verify_tree

    for root in args.paths:
        if not Path(root).exists():
            raise Trace3DError(f"{root}: no such file or folder; give a results folder.")
    folders, problems = [], []
    for root in args.paths:
        found, damaged = verify_tree(root)
        folders += found
        problems += damaged
    for problem in problems:
        print(problem)
    if problems:
        raise Trace3DError(f"{len(problems)} file(s) in {len(folders)} step output(s) differ from their manifests "
                           f"(listed above); rerun the rules named there.")
    print(f"{len(folders)} step output(s) under {', '.join(args.paths)}: every file matches its manifest.")


def _cmd_describe(args: argparse.Namespace) -> None:
    from .tooling.schema import registry_document as describe

    info = describe()
    if args.json:
        print(json.dumps(info, indent=2, sort_keys=False))
        return
    for command, entry in info["steps"].items():
        print(f"{command:22s} {entry['entry'][0] if entry['entry'] else ''}"
              + (f"  (rules: {', '.join(entry['rules'])})" if entry["rules"] else ""))
    print("\nlifting methods and their keys:")
    for method, entry in info["lift_methods"].items():
        print(f"  {method}: {', '.join(entry['keys'])}")
    print("\nvariant defaults: " + json.dumps(info["variant"]["defaults"]))


def _cmd_progress(args: argparse.Namespace) -> None:
    from .progress import progress_text

    print(progress_text(Path(args.results), Path(args.log) if args.log else None))


def _parse_size(text: str) -> tuple[int, int]:
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.isdigit() and int(p) > 0 for p in parts):
        raise Trace3DError(f"bench: --size must look like 160x120, got {text!r}.")
    return int(parts[0]), int(parts[1])


def _cmd_bench(args: argparse.Namespace) -> None:
    if args.name == "render":
        from .bench.render import run_bench

        result = run_bench(quick=args.quick)
    elif args.name == "synthetic":
        from .bench.synthetic import run_bench

        result = run_bench(quick=args.quick)
    elif args.name == "fit":
        from .bench.fit import run_rounds

        sizes = [_parse_size(text) for text in args.size] if args.size else None
        if args.rounds < 1:
            raise Trace3DError(f"bench fit: --rounds must be >= 1, got {args.rounds}.")
        result = run_rounds(args.rounds, quick=args.quick, sizes=sizes, iterations=args.iterations,
                            baseline=Path(args.baseline) if args.baseline else None)
    elif args.name == "fit-sweep":
        from .bench.fit import run_sweep

        if args.merge:
            from .bench.fit import merge_sweeps

            result = merge_sweeps([Path(f) for f in args.merge], Path(args.plot) if args.plot else None)
        else:
            if not args.room_list:
                raise Trace3DError("bench fit-sweep: give at least one --rooms folder (a fitted room's results "
                                   "folder), or --merge earlier sweeps' JSON files.")
            result = run_sweep([Path(r) for r in args.room_list], [int(b) for b in args.budgets],
                               [float(x) for x in args.scales], Path(args.plot) if args.plot else None)
    elif args.name == "trace":
        from .bench.trace import run_bench

        result = run_bench(Path(args.room), quick=args.quick)
    elif args.name == "lift":
        from .bench.lift import run_bench
        from .params import load_params_arg

        result = run_bench(Path(args.room), quick=args.quick, params=load_params_arg(args.params))
    elif args.name == "prompts":
        from .bench.prompts import run_bench

        result = run_bench(Path(args.room), views=4 if args.quick else 16)
    elif args.name == "evaluate":
        from .bench.evaluate import run_bench
        from .params import load_params_arg

        result = run_bench(Path(args.room), variant=args.variant, params=load_params_arg(args.params),
                           repeats=args.rounds)
    elif args.name in ("startup", "forkserver"):  # the same probe, in fresh processes or forks of the server
        from .bench import forkserver, startup

        bench = startup if args.name == "startup" else forkserver
        result = bench.run_bench(rounds=args.rounds, commands=["tables", "evaluate"] if args.quick else None)
    elif args.name == "scheduler":
        from .bench.scheduler import run_bench

        result = run_bench(jobs=60 if args.quick else 200)
    elif args.name == "merge-vote":
        from .bench.merge_vote import run_bench

        result = run_bench([Path(r) for r in (args.room_list or [args.room])])
    elif args.name == "mask-cues":
        from .bench.mask_cues import plot_cues, run_bench

        rooms = [Path(r) for r in (args.room_list or [args.room])]

        def masks_of(room: Path) -> list[Path]:
            try:
                return [room.parent / m.format(room=room.name) for m in (args.masks or [])]
            except (KeyError, IndexError, ValueError) as exc:
                raise Trace3DError(f"bench mask-cues: --masks may name the room as {{room}} and nothing else "
                                   f"({exc!r} in {args.masks}).") from None

        results = [run_bench(room, masks=masks_of(room), stride=args.stride) for room in rooms]
        if args.plot:
            plot_cues(results, Path(args.plot))
        result = results[0] if len(results) == 1 else {"rooms": results}
    elif args.name == "lift-forms":
        from .bench.lift import compare_forms

        result = compare_forms(Path(args.room), iterations=300 if args.quick else 1500)
    else:  # argparse restricts choices; kept for clarity
        raise Trace3DError(f"unknown benchmark {args.name!r}.")
    text = json.dumps(result, indent=2)
    if args.out:
        from .io import atomic_file

        with atomic_file(args.out) as tmp:
            tmp.write_text(text + "\n")
    print(text)


# ----------------------------------------------------------------------------------------------
# parser
# ----------------------------------------------------------------------------------------------


def _parameters_help(command: str) -> str:
    """The parameter list of ``trace3d <command> --help`` (imports the step's parameter dataclasses)."""
    from .tooling.schema import help_text

    return help_text(command)


def build_parser(help_step: str | None = None) -> argparse.ArgumentParser:
    """The ``trace3d`` parser; ``help_step``'s help lists its parameters (imports that step's modules)."""
    parser = argparse.ArgumentParser(
        prog="trace3d",
        description="Trace3D pipeline steps. Each step reads files, writes one output folder atomically.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("--threads", type=int, metavar="N",
                        help="CPU threads for torch, numba, OpenMP and COLMAP (default: all cores)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="STEP")
    if help_step is not None:  # `trace3d <step> --help` lists the step's parameters (trace3d.tooling.schema)
        add_parser = sub.add_parser

        def add_with_parameters(name, **kwargs):
            if name == help_step:
                text = _parameters_help(name)
                if text:
                    kwargs["epilog"] = "--params keys = their defaults (null: the preset's value):\n" + text
                    kwargs["formatter_class"] = argparse.RawDescriptionHelpFormatter
            return add_parser(name, **kwargs)

        sub.add_parser = add_with_parameters

    for step in STEPS:  # the pipeline's steps, from the registry (trace3d.steps)
        p = sub.add_parser(step.command, help=step.help)
        for argument in step.args:
            p.add_argument(*argument.flags, **argument.kwargs)
        p.set_defaults(func=_run_step)

    p = sub.add_parser("bench", help="benchmarks; print one JSON object")
    p.add_argument("name", choices=["render", "synthetic", "trace", "lift", "lift-forms", "fit", "fit-sweep",
                                    "prompts", "evaluate", "startup", "forkserver", "merge-vote",
                                    "scheduler", "mask-cues"])
    p.add_argument("--room", default="results/room0",
                   help="trace, lift: a fitted room's results folder (scene/, poses/, gaussians/, patches/ or "
                        "merge-paper/instances); prompts: a room's results folder or canonical scene with ground "
                        "truth (the prompt sources' answers scored against it, docs/masks.md)")
    p.add_argument("--params", help="lift: the lift step's parameters (JSON/YAML or @file) whose wall time is measured; "
                                    "evaluate: the evaluate step's (default {\"protocol\": \"standard\"})")
    p.add_argument("--variant", default="full", help="evaluate: the variant folder under --room whose lift is evaluated")
    p.add_argument("--quick", action="store_true", help="smaller sizes (smoke run)")
    p.add_argument("--size", action="append", metavar="WxH",
                   help="fit: frame size to measure (repeatable; default 160x120 and 504x378)")
    p.add_argument("--iterations", type=int, help="fit: timed iterations per size (default 200)")
    p.add_argument("--baseline", metavar="CHECKOUT",
                   help="fit: also run this checkout's fit benchmark first (e.g. a git worktree of the previous "
                        "main) and report both side by side")
    p.add_argument("--rounds", type=int, default=1,
                   help="fit: run the benchmark this many times (alternating with --baseline's) and report the "
                        "median round per size, every round's time and, with --baseline, each round pair's "
                        "speedup and their median (default 1); evaluate: evaluations in a row (the first may "
                        "compile kernels); startup, forkserver: fresh processes per step (the median is reported)")
    p.add_argument("--rooms", dest="room_list", nargs="+",
                   help="fit-sweep: rooms' results folders (scene/, poses/); merge-vote: traced synthetic rooms' "
                        "results folders (scene/, patches/, trace-paper/), figures per room and pooled; mask-cues: "
                        "fitted rooms with ground truth")
    p.add_argument("--budgets", nargs="+", default=["20000", "40000", "80000"],
                   help="fit-sweep: Gaussian budgets (max_gaussians)")
    p.add_argument("--scales", nargs="+", default=["0.05", "0.1"],
                   help="fit-sweep: schedule scales (0.1 = 3,000 iterations)")
    p.add_argument("--merge", nargs="+", metavar="JSON",
                   help="fit-sweep: no fitting; merge these earlier sweeps' --out files (rows in order) and plot them")
    p.add_argument("--plot", help="fit-sweep: PNG of test PSNR against minutes; mask-cues: PNG of the cues' AUCs")
    p.add_argument("--masks", action="append", metavar="FOLDER",
                   help="mask-cues: a masks folder to score, relative to the room's parent, {room} standing for the "
                        "room's name (repeatable; e.g. '{room}/masks' '{room}@geometry/masks')")
    p.add_argument("--stride", type=int, default=4, help="mask-cues: every stride-th view (default 4)")
    p.add_argument("--out", help="also write the JSON here")
    p.set_defaults(func=_cmd_bench)

    p = sub.add_parser("progress", help="where a running (or the last) Snakemake run is: jobs done and left per "
                                        "rule, a time estimate, which tables are written (reads .snakemake/log)")
    p.add_argument("results", nargs="?", default="results", help="the results folder (default: results)")
    p.add_argument("--log", help="a Snakemake log (default: the newest in .snakemake/log/ of the current folder)")
    p.set_defaults(func=_cmd_progress)
    p = sub.add_parser("verify", help="check every step output under a folder (results/) against its manifest "
                                      "(.trace3d-step: sizes and SHA-256 of its files)")
    p.add_argument("paths", nargs="+", metavar="PATH", help="results folder(s) or step output folder(s)")
    p.set_defaults(func=_cmd_verify)

    p = sub.add_parser("describe", help="the step registry: steps, their flags and parameters with defaults, "
                                        "the lifting methods' keys, the variant defaults")
    p.add_argument("--json", action="store_true", help="as one JSON object (what the rules and the schema read)")
    p.set_defaults(func=_cmd_describe)
    return parser


def _help_step(argv: list[str]) -> str | None:
    """The step whose ``--help`` is asked for (its parameter list is added to that help only, so that
    other commands do not import the step modules)."""
    if not any(a in ("-h", "--help") for a in argv):
        return None
    steps = [a for a in argv if not a.startswith("-")]
    return steps[0] if steps else None


class _Interrupted(KeyboardInterrupt):
    """SIGTERM (Snakemake stopping a job, ``kill``) raised as an interruption, so that the temporary
    output is removed on the way out as for Ctrl-C."""


def _on_sigterm(signum, frame):  # noqa: ARG001 - signal handler signature
    raise _Interrupted()


def _interrupted(exc: BaseException) -> KeyboardInterrupt | None:
    """The KeyboardInterrupt behind ``exc`` (numba's compiled code reports one as a SystemError)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def main(argv: list[str] | None = None) -> int:
    how = None
    if argv is None and os.environ.get("TRACE3D_FORKSERVER"):  # the command itself, opted in (docs/performance.md)
        from .tooling.forkclient import delegate

        status, how = delegate(sys.argv[1:])
        if status is not None:
            return status
    _entry_point_environment()
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(_help_step(argv))
    args = parser.parse_args(argv)
    _command_environment(args)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    from .io import TempPathFilter
    from .threads import limit_threads

    for handler in logging.getLogger().handlers:
        if not any(isinstance(f, TempPathFilter) for f in handler.filters):
            handler.addFilter(TempPathFilter())
    from .tooling import forkclient

    if how or forkclient.CHILD:
        log.debug("trace3d %s: %s", args.command, forkclient.CHILD or how)
    import signal
    import threading

    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        with limit_threads(args.threads):
            if args.command not in NO_KERNEL_COMMANDS:
                from .tooling.compiling import check_cache_folder, compile_seconds, install

                check_cache_folder()
                install()
            args.func(args)
            if args.command not in NO_KERNEL_COMMANDS and compile_seconds() > 0:
                log.info("compiled kernels for %.1f min (cached for later runs)", compile_seconds() / 60)
    except Trace3DError as exc:
        sentence = " ".join(str(exc).split())  # one line, whatever a wrapped library message held
        print(f"trace3d {args.command}: error: {sentence}", file=sys.stderr)
        return 2
    except OSError as exc:  # disk full, read-only, permission, a path gone: the machine's, not a bug
        from .io import os_error_sentence

        print(f"trace3d {args.command}: error: {os_error_sentence(exc)}", file=sys.stderr)
        return 2
    except BaseException as exc:  # noqa: BLE001 - an interruption is reported in one line, anything else re-raised
        stop = _interrupted(exc)
        if stop is None:
            raise
        # objects torn down half-built by the interruption (a progress bar) would print "Exception ignored"
        # tracebacks on the way out: the one line below is the whole report
        sys.unraisablehook = lambda unraisable: None
        how = "stopped (SIGTERM)" if isinstance(stop, _Interrupted) else "interrupted"
        print(f"trace3d {args.command}: {how}; nothing was written (an earlier output, if any, is unchanged).",
              file=sys.stderr)
        return 143 if isinstance(stop, _Interrupted) else 130
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    return 0


if __name__ == "__main__":
    sys.exit(main())
