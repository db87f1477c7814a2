"""Each step's code version, derived from the import graph: the hash the Snakemake rules rerun a step on.

A step runs its handler module (``trace3d.steps.<command>``, :mod:`trace3d.steps`) and what that imports,
plus the runner every command goes through (:mod:`trace3d.cli`: process settings, thread limits, the
compile listener, atomic writing). Both are read statically with :mod:`ast` (no module is imported, so
the Snakemake process loads neither torch nor numba): every ``import``/``from ... import`` anywhere in a
file (inside functions too), relative imports resolved, each package's ``__init__`` on the way to a
module included, and ``from package import name`` followed into ``package/name.py`` where that is a
module. Two forms of import by name count too: a string constant that is a module's full name
(``"trace3d.lifting.query"``, for ``importlib.import_module``), and a function that lists a package's
modules with ``pkgutil.iter_modules``/``walk_packages`` imports every module of the packages it
imports. The step's hash is over the files of that closure (path and bytes).

Two edges are cut on purpose: the step modules are loaded by name (``importlib``) from the registry, so
the runner's closure holds no step; and in ``cli.py`` the imports of the benchmark handler and of the
``--help`` parameter listing (which imports every step's dataclasses) are not followed
(:data:`NOT_RUN_BY_STEPS`), since no step runs them. An import by a name computed some other way
would not be seen: the library makes none (``tests/cli/test_steps.py`` checks the closures against what
the steps load when run).
"""

from __future__ import annotations

import ast
import functools
import hashlib
import json
import os
import re
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent  # trace3d/
ROOT = "trace3d"
RUNNER = "trace3d.cli"
# Functions of cli.py whose imports no step runs: the benchmarks, the registry's description, the run's progress and the
# `--help` parameter listing.
NOT_RUN_BY_STEPS = ("_cmd_bench", "_cmd_describe", "_cmd_progress", "_parameters_help")


def module_file(module: str, package: Path = PACKAGE) -> Path | None:
    """The file of ``module`` (``trace3d.a.b``) under ``package``; None if there is none."""
    rel = Path(*module.split(".")[1:]) if "." in module else Path()
    base = package / rel
    if (base / "__init__.py").is_file():
        return base / "__init__.py"
    if base.with_suffix(".py").is_file():
        return base.with_suffix(".py")
    return None


def _is_package(module: str, package: Path) -> bool:
    f = module_file(module, package)
    return f is not None and f.name == "__init__.py"


def _resolve(module: str, node: ast.ImportFrom, package: Path) -> str:
    """The absolute name of ``from <node.level dots><node.module> import ...`` inside ``module``."""
    if node.level == 0:
        return node.module or ""
    parts = module.split(".")
    base = parts if _is_package(module, package) else parts[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _skipped_nodes(tree: ast.Module, skip: tuple[str, ...]) -> set[int]:
    out = set()
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.name in skip:
            out.update(id(n) for n in ast.walk(node))
    return out


def _scans_packages(function: ast.AST) -> bool:
    """Whether ``function`` lists a package's modules (``pkgutil.iter_modules`` / ``walk_packages``) to
    import them by name."""
    return any(isinstance(n, ast.Attribute) and n.attr in ("iter_modules", "walk_packages")
               for n in ast.walk(function))


def _package_modules(module: str, function: ast.AST, package: Path) -> list[str]:
    """Every module of the packages that ``function`` imports (it imports them all by name)."""
    out = []
    for node in ast.walk(function):
        if isinstance(node, ast.ImportFrom):
            base = _resolve(module, node, package)
            names = [f"{base}.{alias.name}" for alias in node.names]
        elif isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        else:
            continue
        for name in names:  # the packages imported (not the one imported from)
            if name.startswith(ROOT + "."):
                path = module_file(name, package)
                if path is not None and path.name == "__init__.py":
                    out.extend(f"{name}.{'.'.join(f.relative_to(path.parent).with_suffix('').parts)}"
                               for f in sorted(path.parent.rglob("*.py")) if f.name != "__init__.py")
    return out


@functools.lru_cache(maxsize=None)
def _imports(module: str, package: Path, skip: tuple[str, ...] = ()) -> tuple[str, ...]:
    """The package modules ``module`` imports anywhere in its file (functions of ``skip`` excepted)."""
    path = module_file(module, package)
    if path is None:
        return ()
    tree = ast.parse(path.read_text(), filename=str(path))
    skipped = _skipped_nodes(tree, skip) if skip else set()
    names: list[str] = []
    for node in ast.walk(tree):
        if id(node) in skipped:
            continue
        if isinstance(node, ast.Import):
            names.extend(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = _resolve(module, node, package)
            names.append(base)
            names.extend(f"{base}.{alias.name}" for alias in node.names if alias.name != "*")
        elif (isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value.startswith(ROOT + ".")
              and all(part.isidentifier() for part in node.value.split("."))
              and module_file(node.value, package) is not None):
            names.append(node.value)  # a module's full name in a string: imported by name (importlib)
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and _scans_packages(node):
            names.extend(_package_modules(module, node, package))
    out = []
    for name in names:
        if name != ROOT and not name.startswith(ROOT + "."):
            continue
        parts = name.split(".")
        for i in range(1, len(parts) + 1):  # a module's packages run their __init__ first
            prefix = ".".join(parts[:i])
            if module_file(prefix, package) is not None and prefix not in out:
                out.append(prefix)
    return tuple(out)


def closure(starts: tuple[str, ...], package: Path = PACKAGE) -> list[str]:
    """Every package module that importing and running ``starts`` may import, sorted."""
    seen: set[str] = set()
    todo = list(starts)
    while todo:
        module = todo.pop()
        if module in seen or module_file(module, package) is None:
            continue
        seen.add(module)
        skip = NOT_RUN_BY_STEPS if module == RUNNER else ()
        todo.extend(_imports(module, package, skip))
        parts = module.split(".")
        todo.extend(".".join(parts[:i]) for i in range(1, len(parts)))
    return sorted(seen)


def step_modules(command: str, package: Path = PACKAGE) -> list[str]:
    """The modules the step ``command`` runs: its handler module's closure and the runner's."""
    from ..steps import step

    return closure((step(command).module, RUNNER), package)


def files_hash(modules: list[str], package: Path = PACKAGE) -> str:
    digest = hashlib.sha1()
    for module in sorted(modules):
        path = module_file(module, package)
        digest.update(path.relative_to(package).as_posix().encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:12]


def step_hash(command: str, package: Path = PACKAGE) -> str:
    """The code version of the step ``command``: a hash of the files of :func:`step_modules`."""
    return files_hash(step_modules(command, package), package)


# a module that compiles numba code (the benchmarks only time it)
KERNEL_DEFINITION = re.compile(r"@(?:numba\.)?(?:njit|jit|vectorize|guvectorize|stencil)\b|\bnumba\.(?:njit|jit)\(")


def kernel_definers(package: Path = PACKAGE) -> list[str]:
    """The modules whose own source defines a numba kernel (:data:`KERNEL_DEFINITION`), sorted."""
    users = []
    for path in sorted(package.rglob("*.py")):
        text = path.read_text(encoding="utf-8")
        if "numba" in text and KERNEL_DEFINITION.search(text):
            rel = path.relative_to(package).with_suffix("")
            parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
            users.append(".".join((ROOT, *parts)))
    return users


def kernel_modules(package: Path = PACKAGE) -> list[str]:
    """The modules that define numba kernels (:func:`kernel_definers`), with everything they import:
    numba's cache stamps a compiled kernel with its own file only, so a change to a helper or constant it
    takes from another module would otherwise leave the old machine code in the cache."""
    return closure(tuple(kernel_definers(package)), package)


def kernel_cache_key(package: Path = PACKAGE, memo: Path | None = None) -> str:
    """A hash of :func:`kernel_modules`: the folder under ``NUMBA_CACHE_DIR`` that this code's compiled
    kernels live in.  ``memo`` (a JSON file) keeps the key with a stamp of every package file's size and
    modification time, so that a process whose package is unchanged reads the key instead of parsing the
    import graph again."""
    stamp = hashlib.sha1()
    for path in sorted(package.rglob("*.py")):
        info = path.stat()
        stamp.update(f"{path.relative_to(package).as_posix()} {info.st_mtime_ns} {info.st_size}\n".encode())
    stamp = stamp.hexdigest()
    if memo is not None:
        try:
            data = json.loads(memo.read_text())
            if data.get("stamp") == stamp and isinstance(data.get("key"), str):
                return data["key"]
        except (OSError, ValueError):
            pass
    key = files_hash(kernel_modules(package), package)
    if memo is not None:
        try:
            memo.parent.mkdir(parents=True, exist_ok=True)
            tmp = memo.with_name(f".{memo.name}.{os.getpid()}")
            tmp.write_text(json.dumps({"stamp": stamp, "key": key}))
            os.replace(tmp, memo)
        except OSError:  # a read-only cache folder: recompute next time
            pass
    return key


def key_numba_cache(environ=None, package: Path = PACKAGE) -> str | None:
    """Point ``NUMBA_CACHE_DIR`` (when set) at its subfolder :func:`kernel_cache_key`, so that kernels
    compiled from other code are never loaded; a folder already keyed is left as it is.  Entry points
    call it before numba is imported (the CLI, the tests' conftest).  Returns the folder, or None."""
    environ = os.environ if environ is None else environ
    base = environ.get("NUMBA_CACHE_DIR")
    if not base or environ.get("TRACE3D_NUMBA_CACHE_KEYED") == base:
        return base or None
    key = kernel_cache_key(package, Path(base) / "kernel-key.json")
    environ["NUMBA_CACHE_DIR"] = str(Path(base) / key)
    environ["TRACE3D_NUMBA_CACHE_KEYED"] = environ["NUMBA_CACHE_DIR"]
    return environ["NUMBA_CACHE_DIR"]


def main(argv: list[str] | None = None) -> int:
    """``python -m trace3d.tooling.codehash [command ...]``: each step's hash and the modules it covers."""
    import sys

    from ..steps import STEPS

    commands = (sys.argv[1:] if argv is None else argv) or [s.command for s in STEPS]
    for command in commands:
        modules = step_modules(command)
        print(f"{command} {step_hash(command)} ({len(modules)} modules)")
        for module in modules:
            print(f"    {module}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
