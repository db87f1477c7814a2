"""Atomic outputs and small file helpers.

A step never writes its final output path directly: it writes into a temporary sibling and renames
it at the end, so that a killed step leaves no complete-looking output and never destroys an earlier
result until the new one is complete.  A step killed so hard that it could not remove its temporary
sibling (SIGKILL, a power cut) leaves it behind; the next run of that step removes it.

While a step runs (:func:`step_outputs`, entered by the CLI), every folder it writes holds a manifest,
``.trace3d-step`` (the step's name and each file's size and SHA-256), written last, before the rename:

- an ``--out`` is replaced only if it is missing, an empty folder, or a folder whose manifest names
  the same step (an earlier output of that step, which Snakemake's reruns and a user's second run
  make); anything else (a user's folder, a file, another step's output, one of the step's own
  inputs) is refused in one sentence before anything is written;
- a step reads an input folder only after checking it against its manifest (:func:`verify_inputs`), so
  that a truncated or edited file of a cached output is named, with the rule to rerun, instead of read;
  ``trace3d verify <tree>`` checks every output in a tree (:func:`verify_tree`).
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import logging
import os
import re
import shutil
import uuid
from pathlib import Path
from typing import Any, Iterable, Iterator

from .errors import Trace3DError

MANIFEST = ".trace3d-step"  # inside every folder a step writes: {"step", "files": {path: [size, sha256]}}


def _tmp_sibling(path: Path) -> Path:
    return path.with_name(f".{path.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def remove_stale_siblings(path: str | os.PathLike) -> list[Path]:
    """Remove the temporary siblings of ``path`` that a killed run left (``.<name>.tmp-<pid>-<hex>``
    whose process no longer runs); returns what was removed."""
    final = Path(path)
    if not final.parent.is_dir():
        return []
    pattern = re.compile(rf"^\.{re.escape(final.name)}\.tmp-(\d+)-[0-9a-f]{{8}}$")
    removed = []
    for entry in final.parent.iterdir():
        match = pattern.match(entry.name)
        if match is None or int(match.group(1)) == os.getpid() or _pid_alive(int(match.group(1))):
            continue
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry, ignore_errors=True)
        else:
            with contextlib.suppress(FileNotFoundError):
                entry.unlink()
        removed.append(entry)
    return removed


# temporary path -> final path, for the log messages written while a step runs (see TempPathFilter)
_PENDING: dict[str, str] = {}


class TempPathFilter(logging.Filter):
    """Rewrites the temporary output paths in log messages to the final paths they are renamed to,
    so that a log names files that exist after the step (installed by the CLI on its log handler)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if _PENDING:
            message = record.getMessage()
            changed = message
            for tmp, final in list(_PENDING.items()):
                changed = changed.replace(tmp, final)
            if changed != message:
                record.msg, record.args = changed, ()
        return True


@contextlib.contextmanager
def atomic_dir(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary directory that replaces ``path`` when the block finishes without error.

    On error the temporary directory is removed and ``path`` (if it existed) is left untouched.
    """
    final = Path(path)
    step = _STEP[0]
    if step is not None:
        check_destination(final, step[0], step[1])
    final.parent.mkdir(parents=True, exist_ok=True)
    for stale in remove_stale_siblings(final):
        logging.getLogger(__name__).info("removed %s, left by a killed run", stale)
    tmp = _tmp_sibling(final)
    names = {str(tmp.resolve()): str(final.resolve()), str(tmp): str(final),
             os.path.relpath(tmp): os.path.relpath(final)}
    _PENDING.update(names)
    try:
        tmp.mkdir()  # inside the try: an interruption right after it still removes the folder
        yield tmp
        if step is not None:
            write_manifest(tmp, step[0], step[2])
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        for name in names:
            _PENDING.pop(name, None)
    old = None
    try:
        if final.exists() or final.is_symlink():
            old = _tmp_sibling(final)
            os.replace(final, old)
        os.replace(tmp, final)
    except BaseException:
        if old is not None and not final.exists():
            os.replace(old, final)  # put the earlier output back
            old = None
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        if old is not None:
            _remove(old)


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


@contextlib.contextmanager
def atomic_file(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary file path that is renamed onto ``path`` when the block succeeds."""
    final = Path(path)
    final.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_siblings(final)
    tmp = _tmp_sibling(final)
    try:
        yield tmp
        if final.is_dir() and not final.is_symlink():
            raise Trace3DError(f"{final} is a folder; give a file name that is not one (the folder is left as it is).")
        os.replace(tmp, final)
    except BaseException:
        _remove(tmp)
        raise


def write_json(path: str | os.PathLike, data: Any) -> None:
    """Write ``data`` as indented JSON, atomically."""
    with atomic_file(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2, sort_keys=False) + "\n")


# ----------------------------------------------------------------------------------------------
# what a step may replace, and the manifests of its outputs
# ----------------------------------------------------------------------------------------------

# (step name, its input paths, its Snakemake rules) while a step runs (step_outputs); None: library use
_STEP: list[tuple[str, tuple[Path, ...], tuple[str, ...]] | None] = [None]


@contextlib.contextmanager
def step_outputs(step: str, inputs: Iterable[str | os.PathLike] = (), rules: Iterable[str] = ()) -> Iterator[None]:
    """While the block runs, every :func:`atomic_dir` is an output of ``step``: it refuses a destination
    that is not the step's own (:func:`check_destination`) and writes the folder's manifest last (naming
    ``rules``, the Snakemake rules that run the step, for the message that asks for a rerun)."""
    previous = _STEP[0]
    _STEP[0] = (step, tuple(Path(p) for p in inputs), tuple(rules))
    try:
        yield
    finally:
        _STEP[0] = previous


def read_manifest(folder: str | os.PathLike) -> dict | None:
    """The manifest of a step's output folder (None where the folder has none or it is unreadable)."""
    path = Path(folder) / MANIFEST
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict) or not isinstance(data.get("step"), str) or not isinstance(data.get("files"), dict):
        return None
    return data


def _same_or_inside(path: Path, folder: Path) -> bool:
    return path == folder or folder in path.parents


def check_destination(final: Path, step: str, inputs: Iterable[Path] = ()) -> None:
    """Refuse (:class:`Trace3DError`, one sentence) an output folder ``final`` of ``step`` that is one
    of the step's inputs (or holds one), or that exists and is neither empty nor an earlier output of
    ``step`` (its manifest names the step)."""
    resolved = final.resolve()
    for source in inputs:
        if _same_or_inside(source.resolve(), resolved):
            raise Trace3DError(f"--out {final} is {'' if source.resolve() == resolved else 'a folder holding '}"
                               f"this step's input {source}, which writing it would destroy; give another --out.")
    if not (final.exists() or final.is_symlink()):
        return
    if not final.is_dir() or final.is_symlink():
        raise Trace3DError(f"--out {final} exists and is not a folder (a file or a link); give a path that does not "
                           f"exist yet (it is left as it is).")
    if not any(final.iterdir()):
        return
    manifest = read_manifest(final)
    if manifest is None:
        raise Trace3DError(f"--out {final} already holds files that `trace3d {step}` did not write; give a new or "
                           f"empty folder, or remove this one first (nothing in it was changed).")
    if manifest["step"] != step:
        raise Trace3DError(f"--out {final} is the output of `trace3d {manifest['step']}`, not of `trace3d {step}`; "
                           f"give another --out (nothing in it was changed).")


def _digest(path: Path) -> str:
    sha = hashlib.sha256()
    with open(path, "rb") as handle:
        while chunk := handle.read(1 << 20):
            sha.update(chunk)
    return sha.hexdigest()


def _files(folder: Path) -> list[Path]:
    """Every regular file under ``folder`` but the manifest, sorted (symlinks to files are followed)."""
    out = []
    for root, dirs, names in os.walk(folder):
        dirs.sort()
        for name in names:
            path = Path(root) / name
            if path.parent == folder and name == MANIFEST:
                continue
            if path.is_file():
                out.append(path)
    return sorted(out, key=lambda p: p.relative_to(folder).as_posix())


def write_manifest(folder: str | os.PathLike, step: str, rules: Iterable[str] = ()) -> Path:
    """Write ``folder``'s manifest: the step's name, its Snakemake rules and every file's size and SHA-256
    (call it last)."""
    folder = Path(folder)
    files = {p.relative_to(folder).as_posix(): [p.stat().st_size, _digest(p)] for p in _files(folder)}
    path = folder / MANIFEST
    path.write_text(json.dumps({"step": step, "rules": list(rules), "files": files}, indent=0, sort_keys=True) + "\n")
    return path


def _rule_hint(manifest: dict) -> str:
    rules = [r for r in manifest.get("rules") or () if isinstance(r, str)]
    return (f"rerun it with snakemake --forcerun={rules[0]}" + (f" (or {', '.join(rules[1:])})" if rules[1:] else "")
            if rules else f"rerun `trace3d {manifest['step']}`")


def manifest_problems(folder: str | os.PathLike) -> list[str]:
    """One sentence per file of ``folder`` that is missing or differs from its manifest (empty: intact or
    no manifest)."""
    folder = Path(folder)
    manifest = read_manifest(folder)
    if manifest is None:
        return []
    hint = _rule_hint(manifest)
    problems = []
    for name, entry in sorted(manifest["files"].items()):
        path = folder / name
        size, digest = (entry + [None, None])[:2] if isinstance(entry, list) else (None, None)
        try:
            actual = path.stat().st_size
        except FileNotFoundError:
            problems.append(f"{path} is missing from the output of `trace3d {manifest['step']}` "
                            f"({folder / MANIFEST} lists it); {hint}.")
            continue
        if actual != size:
            problems.append(f"{path} has {actual} bytes where `trace3d {manifest['step']}` wrote {size} (corrupt or "
                            f"changed after it was written); {hint}, or remove {folder / MANIFEST} if the change "
                            f"is yours.")
        elif _digest(path) != digest:
            problems.append(f"{path} differs from what `trace3d {manifest['step']}` wrote (its checksum in "
                            f"{folder / MANIFEST}: corrupt or changed after it was written); {hint}, or remove "
                            f"{folder / MANIFEST} if the change is yours.")
    return problems


def _marked_folder(path: Path) -> Path | None:
    """The nearest folder at or above ``path`` holding a manifest (None if none does)."""
    path = path.absolute()
    for folder in (path, *path.parents):
        if (folder / MANIFEST).is_file():
            return folder
    return None


def check_file_outputs(outputs: Iterable[str | os.PathLike], inputs: Iterable[str | os.PathLike]) -> None:
    """Refuse (one sentence) an output file that is one of the step's inputs, or an existing file inside a
    step output that the step reads (a table written over a scene's cameras.json); folders are
    :func:`check_destination`'s."""
    inputs = [Path(p) for p in inputs]
    for out in map(Path, outputs):
        if out.is_dir():
            continue
        resolved = out.resolve()
        marked = _marked_folder(out) if out.exists() else None
        for source in inputs:
            if resolved == source.resolve() or (marked is not None and _same_or_inside(marked.resolve(),
                                                                                      source.resolve())):
                raise Trace3DError(f"{out} is {'' if resolved == source.resolve() else 'a file of '}this step's "
                                   f"input {source}, which writing it would destroy; give another output path.")


def verify_inputs(paths: Iterable[str | os.PathLike]) -> None:
    """Check every step output that ``paths`` are (or lie inside) against its manifest; the first file
    that differs is raised as one sentence (:class:`Trace3DError`). Folders without a manifest (a
    user's own) are read as they are."""
    seen = set()
    for path in paths:
        folder = _marked_folder(Path(path))
        if folder is None or folder in seen:
            continue
        seen.add(folder)
        problems = manifest_problems(folder)
        if problems:
            raise Trace3DError(problems[0])


def verify_tree(root: str | os.PathLike) -> tuple[list[Path], list[str]]:
    """(the step outputs found under ``root``, one sentence per damaged file among them)."""
    root = Path(root)
    folders, problems = [], []
    for dirpath, dirs, names in os.walk(root):
        dirs.sort()
        dirs[:] = [d for d in dirs if ".tmp-" not in d]
        if MANIFEST in names:
            folders.append(Path(dirpath))
            problems += manifest_problems(dirpath)
    return folders, problems


# ----------------------------------------------------------------------------------------------
# OS errors as one sentence
# ----------------------------------------------------------------------------------------------

_OS_ADVICE = {
    errno.ENOSPC: "the disk is full; free some space and run the step again",
    errno.EDQUOT: "the disk quota is used up; free some space and run the step again",
    errno.EROFS: "the file system is read-only; give a path on a writable disk",
    errno.EACCES: "permission denied; give a path you may write (and read)",
    errno.EPERM: "the operation is not permitted there; give a path you may write",
    errno.ENOENT: "no such file or folder; check the path",
    errno.ENOTDIR: "a part of the path is a file, not a folder; check the path",
    errno.EISDIR: "it is a folder where a file was expected; check the path",
    errno.EMFILE: "too many open files; raise `ulimit -n` and run the step again",
    errno.EIO: "the disk reported an input/output error; check the disk",
}


_TMP_PART = re.compile(r"(^|/)\.([^/]+)\.tmp-\d+-[0-9a-f]{8}(?=/|$)")


def final_name(path: str | os.PathLike) -> str:
    """``path`` with its temporary parts (``.<name>.tmp-<pid>-<hex>``) named as the final paths they
    become, so that a message names a file the user can find."""
    return _TMP_PART.sub(r"\1\2", os.fsdecode(path))


def os_error_sentence(exc: OSError) -> str:
    """An OS error (disk full, read-only, permission, missing path) as one sentence with its path."""
    where = final_name(exc.filename) if exc.filename is not None else None
    advice = _OS_ADVICE.get(exc.errno, (exc.strerror or str(exc)).rstrip(".").lower())
    code = errno.errorcode.get(exc.errno, "") if exc.errno is not None else ""
    text = f"{where}: {advice}" if where is not None else f"{advice}"
    return text + (f" ({code})" if code else "") + "; nothing was written (an earlier output, if any, is unchanged)."
