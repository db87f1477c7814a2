"""A real SLURM cluster runs the pipeline: a one-room tiny config through
``snakemake --profile workflow/profiles/slurm`` gives the same files as a local run.

Runs when a cluster answers (``sbatch`` on PATH and ``sinfo`` shows an idle node;
``bash tests/slurm/start.sh`` as root starts a one-node one, ``.ci/run`` does so before the suite)
and skips, naming why, otherwise.  Every rule but the local ones (the target and two copies) runs as
its own SLURM job: a process of its own, started by sbatch from a directory that is not the
workflow's, that reads only its declared inputs.  What each job asked SLURM for (CPUs, memory, time
limit) is read back from ``squeue`` and compared with the rule's ``threads``, ``mem_mb`` and
``runtime``; that SLURM enforces a memory request is checked by a job that exceeds it.  Both runs use
the suite's numba cache (a cold compile of every kernel takes 10-30 min on the 2-core machine; that
the jobs compile what a cold cache lacks was run by hand, docs/cluster.md).
"""

from __future__ import annotations

import csv
import hashlib
import importlib.util
import io
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from trace3d.io import MANIFEST

REPO = Path(__file__).resolve().parents[2]
PROFILE = REPO / "workflow" / "profiles" / "slurm"
SNAKEMAKE = shutil.which("snakemake", path=str(Path(sys.executable).parent)) or shutil.which("snakemake")


def _cluster_missing() -> str | None:
    """Why no SLURM cluster can run jobs here (None when one can)."""
    if shutil.which("sbatch") is None or shutil.which("sinfo") is None:
        return "no SLURM here (sbatch/sinfo not on PATH); `bash tests/slurm/start.sh` as root starts a one-node cluster"
    try:
        out = subprocess.run(["sinfo", "-h", "-N", "-o", "%N %T"], capture_output=True, text=True, timeout=20)
    except subprocess.TimeoutExpired:
        return "sinfo did not answer within 20 s (slurmctld not running? `bash tests/slurm/start.sh`)"
    if out.returncode != 0:
        return (f"sinfo failed: {(out.stderr or out.stdout).strip()[:300]} "
                "(`bash tests/slurm/start.sh` starts the cluster)")
    states = out.stdout.split()
    if not any(s.rstrip("*~#").startswith(("idle", "mixed", "allocated")) for s in states[1::2]):
        return f"no SLURM node can run jobs (sinfo: {out.stdout.strip() or 'no nodes'})"
    return None


MISSING = _cluster_missing() if SNAKEMAKE is not None else "snakemake is not installed"
pytestmark = [pytest.mark.slow, pytest.mark.skipif(MISSING is not None, reason=f"SLURM test skipped: {MISSING}")]

# One room, one variant, the steps shrunk to seconds (the sizes of tests/workflow/test_workflow.py's tiny run).
TINY_CONFIG = {
    "defaults": {
        "synthetic": {"width": 48, "height": 36, "num_views": 6, "test_every": 3, "num_objects": 10,
                      "supersample": 1},
        "poses": {"mode": "dataset"},
        "masks": {"source": "simulated", "simulated": {"inconsistency": 0.5}},
        "gaussians": {"schedule_scale": 1.0, "iterations": 40, "densify_from": 10, "densify_until": 30,
                      "densify_interval": 10, "normal_from": 20, "sh_degree": 1, "sh_degree_interval": 20,
                      "device": "cpu"},
        "refine": {"iterations": 20, "detect_at": [1, 10], "schedule_scale": 1.0, "highlight_views": 1},
        "lift": {"iterations": 30, "pixels": 256, "pool_pixels": 512, "pca_views": 1},
        "evaluate": {"min_pixels": 20, "turntable_views": 3, "turntable_size": 32},
    },
    "variants": {"full": {}},
    "scenes": {"a": {"kind": "synthetic", "synthetic": {"seed": 1}}},
}

# Files that record wall-clock time, so differ between any two runs. logs/ and benchmarks/ (Snakemake's
# per-step logs and timings) and two summaries of them (reconstruction.md and its figure show the fit's
# minutes, tracing.md the merge's seconds and the refine's minutes) are left out; the JSON and CSV files
# below are compared without their time fields; every other file must be byte-identical.
TIMED_PREFIXES = ("logs/", "benchmarks/")
TIMED_FILES = {"reconstruction.md", "plots/reconstruction.png", "tracing.md"}
TIME_FIELD = re.compile(r"seconds|minutes|(^| )(s|min)$")


def _without_times(path: Path):
    """The file's content without its wall-clock fields (JSON keys, CSV columns named like TIME_FIELD)."""
    if path.suffix == ".json":
        def strip(value):
            if isinstance(value, dict):
                return {k: strip(v) for k, v in value.items() if not TIME_FIELD.search(k)}
            if isinstance(value, list):
                return [strip(v) for v in value]
            return value
        return strip(json.loads(path.read_text()))
    if path.suffix == ".csv":
        rows = list(csv.reader(io.StringIO(path.read_text())))
        keep = [i for i, name in enumerate(rows[0]) if not TIME_FIELD.search(name)]
        assert len(keep) < len(rows[0]), f"{path} differs but has no time column"
        return [[row[i] for i in keep] for row in rows]
    raise AssertionError(f"{path} differs between the runs and records no wall-clock time")


def _env(numba_cache: Path) -> dict:
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env["NUMBA_CACHE_DIR"] = str(numba_cache)
    for var in list(env):  # a pytest started inside a SLURM job must not hand its allocation on
        if var.startswith(("SLURM_", "SBATCH_", "SRUN_")):
            del env[var]
    return env


def _snakemake(workdir: Path, *args: str, env: dict, cwd: Path, timeout: int):
    cmd = [SNAKEMAKE, "-s", str(REPO / "Snakefile"), "--directory", str(workdir),
           "--configfile", str(workdir / "config.yaml"), *args]
    return subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=cwd, timeout=timeout)


def _digests(results: Path) -> dict[str, str]:
    return {p.relative_to(results).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(results.rglob("*")) if p.is_file()}


def _job_blocks(log: str):
    """(rule, threads, block) of every job a Snakemake log lists (no ``threads:`` line: 1)."""
    for block in re.split(r"\n(?=\[[^\n]*\]\n(?:local)?rule )", log):
        head = re.search(r"^(?:local)?rule (\w+):", block, flags=re.M)
        if head:
            threads = re.search(r"^\s+threads: (\d+)", block, flags=re.M)
            yield head.group(1), int(threads.group(1)) if threads else 1, block


def _planned_resources(dry_run: str) -> dict[str, tuple[int, int, int]]:
    """rule -> (threads, mem_mb, runtime minutes) of every job a dry run with the profile lists."""
    plan = {}
    for rule, threads, block in _job_blocks(dry_run):
        resources = re.search(r"^\s+resources: (.*)$", block, flags=re.M)
        if not resources:
            continue
        mem = re.search(r"\bmem_mb=(\d+)", resources.group(1))
        runtime = re.search(r"\bruntime=(\d+)", resources.group(1))
        plan[rule] = (threads, int(mem.group(1)), int(runtime.group(1)))
    return plan


def _minutes(limit: str) -> int:
    """squeue's time limit ([days-]hours:minutes:seconds | minutes:seconds) in minutes."""
    days, _, clock = limit.rpartition("-")
    parts = [int(x) for x in clock.split(":")]
    while len(parts) < 3:
        parts.insert(0, 0)
    hours, minutes, seconds = parts
    return (int(days or 0) * 24 + hours) * 60 + minutes + (seconds > 0)


def _jobs_of_run(run_id: str) -> list[dict]:
    fmt = "%i|%k|%C|%m|%l|%T"
    out = subprocess.run(["squeue", "--states=all", "--noheader", "--name", run_id, "--format", fmt],
                         capture_output=True, text=True, timeout=30, check=True).stdout
    keys = ("id", "comment", "cpus", "mem", "limit", "state")
    return [dict(zip(keys, line.split("|"))) for line in out.splitlines() if line.strip()]


@pytest.mark.xdist_group("slurm")  # beside the whole-DAG group, on the other worker (tests/conftest.py)
def test_slurm_run_equals_local_run(tmp_path):
    assert importlib.util.find_spec("snakemake_executor_plugin_slurm") is not None, (
        "SLURM is up but snakemake-executor-plugin-slurm is not installed: pip install -r requirements.txt")
    local, cluster, elsewhere = tmp_path / "local", tmp_path / "slurm", tmp_path / "elsewhere"
    for d in (local, cluster, elsewhere):
        d.mkdir()
        (d / "config.yaml").write_text(yaml.safe_dump(TINY_CONFIG))

    # the local reference, on the suite's shared numba cache; it runs while the cluster's run below
    # spends most of its time waiting on the executor's status polls
    env_local = _env(Path(os.environ.get("NUMBA_CACHE_DIR", REPO / ".numba_cache")))
    local_log = tmp_path / "local.log"
    with local_log.open("w") as log:
        local_run = subprocess.Popen(
            [SNAKEMAKE, "-s", str(REPO / "Snakefile"), "--directory", str(local), "--configfile",
             str(local / "config.yaml"), "--cores", "2", "reproduce"],
            stdout=log, stderr=subprocess.STDOUT, text=True, env=env_local, cwd=local)
    try:
        _check_against_local(local, local_run, local_log, cluster, elsewhere, env_local)
    finally:
        if local_run.poll() is None:
            local_run.kill()
            local_run.wait()


def _check_against_local(local, local_run, local_log, cluster, elsewhere, env_local):
    # what each job will ask for: the dry run's threads and resources (the profile's defaults included)
    dry = _snakemake(cluster, "--profile", str(PROFILE), "-n", "reproduce", env=env_local, cwd=elsewhere, timeout=300)
    assert dry.returncode == 0, dry.stderr[-4000:]
    planned = _planned_resources(dry.stdout + dry.stderr)

    # the SLURM run, started from another directory (the jobs find the workflow's through sbatch -D)
    start = time.monotonic()
    ran = _snakemake(cluster, "--profile", str(PROFILE), "--slurm-init-seconds-before-status-checks", "2",
                     "--slurm-keep-successful-logs", "reproduce", env=env_local, cwd=elsewhere, timeout=1500)
    cluster_s = time.monotonic() - start
    output = ran.stdout + ran.stderr
    assert ran.returncode == 0, output[-6000:]
    run_id = re.search(r"SLURM run ID: (\S+)", output).group(1)
    assert local_run.wait(timeout=900) == 0, local_log.read_text()[-4000:]
    print(f"SLURM run {cluster_s:.0f} s (run {run_id}), the local run beside it")

    # every rule but the local ones (a target and two copies) ran as a SLURM job that asked for the
    # rule's threads, mem_mb and runtime
    local_rules = set(re.findall(r"^localrule (\w+):", output, flags=re.M))
    assert local_rules == {"reproduce", "evaluation_pictures", "lift_pictures"}, local_rules
    for rule in local_rules:
        planned.pop(rule)
    assert {"scene", "poses", "masks", "patches", "gaussians", "trace", "merge", "refine", "lift", "evaluate",
            "evaluate_official", "tables", "tables_paper_rows", "tables_official", "scenes_table",
            "reconstruction_table", "tracing_table"} == set(planned), sorted(planned)
    jobs = _jobs_of_run(run_id)
    assert all(j["state"] == "COMPLETED" for j in jobs), jobs
    by_rule = {re.match(r"rule_(\w+?)(?:_wildcards_|$)", j["comment"]).group(1): j for j in jobs}
    assert set(by_rule) == set(planned), (sorted(by_rule), sorted(planned))
    assert len(jobs) == len(planned)
    for rule, (threads, mem_mb, runtime) in planned.items():
        job = by_rule[rule]
        assert int(job["cpus"]) == threads, (rule, job)
        assert job["mem"] == f"{mem_mb}M", (rule, job)
        assert _minutes(job["limit"]) == runtime, (rule, job)
    # rules/gaussians.smk: mem_mb 4000, runtime 60; threads 1 there, 2 in the profile (set-threads)
    assert (by_rule["gaussians"]["cpus"], by_rule["gaussians"]["mem"], by_rule["gaussians"]["limit"]) == \
        ("2", "4000M", "1:00:00")
    assert by_rule["refine"]["cpus"] == "2"
    # the local run fitted and refined on 1 thread: the equal files below are also the training's
    # independence of the thread count, on the real steps
    local_threads = {rule: threads for rule, threads, _ in _job_blocks(local_log.read_text())}
    assert local_threads["gaussians"] == 1 and local_threads["refine"] == 1, local_threads

    # the same files, byte for byte, but for wall-clock times
    a, b = _digests(local / "results"), _digests(cluster / "results")
    assert set(a) == set(b), sorted(set(a) ^ set(b))
    compared = [f for f in a if not f.startswith(TIMED_PREFIXES) and f not in TIMED_FILES]
    timed = [f for f in compared if a[f] != b[f] and not f.endswith(MANIFEST)]
    for f in timed:  # equal once the time fields are dropped
        assert _without_times(local / "results" / f) == _without_times(cluster / "results" / f), f
    # a step's manifest (sizes and SHA-256 of its files) differs exactly where one of its files does: the
    # same step and files, and another hash only for a file just found equal without its time fields
    manifests = [f for f in compared if f.endswith(MANIFEST) and a[f] != b[f]]
    for f in sorted(manifests, key=lambda f: -f.count("/")):  # deepest first: a folder's manifest lists its subfolders'
        ours, theirs = (json.loads((root / "results" / f).read_text()) for root in (local, cluster))
        assert (ours["step"], ours["rules"], set(ours["files"])) == (theirs["step"], theirs["rules"],
                                                                     set(theirs["files"])), f
        folder = f[: -len(MANIFEST)]
        other = {name for name in ours["files"] if ours["files"][name] != theirs["files"][name]}
        assert other and all(folder + name in timed or folder + name in TIMED_FILES for name in other), (f, other)
        timed.append(f)
    print(f"{len(compared)} files compared: {len(compared) - len(timed)} byte-identical, {len(timed)} equal "
          f"without their time fields ({', '.join(timed)})")
    assert len(compared) > 100 and any(f.endswith("point_cloud.ply") for f in compared)
    assert "a/full/lift/features.npy" in compared and "tables/table2.csv" in compared


def test_slurm_kills_a_job_above_its_memory(tmp_path):
    """The cluster enforces --mem (the plugin's mem_mb): a job that fills 800 MB under --mem=200 is killed."""
    script = ("import time; x = bytearray(800 << 20); x[::4096] = b'1' * len(x[::4096]); time.sleep(30); "
              "print('survived')")
    log = tmp_path / "oom.log"
    ran = subprocess.run(["sbatch", "--parsable", "--wait", "--mem=200", "--cpus-per-task=1", "--time=2",
                          "--output", str(log), "--wrap", f"{sys.executable} -c \"{script}\""],
                         capture_output=True, text=True, timeout=120, env=_env(tmp_path))
    assert ran.returncode != 0, ran.stdout + ran.stderr
    text = log.read_text()
    assert "survived" not in text
    assert "memory limit" in text, text
