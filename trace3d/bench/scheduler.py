"""``trace3d bench scheduler``: Snakemake's own CPU time on a workflow of many ready jobs, with and without
its job-rate limiter (trace3d/tooling/scheduling.py, which the Snakefile's ``onstart`` applies).

A generated workflow (in a temporary folder) of ``jobs`` independent jobs, each a shell that sleeps
``seconds``, runs twice at ``--cores 2``: once as Snakemake leaves it (``--max-jobs-per-timespan`` at its
default, 100/1s) and once with :func:`trace3d.tooling.scheduling.unthrottle_local` called from its
``onstart``, as this project's Snakefile does. Each job has a params function that spends ``params_ms``
of CPU (this pipeline's merge JSON parameters per variant) and ``inputs`` input files (this pipeline's
lifts and evaluations have 4-6): on every pass the scheduler re-evaluates the params of every ready job
and reads the existence and size of every input of every ready job. The jobs sleep, so what the run
costs is the scheduler's.

Per run: wall seconds, CPU seconds of the Snakemake process (``os.wait4``'s user + system time, which also
holds the reaped shells: about 3 ms each) and the most threads the process had (sampled every 0.25 s;
the limiter's re-evaluation timers are threads).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SNAKEFILE = '''\
import os, time

N = int(os.environ["T3D_BENCH_JOBS"])
SECONDS = float(os.environ["T3D_BENCH_SECONDS"])
PARAMS_S = float(os.environ["T3D_BENCH_PARAMS_MS"]) / 1000.0
INPUTS = int(os.environ["T3D_BENCH_INPUTS"])

onstart:
    if os.environ.get("T3D_BENCH_UNTHROTTLE") == "1":
        from trace3d.tooling.scheduling import unthrottle_local

        unthrottle_local(workflow)


def cost(wildcards):
    t = time.thread_time()
    while time.thread_time() - t < PARAMS_S:
        pass
    return wildcards.i


rule all:
    input:
        expand("out/{i}.txt", i=range(N)),


rule one:
    input:
        [f"in/{{i}}-{k}.txt" for k in range(INPUTS)],
    output:
        "out/{i}.txt",
    params:
        p=cost,
    shell:
        "sleep {SECONDS}; echo {params.p} > {output}"
'''


def _run(folder: Path, unthrottle: bool, jobs: int, seconds: float, params_ms: float, inputs: int) -> dict:
    env = {**os.environ, "T3D_BENCH_JOBS": str(jobs), "T3D_BENCH_SECONDS": str(seconds),
           "T3D_BENCH_PARAMS_MS": str(params_ms), "T3D_BENCH_INPUTS": str(inputs),
           "T3D_BENCH_UNTHROTTLE": "1" if unthrottle else "0"}
    (folder / "in").mkdir()
    for i in range(jobs):
        for k in range(inputs):
            (folder / "in" / f"{i}-{k}.txt").write_text("x")
    start = time.perf_counter()
    # stderr to a file, not a pipe: nobody reads a pipe while the loop below polls, and a full one would block
    log = folder / "snakemake.log"
    with log.open("w") as err:
        proc = subprocess.Popen([sys.executable, "-m", "snakemake", "--cores", "2", "all", "--quiet"],
                                cwd=folder, env=env, stdout=subprocess.DEVNULL, stderr=err)
    peak_threads = 0
    while True:
        waited, status, usage = os.wait4(proc.pid, os.WNOHANG)
        if waited:
            break
        try:
            peak_threads = max(peak_threads, len(os.listdir(f"/proc/{proc.pid}/task")))
        except OSError:
            pass
        time.sleep(0.25)
    wall = time.perf_counter() - start
    code = os.waitstatus_to_exitcode(status)
    proc.returncode = code  # reaped by wait4: keep Popen from waiting for it again
    if code != 0:
        raise RuntimeError(f"the benchmark workflow failed (exit {code}): {log.read_text()[-2000:]}")
    made = len(list((folder / "out").glob("*.txt")))
    if made != jobs:
        raise RuntimeError(f"the benchmark workflow made {made} of {jobs} files")
    return {"wall_s": round(wall, 2), "cpu_s": round(usage.ru_utime + usage.ru_stime, 2),
            "peak_threads": peak_threads}


def run_bench(jobs: int = 200, seconds: float = 0.5, params_ms: float = 0.4, inputs: int = 6) -> dict:
    """Both runs, each in a fresh folder, the default one first; one JSON-able dict."""
    result = {"jobs": jobs, "job_seconds": seconds, "params_ms": params_ms, "inputs_per_job": inputs, "cores": 2,
              "load_before": round(os.getloadavg()[0], 2)}
    for name, unthrottle in (("snakemake_default", False), ("limiter_off", True)):
        with tempfile.TemporaryDirectory(prefix="t3d-bench-scheduler-") as tmp:
            Path(tmp, "Snakefile").write_text(SNAKEFILE)
            result[name] = _run(Path(tmp), unthrottle, jobs, seconds, params_ms, inputs)
    result["load_after"] = round(os.getloadavg()[0], 2)
    d, o = result["snakemake_default"], result["limiter_off"]
    result["cpu_ratio"] = round(d["cpu_s"] / o["cpu_s"], 2) if o["cpu_s"] else None
    return result
