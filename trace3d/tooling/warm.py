"""Fill numba's compile cache with every cached kernel of the package, split over processes.

``python -m trace3d.tooling.warm [--jobs N]`` compiles (or, where the cache has it already, loads) every
specialization the pipeline and the tests use of every ``cache=True`` numba function of ``trace3d``,
into ``NUMBA_CACHE_DIR`` (in its subfolder for this code, :func:`trace3d.tooling.codehash.key_numba_cache`, as
every entry point does). A cold cache costs minutes of CPU (docs/performance.md): numba compiles a
kernel on its first call, in whichever process first calls it, one kernel after another. Warming first spreads that over
``N`` processes (the kernel modules go to whichever process is free, largest first), and afterwards no
step, job or test compiles anything: ``make test`` and ``make reproduce`` run it before pytest and
Snakemake, and on a cluster one run before submitting the jobs saves every job its compile
(docs/cluster.md).

Which functions: every module of the package whose source defines a numba kernel (the test that
:func:`trace3d.tooling.codehash.kernel_modules` uses) is imported and its module-level numba dispatchers with a
cache are taken. Which argument types: numba compiles one specialization per tuple of argument
types, and those are known only from the calls, so they are recorded, from a cache that a full run of
the suite filled, in ``kernel_signatures.json`` beside this file (``--record``). ``tests/tooling/test_warm.py``
checks that every cached dispatcher has its signatures there (all but the ``inline="always"`` ones,
which numba compiles on their own only when Python calls them directly), that no entry names a kernel
that is gone, that every recorded signature still compiles, each in one process, and that a fresh
process then finds every one of them in the cache. A signature a kernel gains later (a new argument
type) is compiled on its first call as before, correct but not warmed, until it is recorded: what is
not checked is that the recorded types are still the ones the pipeline passes.

Two processes never compile the same function: numba saves a specialization by reading the function's
index file, taking the first data-file number that index does not use and writing both back, so two
processes saving different specializations of one function at once can leave the index pointing one
of them at the other's machine code. A module therefore goes to one process, and a kernel module that
imports another module's recorded function (its compiled code may call it) goes to the same process
as that module; a compile of another process's function is reported (``foreign``).
"""

from __future__ import annotations

import argparse
import ast
import json
import os
import pickle
import sys
import time
from pathlib import Path

from .codehash import PACKAGE, ROOT, kernel_definers

MANIFEST = Path(__file__).resolve().parent / "kernel_signatures.json"


# ----------------------------------------------------------------------------------------------
# which modules and functions (no numba import needed)
# ----------------------------------------------------------------------------------------------

def read_manifest(path: Path = MANIFEST) -> dict[str, dict[str, list[str]]]:
    """module -> function (its module-level name) -> the recorded signatures (numba type reprs)."""
    return json.loads(path.read_text())


def _imported_names(module: str, package: Path = PACKAGE) -> dict[str, set[str]]:
    """module -> names that ``module``'s source imports from it (``from X import a, b``, anywhere)."""
    from .codehash import _resolve, module_file

    path = module_file(module, package)
    out: dict[str, set[str]] = {}
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.ImportFrom):
            base = _resolve(module, node, package)
            out.setdefault(base, set()).update(alias.name for alias in node.names)
    return out


def units(manifest: dict[str, dict[str, list[str]]], package: Path = PACKAGE) -> list[list[str]]:
    """The manifest's modules grouped so that no two processes compile one function: a module that
    imports a name with recorded signatures from another module of the manifest joins its group.
    Largest group first (lines of its recorded functions times their specializations)."""
    parent = {m: m for m in manifest}

    def find(m: str) -> str:
        while parent[m] != m:
            parent[m] = parent[parent[m]]
            m = parent[m]
        return m

    for module in manifest:
        for source, names in _imported_names(module, package).items():
            if source in manifest and source != module and names & set(manifest[source]):
                parent[find(module)] = find(source)
    groups: dict[str, list[str]] = {}
    for module in sorted(manifest):
        groups.setdefault(find(module), []).append(module)

    def weight(group: list[str]) -> int:
        return sum(_source_lines(m, package).get(name, 1) * len(sigs)
                   for m in group for name, sigs in manifest[m].items())

    return sorted(groups.values(), key=weight, reverse=True)


def _source_lines(module: str, package: Path = PACKAGE) -> dict[str, int]:
    """Lines of each function of ``module`` by its module-level name (``f = njit(...)(g)`` counts ``g``'s):
    what :func:`units` orders by, a kernel's lines times its specializations standing for its compile
    time (a rough order: the rasterizer's backward compiles far slower per line than the synthetic ray
    caster; the processes take the next unit as they finish one)."""
    from .codehash import module_file

    tree = ast.parse(module_file(module, package).read_text())
    lines = {n.name: n.end_lineno - n.lineno + 1 for n in tree.body if isinstance(n, ast.FunctionDef)}
    for node in tree.body:
        if (isinstance(node, ast.Assign) and isinstance(node.value, ast.Call) and node.value.args
                and isinstance(node.value.args[0], ast.Name) and node.value.args[0].id in lines):
            for target in node.targets:
                if isinstance(target, ast.Name):
                    lines[target.id] = lines[node.value.args[0].id]
    return lines


# ----------------------------------------------------------------------------------------------
# numba's side (imports numba: call after the entry point's environment is set)
# ----------------------------------------------------------------------------------------------

def cached_dispatchers(module_name: str, inlined: bool = True) -> dict[str, object]:
    """The module-level numba dispatchers of ``module_name`` (defined there) that have an on-disk cache,
    by their module-level name; with ``inlined=False`` without the ``inline="always"`` ones (numba
    inlines those into the kernels that call them, so they are compiled on their own only when Python
    code calls them directly, as a test may)."""
    import importlib

    from numba.core.caching import NullCache
    from numba.core.dispatcher import Dispatcher

    module = importlib.import_module(module_name)
    out = {}
    for name, value in vars(module).items():
        if (isinstance(value, Dispatcher) and getattr(value.py_func, "__module__", None) == module_name
                and not isinstance(value._cache, NullCache)
                and (inlined or value.targetoptions.get("inline") != "always")):
            out[name] = value
    return out


def _types_namespace() -> dict:
    """The names numba's type reprs use, for reading a recorded signature back."""
    from numba.core import types

    class _Literal:  # Literal[int](0) -> types.literal(0)
        def __getitem__(self, kind):
            return types.literal

    names = {name: getattr(types, name) for name in dir(types) if not name.startswith("_")}
    names.update({"bool": types.boolean, "int": int, "float": float, "Literal": _Literal(), "__builtins__": {}})
    return names


def parse_signature(text: str) -> tuple:
    """A recorded signature (the repr of numba's argument-type tuple) as that tuple of types."""
    value = eval(text, _types_namespace())  # noqa: S307 - the package's own file, numba type names only
    return value if isinstance(value, tuple) else (value,)


def _listen() -> list:
    """Record every numba compile in this process from now on: a list of (dispatcher, argument types)."""
    from numba.core import event

    compiled: list = []

    class _Listener(event.Listener):
        def on_start(self, ev):
            compiled.append((ev.data["dispatcher"], tuple(ev.data["args"])))

        def on_end(self, ev):  # noqa: ARG002 - numba's signature
            pass

    event.register("numba:compile", _Listener())
    return compiled


_COMPILED: list | None = None


def warm_modules(modules: list[str], manifest: dict[str, dict[str, list[str]]]) -> dict:
    """Compile or load every recorded signature of ``modules``' cached dispatchers in this process.
    Returns what happened: ``kernels`` [module, name, signature, "compiled" | "loaded" | "failed: ..."],
    ``foreign`` [module, name] of the package's cached functions compiled here that belong to a module not
    in ``modules`` (numba compiles its own library functions in every process; those have no file), the CPU seconds
    of each module (importing it included) and of the whole call (``module_cpu_s``, ``cpu_s``)."""
    global _COMPILED
    if _COMPILED is None:
        _COMPILED = _listen()
    cpu = time.process_time()
    start = len(_COMPILED)
    rows, foreign, seconds = [], [], {}
    for module in modules:
        module_cpu = time.process_time()
        found = cached_dispatchers(module)
        for name, signatures in sorted(manifest.get(module, {}).items()):
            dispatcher = found.get(name)
            for text in signatures:
                if dispatcher is None:
                    rows.append([module, name, text, "failed: no cached numba function of that name"])
                    continue
                sig = parse_signature(text)
                try:
                    dispatcher.compile(sig)
                except Exception as exc:  # noqa: BLE001 - a stale signature is reported, not fatal
                    why = " ".join(str(exc).split())[:300]
                    rows.append([module, name, text, f"failed: {type(exc).__name__}: {why}"])
                    continue
                rows.append([module, name, text, dispatcher, sig])
        seconds[module] = time.process_time() - module_cpu
    # compiled in this call (on its own or as a callee of another kernel), else it came from the cache
    compiled = {(id(d), a) for d, a in _COMPILED[start:]}
    rows = [row if len(row) == 4 else [*row[:3], "compiled" if (id(row[3]), row[4]) in compiled else "loaded"]
            for row in rows]
    from numba.core.caching import NullCache

    for dispatcher, _ in _COMPILED[start:]:  # the package's cached functions only (numba's own have no file)
        owner = dispatcher.py_func.__module__
        if (owner.startswith(ROOT + ".") and owner not in modules and not isinstance(dispatcher._cache, NullCache)
                and [owner, dispatcher.py_func.__name__] not in foreign):
            foreign.append([owner, dispatcher.py_func.__name__])
    return {"kernels": rows, "foreign": foreign, "module_cpu_s": seconds, "cpu_s": time.process_time() - cpu,
            "pid": os.getpid()}


def _warm_unit(args: tuple[list[str], dict]) -> dict:
    return warm_modules(*args)


def warm(jobs: int = 1, manifest: dict | None = None) -> dict:
    """Warm every module of the manifest, over ``jobs`` fresh processes (1: in this process).
    Returns the merged report of :func:`warm_modules` plus ``processes`` (the pool's size) and
    ``children_cpu_s`` (the pool's processes' CPU seconds, their start and imports included)."""
    import resource

    manifest = read_manifest() if manifest is None else manifest
    groups = units(manifest)
    if jobs <= 1:
        report = warm_modules([m for g in groups for m in g], manifest)
        report.update(processes=1, children_cpu_s=0.0)
        return report
    import multiprocessing

    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    context = multiprocessing.get_context("spawn")  # fresh interpreters: numba is set up from the environment
    processes = min(jobs, len(groups))
    with context.Pool(processes) as pool:
        parts = list(pool.imap_unordered(_warm_unit, [(g, manifest) for g in groups], chunksize=1))
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    children = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"kernels": [row for p in parts for row in p["kernels"]],
            "foreign": [f for p in parts for f in p["foreign"]],
            "module_cpu_s": {m: t for p in parts for m, t in p["module_cpu_s"].items()},
            "cpu_s": sum(p["cpu_s"] for p in parts), "processes": processes,
            "children_cpu_s": children}


# ----------------------------------------------------------------------------------------------
# recording the signatures from a filled cache
# ----------------------------------------------------------------------------------------------

def _index_signatures(path: Path) -> tuple[tuple, list[tuple]]:
    """(source stamp, argument-type tuples) of one numba index file (``*.nbi``)."""
    with open(path, "rb") as f:
        pickle.load(f)  # numba's version
        stamp, overloads = pickle.loads(f.read())
    return stamp, [key[0] for key in overloads]


def record(cache: Path, package: Path = PACKAGE) -> dict[str, dict[str, list[str]]]:
    """The signatures that ``cache`` (a keyed folder under ``NUMBA_CACHE_DIR``, filled by a full test
    run of this code) holds for every cached dispatcher of the package. A dispatcher's index file is
    found by its name (numba names the subfolder by the source folder's path, which differs between
    checkouts) and taken only if it was written for a source file of today's size."""
    indexes: dict[str, list[Path]] = {}
    for path in cache.rglob("*.nbi"):
        indexes.setdefault(path.name, []).append(path)
    out: dict[str, dict[str, list[str]]] = {}
    for module in kernel_definers(package):
        for name, dispatcher in cached_dispatchers(module).items():
            cache_file = dispatcher._cache._cache_file
            folder = Path(dispatcher.py_func.__code__.co_filename).parent.name
            size = Path(dispatcher.py_func.__code__.co_filename).stat().st_size
            signatures: list[str] = []
            for path in indexes.get(cache_file._index_name, []):
                if not path.parent.name.startswith(folder + "_"):
                    continue
                stamp, sigs = _index_signatures(path)
                if stamp[1] != size:
                    continue
                for sig in sigs:
                    text = repr(tuple(sig))
                    if repr(parse_signature(text)) != text:
                        raise ValueError(f"{module}.{name}: the signature {text} does not read back")
                    if text not in signatures:
                        signatures.append(text)
            if signatures:
                out.setdefault(module, {})[name] = sorted(signatures)
    return out


# ----------------------------------------------------------------------------------------------
# entry point
# ----------------------------------------------------------------------------------------------

def _jobs(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"--jobs takes a whole number of processes, at least 1, not {text!r}")
    return value


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m trace3d.tooling.warm",
        description="Compile (or load) every cached numba kernel of trace3d into NUMBA_CACHE_DIR "
                    "(its subfolder for this code), split over processes.")
    parser.add_argument("--jobs", type=_jobs, default=1, metavar="N",
                        help="processes to split the kernel modules over (default 1; `make` uses its CORES)")
    parser.add_argument("--json", action="store_true", help="print the whole report as one JSON object")
    parser.add_argument("--record", metavar="CACHE",
                        help="instead: write the signatures that CACHE (a keyed folder under NUMBA_CACHE_DIR that "
                             "a full `make test` filled) holds into trace3d/tooling/kernel_signatures.json")
    args = parser.parse_args(argv)
    from ..cli import _entry_point_environment

    _entry_point_environment()  # before numba is imported: the CPU target and the keyed cache folder
    if args.record:
        cache = Path(args.record)
        if not cache.is_dir():
            print(f"trace3d warm: error: {cache} is not a folder (a keyed subfolder of NUMBA_CACHE_DIR)",
                  file=sys.stderr)
            return 2
        try:
            signatures = record(cache)
        except ValueError as err:  # a signature numba wrote that parse_signature cannot rebuild
            print(f"trace3d warm: error: {err}; teach parse_signature in {Path(__file__).name} its type "
                  "before recording", file=sys.stderr)
            return 2
        if not signatures:
            print(f"trace3d warm: error: {cache} holds no compiled kernel of this code", file=sys.stderr)
            return 2
        MANIFEST.write_text(json.dumps(signatures, indent=1, sort_keys=True) + "\n")
        count = sum(len(s) for m in signatures.values() for s in m.values())
        print(f"recorded {count} signatures of {sum(len(m) for m in signatures.values())} kernels into {MANIFEST}")
        return 0
    where = os.environ.get("NUMBA_CACHE_DIR") or "numba's __pycache__ folders"
    if not args.json:
        print(f"numba kernels: compiling what {where} lacks over {args.jobs} process(es) (an empty cache: "
              "4-5 min of CPU in all; a filled one: seconds)", flush=True)
    start = time.monotonic()
    report = warm(args.jobs)
    wall = time.monotonic() - start
    states = [row[3] for row in report["kernels"]]
    failed = [row for row in report["kernels"] if row[3].startswith("failed")]
    if args.json:
        print(json.dumps({**report, "wall_s": wall, "cache": os.environ.get("NUMBA_CACHE_DIR")}))
    else:
        print(f"numba kernels: {len(states)} specializations, {states.count('compiled')} compiled, "
              f"{states.count('loaded')} already cached ({report['processes']} process(es), {wall:.0f} s)")
    for module, name, text, state in failed:
        print(f"trace3d warm: {module}.{name}{text}: {state} (a stale signature in {MANIFEST.name}: "
              f"`python -m trace3d.tooling.warm --record` after a full test run)", file=sys.stderr)
    for module, name in report["foreign"]:
        print(f"trace3d warm: {module}.{name} was compiled by a process that warmed another module "
              "(two processes may have compiled it at once)", file=sys.stderr)
    return 0  # a stale or shared signature only costs a compile later (tests/tooling/test_warm.py fails on either)


if __name__ == "__main__":
    raise SystemExit(main())
