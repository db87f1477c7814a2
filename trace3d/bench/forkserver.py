"""``trace3d bench forkserver``: a job's CPU and wall time to its first line, with and without the fork server.

For each pipeline step (or ``--quick``: ``tables`` and ``evaluate``), ``--rounds`` times each way, the
probe of ``trace3d bench startup`` (:mod:`trace3d.startup_probe`: the entry point's work, the step's imports,
then every cached kernel of its code) runs

    in-process   as a fresh ``python -m trace3d.startup_probe <step>``, as every job does without a server;
    forked       as a fresh ``python -m trace3d.startup_probe <step> --server``: a job's process that hands
                 the probe to a fork of a server (:mod:`trace3d.tooling.forkserver`, key ``default``)
                 started for the benchmark, and waits for it.

Per way, the medians of: ``job_cpu_s``, the CPU of the job's own process over its whole life (this
process's children's user + system time around it, ``getrusage``); ``first_line_cpu_s`` and ``kernels_cpu_s``
as the probe measures them (in-process: the job's process from its start; forked: the server's child,
whose CPU clock starts at the fork); ``to_first_line_cpu_s``, what a job costs up to its first line and
kernels (in-process: the probe's first line and kernels; forked: the job's process, the child's first
line and kernels, and the server's CPU per job besides them, ``server_per_job_cpu_s``: its checks of the
request, the fork, the child's exit); and ``first_line_wall_s`` from the spawn. The server's start (its
imports and kernel loads, paid once per run and key, from its log) is ``server_start_cpu_s``.
"""

from __future__ import annotations

import json
import os
import re
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _spawn(command: str, env: dict, server: bool) -> dict:
    from ..errors import Trace3DError

    cpu = _children_cpu()
    spawn = time.time()
    proc = subprocess.run([sys.executable, "-m", "trace3d.startup_probe", command, repr(spawn),
                           *(["--server"] if server else [])], capture_output=True, text=True, env=env, timeout=600)
    job_cpu = _children_cpu() - cpu
    if proc.returncode != 0:
        raise Trace3DError(f"bench forkserver: the probe of {command!r} failed (exit {proc.returncode}): "
                           f"{proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else 'no message'}")
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    if result["forked"] != server:
        raise Trace3DError(f"bench forkserver: the probe of {command!r} ran {'out of' if server else 'in'} the "
                           f"server against the benchmark's intent: {proc.stderr.strip()[-300:]}")
    first, kernels = result["first_line"], result["kernels"]
    to_first = first["cpu_s"] + kernels["cpu_s"] + (job_cpu if server else 0.0)
    return {"job_cpu_s": job_cpu, "first_line_cpu_s": first["cpu_s"], "kernels_cpu_s": kernels["cpu_s"],
            "to_first_line_cpu_s": to_first, "first_line_wall_s": first["wall_s"], "compiled": kernels["compiled"]}


def _wait_listening(path: Path, server: subprocess.Popen, timeout_s: float = 300.0) -> None:
    import socket

    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
                probe.connect(str(path))
            return
        except OSError:
            if server.poll() is not None or time.monotonic() > deadline:
                from ..errors import Trace3DError

                why = server.stderr.read().strip()[-300:] if server.poll() is not None else "no answer"
                raise Trace3DError(f"bench forkserver: the fork server did not start: {why}") from None
            time.sleep(0.05)


def _medians(runs: list[dict]) -> dict:
    keys = ("job_cpu_s", "first_line_cpu_s", "kernels_cpu_s", "to_first_line_cpu_s", "first_line_wall_s")
    out = {k: round(statistics.median(r[k] for r in runs), 3) for k in keys}
    out["compiled"] = runs[-1]["compiled"]
    return out


def run_bench(rounds: int = 3, commands: list[str] | None = None) -> dict:
    """Both ways for every pipeline command (or ``commands``), ``rounds`` times each, alternating."""
    from ..errors import Trace3DError
    from ..tooling.cputarget import describe
    from ..tooling.forkclient import ENV_VAR
    from .startup import pipeline_commands

    known = pipeline_commands()
    commands = list(commands or known)
    if [c for c in commands if c not in known] or rounds < 1:
        raise Trace3DError(f"bench forkserver: give --rounds >= 1 and steps among {', '.join(known)}.")
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.pop(ENV_VAR, None)
    load_before = os.getloadavg()
    folder = Path(tempfile.mkdtemp(prefix="trace3d-bench-")) / "s"
    folder.mkdir(mode=0o700)
    cpu = _children_cpu()
    # the server as this process's child (`python -m trace3d.tooling.forkserver run`), in the jobs' environment:
    # its CPU and its children's count in this process's children's once it is reaped
    server = subprocess.Popen([sys.executable, "-m", "trace3d.tooling.forkserver", "run", str(folder), "default"],
                              stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                              env=env)
    try:
        _wait_listening(folder / "default.sock", server)
        served = {**env, ENV_VAR: str(folder)}
        runs: dict[str, dict[str, list]] = {c: {"in_process": [], "forked": []} for c in commands}
        for _ in range(rounds):
            for command in commands:
                runs[command]["in_process"].append(_spawn(command, env, server=False))
                runs[command]["forked"].append(_spawn(command, served, server=True))
    finally:
        server.terminate()
        _, log = server.communicate(timeout=60)
        shutil.rmtree(folder.parent, ignore_errors=True)
    jobs_cpu = sum(r["job_cpu_s"] for c in commands for r in runs[c]["in_process"] + runs[c]["forked"])
    total = _children_cpu() - cpu - jobs_cpu  # the server and its children, reaped with it
    children = sum(r["first_line_cpu_s"] + r["kernels_cpu_s"] for c in commands for r in runs[c]["forked"])
    preload = float(re.search(r"preload ([0-9.]+) s CPU", log).group(1))
    # the server's CPU per forked job besides the child's first line and kernels: its checks, the fork, the
    # child's exit; counted into the forked jobs' cost
    per_job = max(total - preload - children, 0.0) / (rounds * len(commands))
    for c in commands:
        for r in runs[c]["forked"]:
            r["to_first_line_cpu_s"] += per_job
    out = {c: {way: _medians(runs[c][way]) for way in ("in_process", "forked")} for c in commands}
    for c in commands:
        out[c]["saved_cpu_s"] = round(out[c]["in_process"]["to_first_line_cpu_s"]
                                      - out[c]["forked"]["to_first_line_cpu_s"], 3)
    mean = {way: round(statistics.mean(out[c][way]["to_first_line_cpu_s"] for c in commands), 3)
            for way in ("in_process", "forked")}
    return {"cpu": describe(), "python": sys.version.split()[0], "rounds": rounds,
            "numba_cache": os.environ.get("NUMBA_CACHE_DIR"), "loadavg_before": load_before,
            "loadavg_after": os.getloadavg(), "server_start_cpu_s": preload,
            "server_per_job_cpu_s": round(per_job, 3), "mean_to_first_line_cpu_s": mean, "commands": out}
