"""An opt-in fork server for the ``trace3d`` command: every job's imports and kernel loads, paid once.

Every Snakemake job runs ``trace3d <step> ...`` as a fresh Python, which spends 1-2 s of CPU importing
torch and its step and up to 2 s more loading its cached numba kernels (``trace3d bench startup``). A
server process pays that once; each job then forks from it:

    python -m trace3d.tooling.forkserver start DIR [--keys 1 1-spin 2]   # servers, in the background
    export TRACE3D_FORKSERVER=DIR                                          # the jobs' opt-in
    python -m trace3d.tooling.forkserver stop DIR

**One server per process setting.** The in-process command sets ``OMP_NUM_THREADS``, ``MKL_NUM_THREADS``,
``OPENBLAS_NUM_THREADS`` and ``NUMBA_NUM_THREADS`` to its ``--threads N`` (:func:`trace3d.threads.limit_threads`)
and, for the lift, ``GOMP_SPINCOUNT`` (:data:`trace3d.cli.SPIN_COMMANDS`) *before* it imports numpy, torch and
numba, whose runtimes read them once, when loaded. A server loads its libraries with the values a job of
its key would have (:func:`effective_environment`): the key is the thread count (``default``: no
``--threads``) plus ``-spin`` for the spinning steps, the socket ``DIR/<key>.sock``. A server of N threads
serves Snakemake's jobs of N threads, whose environment Snakemake gives N in ``OMP_NUM_THREADS``,
``GOTO_NUM_THREADS``, ``OPENBLAS_NUM_THREADS``, ``MKL_NUM_THREADS``, ``VECLIB_MAXIMUM_THREADS`` and
``NUMEXPR_NUM_THREADS`` (:data:`SNAKEMAKE_THREAD_VARS`); a job finds the server of its own key or runs
in-process. The job's side (which key, what it sends, the wait) is :mod:`trace3d.tooling.forkclient`, which
the command imports; this module imports every step.

**The server** (:func:`serve`) makes the process settings of a job of its key (:func:`effective_environment`),
imports torch, numba, every step's handler and library modules, and loads every recorded kernel
(``kernel_signatures.json``) from ``NUMBA_CACHE_DIR`` -- without running anything that starts a thread pool
(no ``limit_threads``, no torch op, no kernel call). Before it listens it checks that it runs no more threads
than right after its bare ``import numpy, scipy.linalg, torch, numba`` (forking copies only the calling thread;
OpenBLAS's pools, started when it loads, are shut down before a fork by OpenBLAS itself). Then it
listens on ``DIR/<key>.sock``, ``DIR`` being a folder of mode 0700 that only its owner may enter.

**A job** (:func:`trace3d.tooling.forkclient.delegate`, called by :func:`trace3d.cli.main` when
``TRACE3D_FORKSERVER`` is set) connects, sends its argv, working folder, environment, umask, nice value, CPU
affinity, resource limits, ``sys.path`` and its stdin/stdout/stderr (as file descriptors), and waits. The
server checks that the job may run in a fork of it (:func:`unsafe`): the same user, interpreter and flags; the
same values, once the entry point's and ``--threads``' settings are made, of every environment variable read
when the libraries load (:data:`AGREE_PREFIXES`, :data:`AGREE_NAMES`: numba's, OpenMP's, MKL's, OpenBLAS's,
torch's, CUDA's, Python's, the loader's, the locale, a batch job's id); every module the server has loaded
found at the same file through the job's ``sys.path``; no source file of the package changed, appeared or
vanished since the server loaded it (size and modification time); and limits the fork can take on (a nice
value and resource limits no looser than the server's), in the server's control group. If so it forks: the
child takes the job's descriptors, folder, environment (plus what the server's imports added to the
environment, as the job's own imports would: cv2's ``LD_LIBRARY_PATH``) and the rest, re-seeds numpy's global
generator from the OS as a fresh process's import does, and runs :func:`trace3d.cli.main` with the job's
arguments -- the code path of an in-process run -- while the server sends the child's pid, then its exit
status, back to the job, which exits with it (a child killed by a signal: the job kills itself with it).
Otherwise the job runs in-process, as without a server; so it does when no server answers. Which way a job ran
is logged at debug level (``trace3d -v``), each job and each refusal in the server's log (``DIR/<key>.log``
when started by :func:`start`).

Known fault: a signal that stops a job while a numba kernel runs can crash it (SIGSEGV): rarely in a fresh
process (1 of 147 measured), in about half of the cases in a forked child (docs/performance.md, 'The fork
server'); the job then ends as if killed.

What differs from an in-process run, by design: the warnings and log lines that importing the libraries
prints were printed once, into the server's log; Python's string hashes and numpy's legacy global
generator are the server's (re-seeded); numba's OpenMP layer is re-armed for the child
(:func:`_numba_threads_after_fork`). The outputs are the same bytes (tests/workflow/test_forkserver.py).

**Signals and deaths.** SIGINT, SIGTERM, SIGHUP, SIGQUIT, SIGUSR1, SIGUSR2 and SIGALRM sent to the job go on
to the child, which handles them as the in-process command does (SIGTERM and Ctrl-C remove the temporary
output), and the job exits with the child's status. A job that dies without forwarding (SIGKILL: a time
limit, ``kill -9``) closes its connection: the server kills its child at once with SIGKILL too, as the
in-process step would have died (its temporary output left for the next run to remove). A child dies
with its server (``PR_SET_PDEATHSIG``, SIGTERM), and a job whose server vanished mid-run runs the step
again in-process (outputs are written atomically).

**Not for batch jobs.** A job inside a SLURM (or PBS, LSF) allocation names its job id in the environment,
which the server's lacks, so it runs in-process: work done in a fork of the server would escape the job's
memory and CPU accounting and its limits (tests/workflow/test_slurm.py checks that SLURM kills a job above
its memory). The same holds for Snakemake's ``benchmark:`` files of a local run: the job's process uses
almost no CPU or memory, the server's child does the work, so ``results/benchmarks/`` keep the wall time
and lose the job's CPU seconds and peak memory while a server is used (docs/performance.md).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import socket
import struct
import sys
import time
from pathlib import Path

from . import forkclient
from .forkclient import ENV_VAR, FORWARDED, _cgroup, _Empty, _interpreter, _limits, _recv, _send

# environment variables read when Python, numpy, torch, numba or their runtimes load, or that place a
# process in a batch job: a job runs in a fork only where the server's values are the same
AGREE_PREFIXES = ("NUMBA_", "OMP_", "GOMP_", "KMP_", "MKL_", "OPENBLAS_", "GOTO", "BLIS_", "TORCH", "PYTORCH",
                  "CUDA_", "NVIDIA_", "PYTHON", "LD_", "MALLOC_", "LC_", "MPL", "XDG_", "TRACE3D_",
                  "SLURM_JOB_ID", "PBS_JOBID", "LSB_JOBID")
AGREE_NAMES = ("HOME", "LANG", "LANGUAGE", "TZ", "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")
# what Snakemake puts into the environment of a job with N threads (snakemake/shell.py), so into a server's of key N
SNAKEMAKE_THREAD_VARS = ("OMP_NUM_THREADS", "GOTO_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                         "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")
NOT_COMPARED = (ENV_VAR,)


def _key_settings(key: str) -> tuple[int | None, bool]:
    threads, _, spin = key.partition("-")
    if spin not in ("", "spin") or not (threads == "default" or (threads.isdigit() and int(threads) > 0)):
        raise ValueError(f"a server key is <threads>[-spin] or default[-spin], got {key!r}")
    return (None if threads == "default" else int(threads)), spin == "spin"


# ----------------------------------------------------------------------------------------------
# what must agree between a job and the server
# ----------------------------------------------------------------------------------------------

def agreeing_environment(environ) -> dict[str, str]:
    """The variables of ``environ`` that a job and its server must share. ``LD_LIBRARY_PATH`` is compared
    without its folders that do not exist, which the loader skips, and its empty entries: importing cv2
    adds ``cv2/../../lib64:`` to the environment of the process that imports it, for its subprocesses (a
    test process, Snakemake's); the empty entry would have the job's loader look for shared libraries in
    its working folder too, which matters only where that folder holds one that torch or numpy loads."""
    out = {k: v for k, v in environ.items()
           if (k.startswith(AGREE_PREFIXES) or k in AGREE_NAMES) and k not in NOT_COMPARED}
    if "LD_LIBRARY_PATH" in out:
        folders = [f for f in out["LD_LIBRARY_PATH"].split(":") if f and os.path.isdir(f)]
        if folders:
            out["LD_LIBRARY_PATH"] = ":".join(folders)
        else:
            del out["LD_LIBRARY_PATH"]
    return out


def effective_environment(environ, key: str) -> dict[str, str]:
    """The environment a ``trace3d`` job of ``key`` started in ``environ`` has when it first imports numpy,
    torch and numba: the entry point's settings (:func:`trace3d.cli._entry_point_environment`: OpenMP's
    wait policy, numba's CPU target and keyed cache folder), ``GOMP_SPINCOUNT`` for a spinning step
    (:func:`trace3d.cli._command_environment`) and the ``--threads`` budget
    (:func:`trace3d.threads.limit_threads`, which sets these before its imports)."""
    from ..threads import ENV_VARS
    from .codehash import key_numba_cache
    from .cputarget import set_wide_vectors

    env = dict(environ)
    threads, spin = _key_settings(key)
    env.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    set_wide_vectors(env)
    key_numba_cache(env)
    if spin:
        env.setdefault("GOMP_SPINCOUNT", "10000")
    if threads is not None:
        for name in ENV_VARS:
            env[name] = str(threads)
        env["NUMBA_NUM_THREADS"] = str(threads)
    return env


def source_stamp(package: Path | None = None) -> dict[str, list[int]]:
    """path -> [size, mtime_ns] of every Python file of the package (and the kernel manifest)."""
    package = package or Path(__file__).resolve().parent.parent
    out = {}
    for path in sorted([*package.rglob("*.py"), *package.rglob("*.json")]):
        with contextlib.suppress(OSError):
            info = path.stat()
            out[str(path)] = [info.st_size, info.st_mtime_ns]
    return out


def _origin(name: str, path: list[str]) -> str | None:
    """Where a fresh import of the top-level module ``name`` would load it from, searching ``path``."""
    import importlib.machinery

    for finder in sys.meta_path:
        if finder is importlib.machinery.PathFinder:
            spec = finder.find_spec(name, path)
        elif isinstance(finder, type) and finder in (importlib.machinery.BuiltinImporter,
                                                     importlib.machinery.FrozenImporter):
            continue
        else:
            try:
                spec = finder.find_spec(name, None)
            except Exception:  # noqa: BLE001 - a third-party finder that cannot answer: not its module
                spec = None
        if spec is not None:
            return spec.origin
    return None


class Server:
    """The state one server compares every job with (made after its preload)."""

    def __init__(self, key: str, environ: dict[str, str], package: Path | None = None):
        self.key = key
        self.environment = agreeing_environment(environ)  # the server's effective environment
        self.interpreter = _interpreter()
        self.package = package or Path(__file__).resolve().parent.parent
        self.added: dict[str, str] = {}  # what the server's imports added to its environment
        self.stamp = source_stamp(self.package)
        self.cgroup = _cgroup()
        self.limits = _limits()
        self.nice = os.getpriority(os.PRIO_PROCESS, 0)
        # top-level module -> its file, for every loaded module that an import by its name finds there (not
        # the extension modules that register themselves under a top-level name, such as scipy's _cyutility)
        self.modules = {}
        for name, module in list(sys.modules.items()):
            origin = getattr(getattr(module, "__spec__", None), "origin", None)
            if ("." not in name and not name.startswith("__") and origin and os.path.isabs(origin)
                    and _origin(name, sys.path) == origin):
                self.modules[name] = origin


def unsafe(server: Server, request: dict) -> str | None:
    """Why the job of ``request`` must not run in a fork of ``server`` (None: it may)."""
    if request.get("key") != server.key:
        return f"it needs the server {request.get('key')!r}, this one is {server.key!r}"
    theirs = request["interpreter"]
    for name, ours in server.interpreter.items():
        if theirs.get(name) != ours:
            return f"another interpreter ({name}: {theirs.get(name)!r} here, {ours!r} in the server)"
    env = agreeing_environment(effective_environment(request["environ"], server.key))
    for name in sorted(set(env) | set(server.environment)):
        if env.get(name) != server.environment.get(name):
            return (f"the environment differs: {name}={env.get(name)!r} here, {server.environment.get(name)!r} "
                    f"in the server")
    if request["cgroup"] != server.cgroup:
        return "the job runs in another control group (a batch job's?), whose limits a fork of the server would escape"
    if request["nice"] < server.nice:
        return f"nice {request['nice']} is below the server's {server.nice}"
    for name, (soft, hard) in request["limits"].items():
        ours = server.limits.get(name)
        if ours is None or not _within(hard, ours[1]) or not _within(soft, hard):
            return f"resource limit {name} {soft}/{hard} cannot be taken on by a fork of the server ({ours})"
    now = source_stamp(server.package)
    if now != server.stamp:
        changed = sorted(set(now) ^ set(server.stamp) | {p for p in now if server.stamp.get(p) != now[p]})
        return f"the package's sources changed since the server loaded them ({changed[0]}" + \
            (f" and {len(changed) - 1} more)" if len(changed) > 1 else ")")
    cwd = request["cwd"]
    path = [os.path.join(cwd, p) if not os.path.isabs(p) else p for p in request["path"]]
    for name, origin in server.modules.items():
        found = _origin(name, path)
        if found != origin:
            return f"module {name} would be imported from {found}, the server has {origin}"
    return None


def _within(value: int, bound: int) -> bool:
    import resource

    if bound == resource.RLIM_INFINITY:
        return True
    return value != resource.RLIM_INFINITY and value <= bound


# ----------------------------------------------------------------------------------------------
# the server
# ----------------------------------------------------------------------------------------------

def _threads() -> list[str]:
    names = []
    for task in sorted(os.listdir("/proc/self/task")):
        try:
            names.append(Path(f"/proc/self/task/{task}/comm").read_text().strip())
        except OSError:
            pass
    return names


def preload(key: str) -> dict:
    """In the server, before it listens: the process settings of a ``trace3d`` job of ``key``, then every
    step's imports and every recorded kernel. Starts no thread pool: raises RuntimeError if the process
    runs more threads afterwards than right after ``import numpy, scipy.linalg, torch, numba`` (OpenBLAS,
    in numpy and in scipy, starts its pool of ``OPENBLAS_NUM_THREADS - 1`` threads when loaded, as in a job,
    and shuts it down before a fork, its own ``pthread_atfork`` handler; the child starts it again)."""
    import importlib

    threads, _ = _key_settings(key)
    environ = dict(os.environ)
    if threads is not None:  # the server of N threads serves Snakemake's jobs of N threads
        environ.update({name: str(threads) for name in SNAKEMAKE_THREAD_VARS})
    environ = effective_environment(environ, key)
    os.environ.clear()
    os.environ.update(environ)
    from .. import cli  # noqa: F401 - what the job has loaded when it forks off

    cpu = time.process_time()
    import numba  # noqa: F401
    import numpy  # noqa: F401
    import scipy.linalg  # noqa: F401
    import torch  # noqa: F401

    bare = _threads()  # numpy's and scipy's OpenBLAS start their pools (N - 1 threads) when loaded
    from ..steps import STEPS

    for s in STEPS:
        importlib.import_module(s.module)
        for entry in s.entry:
            importlib.import_module(entry.split(":")[0])
    from .warm import cached_dispatchers, parse_signature, read_manifest

    loaded = failed = 0
    for module, functions in sorted(read_manifest().items()):
        found = cached_dispatchers(module)
        for name, signatures in sorted(functions.items()):
            for text in signatures:
                try:
                    found[name].compile(parse_signature(text))
                    loaded += 1
                except Exception:  # noqa: BLE001 - a kernel that cannot load is loaded by the job, as without a server
                    failed += 1
    after = _threads()
    # what the imports put into the environment (cv2: LD_LIBRARY_PATH, for its subprocesses), as they would
    # in the job's own imports: the child adds it to the job's environment
    added = {k: v for k, v in os.environ.items() if environ.get(k) != v}
    if len(after) > len(bare):
        raise RuntimeError(f"the preload started threads ({len(bare)} after the bare imports: {bare}; {len(after)} "
                           f"after the steps and kernels: {after}); a fork would lose them")
    return {"threads": after, "kernels": loaded, "kernels_failed": failed, "cpu_s": round(time.process_time() - cpu, 2),
            "environ": environ, "added": added}


def _say(text: str) -> None:
    print(f"{time.strftime('%H:%M:%S')} trace3d fork server [{os.getpid()}]: {text}", file=sys.stderr, flush=True)


def check_folder(folder: Path) -> None:
    """Make ``folder`` (mode 0700) or check that it is this user's and closed to others."""
    folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    info = folder.stat()
    if info.st_uid != os.getuid() or info.st_mode & 0o077:
        raise PermissionError(f"{folder}: a fork server's folder must be yours with mode 0700 "
                              f"(it is mode {oct(info.st_mode & 0o777)})")


def serve(folder: Path, key: str, idle_s: float = 3600.0) -> int:
    """Run the server of ``key`` in this process until SIGTERM/SIGINT, or ``idle_s`` without a job."""
    import gc
    import selectors

    check_folder(folder)
    info = preload(key)
    server = Server(key, info["environ"])
    server.added = info["added"]
    gc.collect()
    gc.freeze()  # the children's garbage collector leaves the preloaded objects (and their pages) alone
    sock_path = folder / f"{key}.sock"
    pid_path = folder / f"{key}.pid"
    with contextlib.suppress(OSError):
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        probe.connect(str(sock_path))
        probe.close()
        _say(f"a server of {key} already answers at {sock_path}; leaving")
        return 1
    with contextlib.suppress(FileNotFoundError):
        sock_path.unlink()
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(str(sock_path))
    listener.listen(64)
    pid_path.write_text(f"{os.getpid()}\n")

    class _Stop(Exception):
        pass

    def stop(signum, frame):  # noqa: ARG001 - signal handler signature
        raise _Stop()

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGHUP, stop)
    _say(f"{key}: listening at {sock_path} ({info['kernels']} kernels loaded, {info['kernels_failed']} failed; "
         f"{len(info['threads'])} thread(s); preload {info['cpu_s']} s CPU)")
    selector = selectors.DefaultSelector()
    selector.register(listener, selectors.EVENT_READ, ("listen", None))
    jobs: dict[int, dict] = {}  # child pid -> its connection, pidfd, whether the job is gone
    last = time.monotonic()
    served = 0
    try:
        while True:
            for sel_key, _ in selector.select(30.0):
                kind, pid = sel_key.data
                if kind == "listen":
                    conn, _ = listener.accept()
                    child = _start_job(conn, server, listener, selector, jobs)
                    if child is not None:
                        selector.register(jobs[child]["pidfd"], selectors.EVENT_READ, ("child", child))
                        selector.register(conn, selectors.EVENT_READ, ("conn", child))
                        served += 1
                elif kind == "child":
                    job = jobs.pop(pid)
                    _, status = os.waitpid(pid, 0)
                    reply = ({"signal": os.WTERMSIG(status)} if os.WIFSIGNALED(status)
                             else {"exit": os.waitstatus_to_exitcode(status)})
                    with contextlib.suppress(OSError):
                        _send(job["conn"], reply)
                    _say(f"job {pid} (trace3d {' '.join(job['argv'][:3])} ... in {job['cwd']}): {reply}")
                    selector.unregister(job["pidfd"])
                    os.close(job["pidfd"])
                    if not job["gone"]:  # else unregistered when the job went away
                        selector.unregister(job["conn"])
                    job["conn"].close()
                    last = time.monotonic()
                else:  # the job's connection: readable only when the job died unforwarded (SIGKILL)
                    job = jobs.get(pid)
                    if job is None or job["gone"]:
                        continue
                    selector.unregister(job["conn"])
                    job["gone"] = True
                    with contextlib.suppress(ProcessLookupError):  # as the job died: at once, no clean-up
                        os.kill(pid, signal.SIGKILL)
            if not jobs and time.monotonic() - last > idle_s:
                _say(f"{key}: no job for {idle_s:.0f} s; leaving")
                break
    except _Stop:
        pass
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        for pid in jobs:  # a server stopped mid-job stops its jobs as SIGTERM would, and says so to them
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGTERM)
        for pid, job in jobs.items():
            with contextlib.suppress(ChildProcessError):
                _, status = os.waitpid(pid, 0)
                with contextlib.suppress(OSError):
                    _send(job["conn"], {"signal": os.WTERMSIG(status)} if os.WIFSIGNALED(status)
                          else {"exit": os.waitstatus_to_exitcode(status)})
            job["conn"].close()
        listener.close()
        with contextlib.suppress(FileNotFoundError):
            if pid_path.read_text().strip() == str(os.getpid()):
                sock_path.unlink()
                pid_path.unlink()
        _say(f"{key}: stopped after {served} job(s)")
    return 0


def _start_job(conn, server: Server, listener, selector, jobs) -> int | None:
    """Read a job's request; fork its child, or answer why not. Returns the child's pid (None: declined)."""
    fds: list[int] = []
    try:
        conn.settimeout(10)
        request, fds = _recv(conn, with_fds=True)
        creds = conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
        _, uid, _ = struct.unpack("3i", creds)
        why = "another user's job" if uid != os.getuid() else unsafe(server, request)
        if why is None and len(fds) != len(request["fds"]):
            why = "its standard streams did not arrive"
        if why is not None:
            _say(f"declined trace3d {' '.join(request.get('argv', [])[:3])} ...: {why}")
            _send(conn, {"ok": False, "why": why})
            raise ConnectionAbortedError(why)
        blocked = signal.pthread_sigmask(signal.SIG_BLOCK, FORWARDED)
        for stream in (sys.stdout, sys.stderr):
            stream.flush()
        pid = os.fork()
        if pid == 0:  # the child: never returns
            _child(conn, request, fds, (listener, selector, jobs, server.added), blocked)
        signal.pthread_sigmask(signal.SIG_SETMASK, blocked)
        for fd in fds:
            os.close(fd)
        _send(conn, {"ok": True, "pid": pid, "server": os.getpid()})
        conn.settimeout(None)
        jobs[pid] = {"conn": conn, "pidfd": os.pidfd_open(pid), "gone": False, "argv": request["argv"],
                     "cwd": request["cwd"]}
        return pid
    except (OSError, ValueError, KeyError, ConnectionError) as exc:
        if not isinstance(exc, (ConnectionAbortedError, _Empty)):
            _say(f"a request failed: {exc}")
        for fd in fds:
            with contextlib.suppress(OSError):
                os.close(fd)
        conn.close()
        return None


def _child(conn, request: dict, fds: list[int], server_state, blocked) -> None:
    """The forked child: become the job, run it, exit with its status (never returns)."""
    status = 1
    server_pid = os.getppid()
    listener, selector, jobs, added = server_state
    try:
        for sig in FORWARDED + (signal.SIGCHLD,):
            signal.signal(sig, signal.SIG_DFL)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGPIPE, signal.SIG_IGN)  # as Python starts
        _die_with_parent(server_pid)
        for job in jobs.values():  # the other jobs' connections and children are the server's
            job["conn"].close()
            os.close(job["pidfd"])
        selector.close()
        listener.close()
        conn.close()
        for fd, target in zip(fds, request["fds"]):
            os.dup2(fd, target)
            os.close(fd)
        for target in {0, 1, 2} - set(request["fds"]):
            with contextlib.suppress(OSError):
                os.close(target)
        os.chdir(request["cwd"])
        os.umask(request["umask"])
        os.environ.clear()
        os.environ.update(request["environ"])
        os.environ.update(added)
        import resource
        import tempfile

        for name, (soft, hard) in request["limits"].items():
            with contextlib.suppress(ValueError, OSError):
                if list(resource.getrlimit(getattr(resource, name))) != [soft, hard]:
                    resource.setrlimit(getattr(resource, name), (soft, hard))
        if request["nice"] != os.getpriority(os.PRIO_PROCESS, 0):
            os.setpriority(os.PRIO_PROCESS, 0, request["nice"])
        if request.get("affinity") and hasattr(os, "sched_setaffinity"):
            with contextlib.suppress(OSError):
                os.sched_setaffinity(0, request["affinity"])
        tempfile.tempdir = None  # found again from this environment's TMPDIR
        if "numpy" in sys.modules:  # numpy's global generator, seeded from the OS at import in a fresh process
            sys.modules["numpy"].random.seed()
        sys.argv = [request["argv0"], *request["argv"]]
        sys.path[:] = request["path"]
        for stream, fd in ((sys.stdout, 1), (sys.stderr, 2)):
            with contextlib.suppress(Exception):
                stream.reconfigure(line_buffering=fd == 2 or os.isatty(fd))
        _numba_threads_after_fork()
        forkclient.CHILD = f"ran in a fork of the fork server {server_pid} (the job's pid is {os.getpid()})"
        signal.pthread_sigmask(signal.SIG_SETMASK, blocked)
        status = _run(request)
    except SystemExit as exc:
        status = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        if exc.code is not None and not isinstance(exc.code, int):
            print(exc.code, file=sys.stderr)
    except BaseException:  # noqa: BLE001 - reported as the interpreter reports an uncaught exception
        import traceback

        with contextlib.suppress(Exception):
            traceback.print_exc()
        status = 1
    finally:
        with contextlib.suppress(BaseException):
            import atexit

            atexit._run_exitfuncs()
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(BaseException):
                stream.flush()
        os._exit(status if isinstance(status, int) else 1)


def _run(request: dict) -> int:
    if request["entry"] == "cli":
        from ..cli import main

        return main(request["argv"])
    if request["entry"] == "probe":
        from ..startup_probe import main

        return main(request["argv"])
    raise ValueError(f"unknown entry {request['entry']!r}")


def _numba_threads_after_fork() -> None:
    """Numba's OpenMP threading layer as this process's own.

    Loading a cached parallel kernel launches numba's threading layer (``_launch_threads``), which for the
    OpenMP layer sets its thread count (``omp_set_num_threads``) and records the launching pid; its
    ``parallel_for`` then terminates a direct child of that pid ("fork() called from a process already
    using GNU OpenMP"), since GNU OpenMP's thread pool does not survive a fork. The server has run no
    parallel region (:func:`preload` checks that no thread was started), so there is no pool to lose: the
    child calls the layer's ``launch_threads`` again, with the count numba's own launch used, which
    records the child's pid and sets what the first launch set."""
    parallel = sys.modules.get("numba.np.ufunc.parallel")
    if parallel is None or not parallel._is_initialized or parallel._threading_layer != "omp":
        return
    from ctypes import CFUNCTYPE, c_int

    from numba.np.ufunc import omppool

    CFUNCTYPE(None, c_int)(omppool.launch_threads)(parallel.NUM_THREADS)


def _die_with_parent(server_pid: int) -> None:
    """SIGTERM this process when the server dies (Linux's PR_SET_PDEATHSIG)."""
    import ctypes

    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGTERM), 0, 0, 0)  # PR_SET_PDEATHSIG
    if os.getppid() != server_pid:  # it died before the line above
        os._exit(143)


# ----------------------------------------------------------------------------------------------
# start / stop / run (the command line)
# ----------------------------------------------------------------------------------------------

DEFAULT_KEYS = ("1", "1-spin", "2")  # the rules' thread counts on the default 2-core run; the lift spins


def start(folder: Path, keys: tuple[str, ...] = DEFAULT_KEYS, wait_s: float = 300.0) -> list[int]:
    """Start one server per key in the background (each in its own session; its messages in
    ``folder/<key>.log``) and wait until each listens. Returns their pids."""
    import subprocess

    check_folder(folder)
    procs = []
    for key in keys:
        _key_settings(key)
        log = open(folder / f"{key}.log", "ab")  # noqa: SIM115 - handed to the child
        procs.append((key, subprocess.Popen([sys.executable, "-m", "trace3d.tooling.forkserver", "run", str(folder),
                                             key], stdin=subprocess.DEVNULL, stdout=log, stderr=log,
                                            start_new_session=True)))
        log.close()
    deadline = time.monotonic() + wait_s
    for key, proc in procs:
        while not _answers(folder / f"{key}.sock"):
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"the fork server {key} did not start (exit {proc.poll()}); see {folder / key}.log")
            time.sleep(0.1)
    return [proc.pid for _, proc in procs]


def _answers(path: Path) -> bool:
    try:
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        probe.connect(str(path))
        probe.close()
        return True
    except OSError:
        return False


def stop(folder: Path, wait_s: float = 30.0) -> int:
    """SIGTERM every server of ``folder`` and wait for them to leave. Returns how many were stopped."""
    pids = []
    for pid_path in sorted(folder.glob("*.pid")) if folder.is_dir() else []:
        with contextlib.suppress(OSError, ValueError):
            pid = int(pid_path.read_text())
            cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
            if b"trace3d.tooling.forkserver" in cmdline:  # not a recycled pid
                os.kill(pid, signal.SIGTERM)
                pids.append(pid)
    stopped = len(pids)
    deadline = time.monotonic() + wait_s
    while pids and time.monotonic() < deadline:
        pids = [p for p in pids if not _ended(p)]
        time.sleep(0.05)
    for pid in pids:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    return stopped


def _ended(pid: int) -> bool:
    """Whether ``pid`` has ended (reaped here when it is this process's child, so that its CPU time counts
    in this process's children's)."""
    try:
        return os.waitpid(pid, os.WNOHANG)[0] == pid
    except ChildProcessError:
        return not Path(f"/proc/{pid}").exists() or _zombie(pid)


def _zombie(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except (OSError, IndexError):
        return True


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m trace3d.tooling.forkserver",
                                     description="the fork server of the trace3d command (docs/performance.md)")
    sub = parser.add_subparsers(dest="action", required=True)
    p = sub.add_parser("start", help="start servers in the background, one per key, and wait until they listen")
    p.add_argument("folder")
    p.add_argument("--keys", nargs="+", default=list(DEFAULT_KEYS),
                   help="<threads>[-spin] or default[-spin] (default: %(default)s)")
    p = sub.add_parser("stop", help="stop the folder's servers")
    p.add_argument("folder")
    p = sub.add_parser("run", help="run one server in this process (what `start` runs)")
    p.add_argument("folder")
    p.add_argument("key")
    p.add_argument("--idle", type=float, default=3600.0, help="leave after this many seconds without a job")
    args = parser.parse_args(argv)
    folder = Path(args.folder).absolute()
    try:
        if args.action == "start":
            pids = start(folder, tuple(args.keys))
            print(f"fork servers {' '.join(args.keys)} listening in {folder} (pids {' '.join(map(str, pids))}); "
                  f"export {ENV_VAR}={folder}")
            return 0
        if args.action == "stop":
            print(f"stopped {stop(folder)} fork server(s) in {folder}")
            return 0
        return serve(folder, args.key, args.idle)
    except (RuntimeError, PermissionError, ValueError) as exc:
        print(f"trace3d fork server: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    # run as the package's module, not as __main__: the forked child's state (CHILD) is read through it
    from trace3d.tooling import forkserver

    sys.exit(forkserver.main())
