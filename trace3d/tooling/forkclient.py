"""The job's side of the fork server (:mod:`trace3d.tooling.forkserver`): which server a ``trace3d`` job needs,
what it sends, and how it hands its run to a fork of the server and waits for it.

:func:`trace3d.cli.main` calls :func:`delegate` when ``TRACE3D_FORKSERVER`` names a folder of servers; it
returns the exit status of the job's run in a fork of the right server, or why the job runs in-process.
Here and not in the server's module because the command imports it: it loads nothing but the standard
library and the step registry (the server's module imports every step).
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import struct
import sys
import time
from pathlib import Path

ENV_VAR = "TRACE3D_FORKSERVER"
# the signals a job hands on to its child (every catchable one whose default ends a process and that Python
# does not ignore)
FORWARDED = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT, signal.SIGUSR1, signal.SIGUSR2,
             signal.SIGALRM)
HEADER = struct.Struct("!I")
# the signals whose default action dumps core
CORE_SIGNALS = {signal.SIGQUIT, signal.SIGILL, signal.SIGTRAP, signal.SIGABRT, signal.SIGFPE, signal.SIGSEGV,
                signal.SIGBUS, signal.SIGSYS, signal.SIGXCPU, signal.SIGXFSZ}

# set in a forked child: how it ran (trace3d.cli logs it), and that it must not delegate again
CHILD: str | None = None


# ----------------------------------------------------------------------------------------------
# keys: which server a job needs
# ----------------------------------------------------------------------------------------------

def job_key(argv: list[str]) -> str | None:
    """The server key of ``trace3d <argv>``: ``<N>`` for ``--threads N`` (``default`` without), plus ``-spin``
    for the steps whose workers spin (:data:`trace3d.cli.SPIN_COMMANDS`); None for a command that is not a
    pipeline step (benchmarks, ``--help``, ``describe``...: they run in-process)."""
    from ..steps import BY_COMMAND

    threads, i = "default", 0
    while i < len(argv) and argv[i].startswith("-"):
        token = argv[i]
        if token in ("-v", "--verbose"):
            i += 1
        elif token == "--threads" and i + 1 < len(argv):
            threads, i = argv[i + 1], i + 2
        elif token.startswith("--threads="):
            threads, i = token.split("=", 1)[1], i + 1
        else:
            return None
    if i >= len(argv) or argv[i] not in BY_COMMAND or any(a in ("-h", "--help") for a in argv):
        return None
    if threads != "default" and not (threads.isdigit() and int(threads) > 0):
        return None  # the in-process parser words the error
    return f"{int(threads) if threads != 'default' else threads}" + ("-spin" if BY_COMMAND[argv[i]].spin else "")


def _interpreter() -> dict:
    return {"executable": sys.executable, "version": sys.version, "flags": list(sys.flags),
            "prefix": sys.prefix, "uid": os.getuid()}


def _cgroup() -> str:
    try:
        return Path("/proc/self/cgroup").read_text()
    except OSError:
        return ""


def _limits() -> dict[str, list[int]]:
    import resource

    return {name: list(resource.getrlimit(getattr(resource, name))) for name in dir(resource)
            if name.startswith("RLIMIT_")}


# ----------------------------------------------------------------------------------------------
# wire: a length-prefixed JSON message, the first carrying the job's descriptors
# ----------------------------------------------------------------------------------------------

def _send(sock: socket.socket, message: dict, fds: list[int] | None = None) -> None:
    data = json.dumps(message).encode()
    if fds:
        socket.send_fds(sock, [HEADER.pack(len(data))], fds)
        sock.sendall(data)
    else:
        sock.sendall(HEADER.pack(len(data)) + data)


def _recv_exact(sock: socket.socket, size: int) -> bytes:
    chunks, got = [], 0
    while got < size:
        chunk = sock.recv(size - got)
        if not chunk:
            raise ConnectionError("the connection closed mid-message")
        chunks.append(chunk)
        got += len(chunk)
    return b"".join(chunks)


class _Empty(ConnectionError):
    """A connection closed before its first byte (:func:`start` asking whether a server listens)."""


def _recv(sock: socket.socket, with_fds: bool = False) -> tuple[dict, list[int]]:
    if with_fds:
        head, fds, _, _ = socket.recv_fds(sock, HEADER.size, 8)
        if not head and not fds:
            raise _Empty()
        if len(head) < HEADER.size:
            head += _recv_exact(sock, HEADER.size - len(head))
    else:
        head, fds = _recv_exact(sock, HEADER.size), []
    (size,) = HEADER.unpack(head)
    return json.loads(_recv_exact(sock, size)), list(fds)


# ----------------------------------------------------------------------------------------------
# the job's side
# ----------------------------------------------------------------------------------------------

def delegate(argv: list[str], entry: str = "cli", key: str | None = None) -> tuple[int | None, str]:
    """Run ``trace3d <argv>`` (``entry`` "cli"; "probe": ``python -m trace3d.startup_probe <argv>``, the
    benchmark's) in a fork of the server named by ``TRACE3D_FORKSERVER``, of ``key`` (default: the
    job's, :func:`job_key`).

    Returns (exit status, how it ran) when it ran there, (None, why not) when the caller must run it
    in-process. Never raises for the server's sake."""
    folder = os.environ.get(ENV_VAR)
    if not folder or CHILD is not None:
        return None, "ran in-process (no fork server)"
    key = key or job_key(argv)
    if key is None:
        return None, "ran in-process (not a pipeline step)"
    path = os.path.join(folder, f"{key}.sock")
    try:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        sock.settimeout(10)
        sock.connect(path)
    except OSError as exc:
        return None, f"ran in-process (no fork server at {path}: {exc.strerror or exc})"
    try:
        return _delegate(sock, argv, key, entry)
    except (OSError, ValueError, KeyError) as exc:
        return None, f"ran in-process (the fork server at {path} did not answer: {exc})"
    finally:
        sock.close()


def job_request(argv: list[str], key: str, entry: str = "cli") -> dict:
    """What a job sends its server: everything of this process that the fork takes on or checks."""
    mask = os.umask(0)
    os.umask(mask)
    return {"argv": argv, "entry": entry, "key": key, "argv0": sys.argv[0] if sys.argv else "trace3d",
            "cwd": os.getcwd(), "environ": dict(os.environ), "umask": mask, "path": list(sys.path),
            "interpreter": _interpreter(), "cgroup": _cgroup(), "limits": _limits(),
            "nice": os.getpriority(os.PRIO_PROCESS, 0), "fds": [fd for fd in (0, 1, 2) if _is_open(fd)],
            "affinity": sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None}


def _delegate(sock: socket.socket, argv: list[str], key: str, entry: str) -> tuple[int | None, str]:
    request = job_request(argv, key, entry)
    fds = request["fds"]
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    # signals from now on go to the child; one that comes before the child's pid is held until then (or,
    # if the server declines, delivered to this process as it would have been without the server)
    child: list[int] = []
    pending: list[int] = []
    previous = {}

    def forward(signum, frame):  # noqa: ARG001 - signal handler signature
        if child:
            with contextlib.suppress(ProcessLookupError):
                os.kill(child[0], signum)
        else:
            pending.append(signum)

    for sig in FORWARDED:
        with contextlib.suppress(ValueError, OSError):  # not the main thread: nothing to forward from
            previous[sig] = signal.signal(sig, forward)
    try:
        _send(sock, request, fds)
        reply, _ = _recv(sock)
        if not reply.get("ok"):
            return None, f"ran in-process (the fork server declined: {reply.get('why')})"
        child.append(int(reply["pid"]))
        sock.settimeout(None)
        for sig in pending:
            forward(sig, None)
        pending.clear()
        try:
            status, _ = _recv(sock)
        except (ConnectionError, OSError, ValueError):
            _wait_gone(child[0])  # its death signal (PR_SET_PDEATHSIG) has it remove its temporary output
            return None, (f"ran in-process again (the fork server's child {child[0]} stopped without a status: "
                          f"the server is gone)")
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        for sig in pending:  # never reached a child: this process's own, as without the server
            os.kill(os.getpid(), sig)
    how = f"ran in the fork server's child {child[0]} (server {reply.get('server')})"
    if status.get("signal"):
        sig = int(status["signal"])
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        signal.signal(sig, signal.SIG_DFL)
        if sig in CORE_SIGNALS:  # the job dies of it too, without a core file of its own: the child's is the one
            import resource

            with contextlib.suppress(ValueError, OSError):
                resource.setrlimit(resource.RLIMIT_CORE, (0, resource.getrlimit(resource.RLIMIT_CORE)[1]))
        os.kill(os.getpid(), sig)
        return 128 + sig, how
    return int(status["exit"]), how


def _wait_gone(pid: int, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return
        except PermissionError:  # the pid is someone else's now
            return
        time.sleep(0.05)


def _is_open(fd: int) -> bool:
    try:
        os.fstat(fd)
        return True
    except OSError:
        return False
