"""``trace3d progress [RESULTS]``: where a Snakemake run of the pipeline is, read from its log.

Reads the newest ``.snakemake/log/*.snakemake.log`` of the working directory (or ``--log``) and the
results folder, and prints:

- the jobs of that run: in all, finished, running, waiting, failed, and what is left per rule;
- a time estimate: every job left costs the mean wall seconds x cores of the finished jobs of its rule
  in this run, else in the newest earlier run's log that has one (``make reproduce``'s second
  Snakemake run learns from its first), a running job that minus the seconds it has run (at least 0),
  summed and divided by the run's cores; jobs of rules no log has a finished job of are counted and
  named, not guessed, so the estimate is then a lower bound and says so;
- the tables: for each table the run builds, done (and when) or waiting; a table whose rule is not in
  the run is listed as it is on disk (from an earlier run).

Only the text of the log is read (no Snakemake import, nothing written), so it is safe to run beside a
running ``make reproduce``, e.g. ``watch -n 60 trace3d progress``.
"""

from __future__ import annotations

import datetime as _dt
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

from .errors import Trace3DError

# (what the user reads, path under the results folder, the rule that writes it)
TABLES = (
    ("Table 2, the paper's rows (written first)", "tables/paper/table2.md", "tables_paper_rows"),
    ("Table 3, the paper's rows (written first)", "tables/paper/table3.md", "tables_paper_rows"),
    ("Table 5, the paper's rows (written first)", "tables/paper/table5.md", "tables_paper_rows"),
    ("Table 2 (3D object extraction)", "tables/table2.md", "tables"),
    ("Table 3 (novel-view segmentation)", "tables/table3.md", "tables"),
    ("Table 5 (ablation)", "tables/table5.md", "tables"),
    ("Tables 2, 3, 5, official protocol", "tables/official/table2.md", "tables_official"),
    ("Table 4 (NVOS)", "tables/table4.md", "tables_nvos"),
    ("study effects", "tables/effects.md", "effects"),
    ("robustness curve", "tables/robustness.md", "robustness"),
    ("reconstruction table", "reconstruction.md", "reconstruction_table"),
    ("tracing table", "tracing.md", "tracing_table"),
    ("scenes table", "scenes.md", "scenes_table"),
)

# The workflow's rules without a command (targets that only collect their inputs): they take no time.
TARGET_RULES = ("reproduce", "paper_tables")

_STAMP = re.compile(r"^\[(\w{3} \w{3} +\d+ \d\d:\d\d:\d\d \d{4})\]$")
_START = re.compile(r"^(?:local)?rule (\w+):$")
_FINISHED = re.compile(r"^Finished jobid: (\d+) \(Rule: (\w+)\)$")
_ERROR = re.compile(r"^Error in rule (\w+):$")
_JOBID = re.compile(r"^\s+jobid: (\d+)$")
_THREADS = re.compile(r"^\s+threads: (\d+)$")
_STEPS = re.compile(r"^(\d+) of (\d+) steps \(.*\) done$")


@dataclass
class Job:
    rule: str
    threads: int = 1
    start: float | None = None
    end: float | None = None


@dataclass
class Run:
    """What a Snakemake log says about its run."""

    path: Path
    started: float | None = None
    cores: int = 1
    counts: dict[str, int] = field(default_factory=dict)  # rule -> jobs planned (the log's "Job stats")
    jobs: dict[int, Job] = field(default_factory=dict)  # jobid -> job (started ones)
    done: int = 0
    total: int | None = None
    failed: set[int] = field(default_factory=set)  # jobids of the failed jobs ("Error in rule")
    complete: bool = False  # the log ends with Snakemake's own summary line
    nothing: bool = False  # "Nothing to be done"


def _time(text: str) -> float:
    return _dt.datetime.strptime(" ".join(text.split()), "%a %b %d %H:%M:%S %Y").timestamp()


def parse_log(path: Path) -> Run:
    """The run a Snakemake log describes (its jobs with start / end times, cores, the planned counts)."""
    run = Run(Path(path))
    lines = Path(path).read_text(errors="replace").splitlines()
    stamp = None
    current: Job | None = None  # the job block being read
    in_stats = in_error = False
    for line in lines:
        if m := _STAMP.match(line):
            stamp = _time(m.group(1))
            run.started = run.started if run.started is not None else stamp
            current, in_error = None, False
            continue
        if line.startswith("Provided cores: "):
            run.cores = max(int(line.split(":")[1]), 1)
        elif line.startswith("Job stats:"):
            in_stats, run.counts = True, {}
        elif in_stats:
            parts = line.split()
            if len(parts) == 2 and parts[1].isdigit():
                if parts[0] == "total":
                    in_stats = False
                else:
                    run.counts[parts[0]] = int(parts[1])
            elif line.strip() == "" and run.counts:
                in_stats = False
        if m := _START.match(line):
            current = Job(m.group(1), start=stamp)
        elif in_error and (m := _JOBID.match(line)):
            run.failed.add(int(m.group(1)))
            in_error = False
        elif current is not None and (m := _JOBID.match(line)):
            run.jobs[int(m.group(1))] = current
        elif current is not None and (m := _THREADS.match(line)):
            current.threads = int(m.group(1))
        elif m := _FINISHED.match(line):
            job = run.jobs.setdefault(int(m.group(1)), Job(m.group(2)))
            job.end = stamp
        elif _ERROR.match(line):
            current, in_error = None, True  # its jobid line follows
        elif m := _STEPS.match(line):
            run.done, run.total = int(m.group(1)), int(m.group(2))
        elif line.startswith("Nothing to be done"):
            run.nothing = True
        elif line.startswith("Complete log"):
            run.complete = True
    if run.total is None and run.counts:
        run.total = sum(run.counts.values())
    return run


def _runs_jobs(path: Path) -> bool:
    """Whether a log is a run's: one that builds a DAG (``--lint`` writes a log too), not a report's
    (``--report``) nor a dry run's (``-n``)."""
    text = Path(path).read_text(errors="replace")
    return ("Building DAG of jobs" in text and "Creating report..." not in text
            and "This was a dry-run" not in text)


def run_logs(workdir: Path) -> list[Path]:
    """The logs of runs in ``workdir``'s ``.snakemake/log``, oldest first (lints, reports and dry runs
    write logs too: skipped)."""
    return [p for p in sorted((Path(workdir) / ".snakemake" / "log").glob("*.snakemake.log")) if _runs_jobs(p)]


def earlier_means(log: Path, count: int = 20) -> dict[str, float]:
    """Rule -> mean job cost from the (at most ``count``) run logs before ``log`` in its folder, the
    newest run's figure where several have one."""
    logs = [p for p in run_logs(Path(log).parent.parent.parent) if p.name < Path(log).name][-count:]
    out: dict[str, float] = {}
    for path in logs:  # oldest first: a newer run's mean replaces an older one's
        out.update(rule_means(parse_log(path)))
    return out


def newest_log(workdir: Path) -> Path:
    """The newest log of a run (:func:`run_logs`)."""
    logs = run_logs(workdir)
    if not logs:
        raise Trace3DError(f"{Path(workdir) / '.snakemake' / 'log'}: no Snakemake log there; run it from the folder "
                           f"you started Snakemake in (`make reproduce`: the checkout), or pass --log.")
    return logs[-1]


def rule_means(run: Run) -> dict[str, float]:
    """Rule -> the mean cost of its finished jobs in ``run``: wall seconds x min(threads, cores)."""
    per_rule: dict[str, list[float]] = {}
    for jobid, job in run.jobs.items():
        if job.start is not None and job.end is not None and jobid not in run.failed:
            per_rule.setdefault(job.rule, []).append((job.end - job.start) * min(job.threads, run.cores))
    return {rule: sum(v) / len(v) for rule, v in per_rule.items()}


def estimate(run: Run, now: float, earlier: dict[str, float] | None = None) -> dict:
    """Jobs left per rule and the seconds left: {left: {rule: n}, running: {rule: n}, seconds: s,
    unestimated: {rule: n}, from_earlier: [rule]}. A job's cost is the mean of its rule's finished jobs
    in ``run`` (wall seconds x min(threads, cores)), else ``earlier``'s (rule -> cost, from earlier runs);
    the rules without a command (:data:`TARGET_RULES`) cost nothing."""
    failed = run.failed
    started = {i: j for i, j in run.jobs.items() if j.start is not None}
    finished = {i: j for i, j in started.items() if j.end is not None and i not in failed}
    own = rule_means(run)
    mean = {**{rule: 0.0 for rule in TARGET_RULES}, **(earlier or {}), **own}
    done_by_rule: dict[str, int] = {}
    for job in finished.values():
        done_by_rule[job.rule] = done_by_rule.get(job.rule, 0) + 1
    running = {i: j for i, j in started.items() if j.end is None and i not in failed}
    running_by_rule: dict[str, int] = {}
    for job in running.values():
        running_by_rule[job.rule] = running_by_rule.get(job.rule, 0) + 1
    left = {rule: count - done_by_rule.get(rule, 0) for rule, count in run.counts.items()}
    left = {rule: n for rule, n in left.items() if n > 0}
    seconds, unestimated = 0.0, {}
    for rule, n in left.items():
        if rule not in mean:
            unestimated[rule] = n
            continue
        waiting = n - running_by_rule.get(rule, 0)
        seconds += waiting * mean[rule]
    for job in running.values():
        if job.rule in mean:
            seconds += max(mean[job.rule] - (now - job.start) * min(job.threads, run.cores), 0.0)
    from_earlier = sorted(rule for rule in left if rule not in own and rule in (earlier or {}))
    return {"left": left, "running": running_by_rule, "seconds": seconds / run.cores,
            "unestimated": unestimated, "failed": len(failed), "from_earlier": from_earlier}


def _clock(t: float) -> str:
    return time.strftime("%H:%M", time.localtime(t))


def _duration(seconds: float) -> str:
    if seconds < 30:
        return "a few seconds"
    minutes = round(seconds / 60)
    return f"{minutes // 60} h {minutes % 60:02d} min" if minutes >= 60 else f"{minutes} min"


def tables_status(results: Path, run: Run) -> list[str]:
    """One line per table: done (when), waiting (its rule has a job left in the run), or as on disk."""
    lines = []
    finished_rules = {j.rule for j in run.jobs.values() if j.end is not None}
    for label, rel, rule in TABLES:
        path = Path(results) / rel
        planned = rule in run.counts
        if planned and rule in finished_rules and path.exists():
            lines.append(f"  done     {label}: {path} ({_clock(path.stat().st_mtime)})")
        elif planned:
            lines.append(f"  waiting  {label}: {path}")
        elif path.exists():
            lines.append(f"  done     {label}: {path} ({_clock(path.stat().st_mtime)}, before this run)")
    report = Path(results) / "report.html"
    if report.exists():
        lines.append(f"  written  HTML report: {report} ({_clock(report.stat().st_mtime)})")
    return lines


def progress_text(results: Path, log: Path | None = None, workdir: Path = Path("."), now: float | None = None) -> str:
    """The report ``trace3d progress`` prints."""
    log = Path(log) if log is not None else newest_log(workdir)
    if not log.is_file():
        raise Trace3DError(f"{log}: no such Snakemake log; pass a file from .snakemake/log/.")
    now = time.time() if now is None else now
    run = parse_log(log)
    failed = run.failed
    out = [f"Snakemake log {log}" + (f", started {_clock(run.started)}" if run.started else "")
           + f", {run.cores} core{'s' if run.cores != 1 else ''}"]
    if run.nothing:
        out.append("jobs: nothing to be done (every output is up to date)")
    elif run.total is not None:
        est = estimate(run, now, earlier_means(log))
        running = sum(est["running"].values())
        waiting = run.total - run.done - running - len(failed)
        state = "finished" if run.complete and run.done == run.total else \
            ("stopped" if run.complete or failed else "running")
        out.append(f"jobs: {run.done} of {run.total} done, {running} running, {max(waiting, 0)} waiting"
                   + (f", {len(failed)} failed" if failed else "") + f" ({state})")
        if est["left"] and state == "running":
            rules = ", ".join(f"{rule} {n}" + (f" ({est['running'][rule]} running)" if est["running"].get(rule) else "")
                              for rule, n in sorted(est["left"].items(), key=lambda kv: -kv[1]))
            out.append(f"left by rule: {rules}")
            if est["unestimated"]:
                names = ", ".join(f"{rule} {n}" for rule, n in sorted(est["unestimated"].items()))
                if est["seconds"] > 0:
                    # "about", not "more than": the per-rule means come from the jobs finished so far, which
                    # need not be the typical ones (docs/history/runs.md: 1 h 44 min said, 1 h 23 min taken)
                    out.append(f"time left: about {_duration(est['seconds'])} (the finished jobs' mean time per "
                               f"rule / {run.cores} cores), plus {names} job(s) of rules with no finished job yet")
                else:
                    out.append(f"time left: not estimated yet (no job of {names} has finished)")
            else:
                out.append(f"time left: about {_duration(est['seconds'])}, until about {_clock(now + est['seconds'])} "
                           f"(the finished jobs' mean time per rule x jobs left / {run.cores} cores)")
            if est["from_earlier"]:
                out.append(f"  (no job of {', '.join(est['from_earlier'])} has finished in this run: their time is "
                           f"from earlier runs' logs in {Path(log).parent})")
    elif run.complete:
        out.append("jobs: the run has ended; its log lists no jobs (was it run with --quiet?)")
    else:
        out.append("jobs: the log lists no jobs yet (Snakemake is building its DAG)")
    tables = tables_status(results, run)
    if tables:
        out.append("tables:")
        out.extend(tables)
    return "\n".join(out)
