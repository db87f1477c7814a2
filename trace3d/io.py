"""Atomic outputs and small file helpers.

A step never writes its final output path directly: it writes into a temporary sibling and renames
it at the end, so that a killed step leaves no complete-looking output and never destroys an earlier
result until the new one is complete.  A step killed so hard that it could not remove its temporary
sibling (SIGKILL, a power cut) leaves it behind; the next run of that step removes it.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import shutil
import uuid
from pathlib import Path
from typing import Any, Iterator


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
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        for name in names:
            _PENDING.pop(name, None)
    old = None
    if final.exists():
        old = _tmp_sibling(final)
        os.replace(final, old)
    os.replace(tmp, final)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def atomic_file(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary file path that is renamed onto ``path`` when the block succeeds."""
    final = Path(path)
    final.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_siblings(final)
    tmp = _tmp_sibling(final)
    try:
        yield tmp
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise
    os.replace(tmp, final)


def write_json(path: str | os.PathLike, data: Any) -> None:
    """Write ``data`` as indented JSON, atomically."""
    with atomic_file(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2, sort_keys=False) + "\n")
