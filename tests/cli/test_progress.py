"""``trace3d progress``: jobs done / left, the time estimate and the tables, read from a Snakemake log."""

import datetime as dt
import os
import subprocess
import sys
from pathlib import Path

from trace3d.progress import estimate, newest_log, parse_log, progress_text

REPO = str(Path(__file__).resolve().parents[2])
T0 = dt.datetime(2026, 11, 28, 21, 0, 0)


def _stamp(minutes: float) -> str:
    return "[" + (T0 + dt.timedelta(minutes=minutes)).strftime("%a %b %d %H:%M:%S %Y").replace(" 0", "  ", 1) + "]"


def _start(minutes, rule, jobid, threads=None, local=False):
    lines = [_stamp(minutes), f"{'local' if local else ''}rule {rule}:", f"    output: results/x/{rule}{jobid}",
             f"    jobid: {jobid}"]
    if threads:
        lines.append(f"    threads: {threads}")
    lines.append("    resources: tmpdir=/tmp, mem_mb=1000, mem_mib=954, runtime=5")
    return lines


def _finish(minutes, rule, jobid, done, total):
    return [_stamp(minutes), f"Finished jobid: {jobid} (Rule: {rule})",
            f"{done} of {total} steps ({done * 100 // total}%) done"]


def _log(tmp_path, body, stats):
    head = ["Assuming unrestricted shared filesystem usage.", "host: vm", "Building DAG of jobs...",
            "Provided cores: 2", "Job stats:", "job          count", "---------  -------"]
    head += [f"{rule:<10} {n:>6}" for rule, n in stats.items()]
    head += [f"{'total':<10} {sum(stats.values()):>6}", "", "Select jobs to execute..."]
    log = tmp_path / ".snakemake" / "log" / "2026-11-28T210000.000000.snakemake.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    log.write_text("\n".join(head + body) + "\n")
    return log


STATS = {"evaluate": 4, "lift": 2, "tables": 1}


def _running_log(tmp_path):
    body = (_start(0, "lift", 1, threads=2) + _finish(10, "lift", 1, 1, 7)
            + _start(10, "lift", 2, threads=2)
            + _start(10, "evaluate", 3) + _finish(11, "evaluate", 3, 2, 7)
            + _start(11, "evaluate", 4) + _finish(14, "evaluate", 4, 3, 7)
            + _start(14, "evaluate", 5))
    return _log(tmp_path, body, STATS)


def test_parse_log_reads_jobs_threads_and_counts(tmp_path):
    run = parse_log(_running_log(tmp_path))
    assert run.cores == 2 and run.counts == STATS and (run.done, run.total) == (3, 7)
    assert run.jobs[1].threads == 2 and run.jobs[3].threads == 1
    assert run.jobs[1].end - run.jobs[1].start == 600
    assert run.jobs[2].end is None and not run.failed and not run.complete


def test_estimate_uses_each_rules_finished_jobs(tmp_path):
    run = parse_log(_running_log(tmp_path))
    now = (T0 + dt.timedelta(minutes=15)).timestamp()
    est = estimate(run, now)
    assert est["left"] == {"evaluate": 2, "lift": 1, "tables": 1}
    assert est["running"] == {"evaluate": 1, "lift": 1}
    assert est["unestimated"] == {"tables": 1}
    # evaluate: mean 2 min x 1 core; one waiting (120 s), one running for 1 min (60 s left);
    # lift: 10 min x 2 cores = 1200 core-s, running for 5 min x 2 cores (600 left); over 2 cores
    assert est["seconds"] == (120 + 60 + 600) / 2


def test_progress_text_says_what_is_left_and_which_tables_are_done(tmp_path):
    log = _running_log(tmp_path)
    results = tmp_path / "results"
    (results / "tables").mkdir(parents=True)
    (results / "tables" / "effects.md").write_text("x")  # not in this run's jobs: from an earlier run
    now = (T0 + dt.timedelta(minutes=15)).timestamp()
    text = progress_text(results, log, now=now)
    assert "jobs: 3 of 7 done, 2 running, 2 waiting (running)" in text
    assert "left by rule: evaluate 2 (1 running), lift 1 (1 running), tables 1" in text
    assert "time left: about 6 min" in text and "tables 1 job(s) of rules with no finished job yet" in text
    assert "waiting  Table 2 (3D object extraction)" in text
    assert "study effects" in text and "before this run" in text
    assert "robustness" not in text  # neither planned nor on disk


def test_finished_run_and_written_tables(tmp_path):
    stats = {"evaluate": 1, "tables": 1}
    body = (_start(0, "evaluate", 1) + _finish(2, "evaluate", 1, 1, 2) + _start(2, "tables", 2)
            + _finish(3, "tables", 2, 2, 2) + ["Complete log(s): x.log"])
    log = _log(tmp_path, body, stats)
    results = tmp_path / "results"
    (results / "tables").mkdir(parents=True)
    for name in ("table2.md", "table3.md", "table5.md"):
        (results / "tables" / name).write_text("x")
    text = progress_text(results, log)
    assert "jobs: 2 of 2 done, 0 running, 0 waiting (finished)" in text
    assert "time left" not in text
    assert "done     Table 2 (3D object extraction)" in text and "done     Table 3" in text


def test_rules_without_a_finished_job_take_earlier_runs_times(tmp_path):
    """The second run of `make reproduce` (reproduce) learns the lift's time from the first (paper_tables);
    a rule without a command (the targets) costs nothing."""
    logs = tmp_path / ".snakemake" / "log"
    logs.mkdir(parents=True)
    first = _log(tmp_path, _start(0, "lift", 1, threads=2) + _finish(6, "lift", 1, 1, 2)
                 + _start(6, "paper_tables", 2, local=True) + _finish(6, "paper_tables", 2, 2, 2)
                 + ["Complete log(s): x.log"], {"lift": 1, "paper_tables": 1})
    first.rename(logs / "2026-11-28T200000.000000.snakemake.log")
    second = _log(tmp_path, _start(0, "evaluate", 3) + _finish(2, "evaluate", 3, 1, 5),
                  {"lift": 2, "evaluate": 2, "reproduce": 1})
    now = (T0 + dt.timedelta(minutes=2)).timestamp()
    text = progress_text(tmp_path / "results", second, now=now)
    # lift: 6 min x 2 cores each (earlier run), evaluate: 2 min; (2 x 720 + 120) / 2 cores = 13 min
    assert "time left: about 13 min" in text, text
    assert "no job of lift has finished in this run" in text
    assert "reproduce" not in text.split("time left")[1].split("\n")[0]


def test_failed_job_is_counted(tmp_path):
    body = (_start(0, "evaluate", 1) + [_stamp(1), "Error in rule evaluate:", "    message: x", "    jobid: 1",
                                        "    log: x.log (check log file(s) for error details)"])
    run = parse_log(_log(tmp_path, body, {"evaluate": 1}))
    assert run.failed == {1}
    assert "1 failed" in progress_text(tmp_path / "results", run.path)


def test_every_rule_estimated_gives_an_end_time(tmp_path):
    body = _start(0, "evaluate", 1) + _finish(4, "evaluate", 1, 1, 3)
    log = _log(tmp_path, body, {"evaluate": 3})
    now = (T0 + dt.timedelta(minutes=4)).timestamp()
    text = progress_text(tmp_path / "results", log, now=now)
    assert "time left: about 4 min, until about 21:08" in text  # 2 jobs x 4 min / 2 cores


def test_report_logs_are_not_runs(tmp_path):
    run_log = _running_log(tmp_path)
    report = run_log.parent / "2026-11-28T220000.000000.snakemake.log"
    report.write_text("Building DAG of jobs...\nCreating report...\nReport created.\n")
    assert newest_log(tmp_path) == run_log
    report.unlink()
    lint = run_log.parent / "2026-11-28T221000.000000.snakemake.log"
    lint.write_text("Congratulations, your workflow is in a good condition!\n")
    assert newest_log(tmp_path) == run_log
    nothing = run_log.parent / "2026-11-28T230000.000000.snakemake.log"
    nothing.write_text("Building DAG of jobs...\n"
                       "Nothing to be done (all requested files are present and up to date).\n")
    assert newest_log(tmp_path) == nothing
    assert "nothing to be done" in progress_text(tmp_path / "results", workdir=tmp_path)


def test_cli_without_a_log_is_one_sentence(tmp_path):
    env = {**os.environ, "PYTHONPATH": REPO}
    result = subprocess.run([sys.executable, "-m", "trace3d.cli", "progress", str(tmp_path / "results")],
                            cwd=tmp_path, capture_output=True, text=True, env=env, timeout=120)
    assert result.returncode == 2, result.stderr
    assert "no Snakemake log there" in result.stderr and "Traceback" not in result.stderr


def test_cli_prints_the_progress(tmp_path):
    _running_log(tmp_path)
    env = {**os.environ, "PYTHONPATH": REPO}
    result = subprocess.run([sys.executable, "-m", "trace3d.cli", "progress"], cwd=tmp_path, capture_output=True,
                            text=True, env=env, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "jobs: 3 of 7 done" in result.stdout
