"""Snakemake's job-rate limiter, turned off for local runs (the Snakefile's ``onstart``).

Snakemake (9.x) limits job starts to ``--max-jobs-per-timespan`` (default 100/1s). While a limiter is
set, every scheduling pass that finds a ready job arms a timer that triggers one more pass after the
timespan, and that pass arms the next: each finished job (which triggers a pass of its own) starts one
more such chain, and a chain ends only on a pass that finds no ready job. On this pipeline's grid,
where hundreds of jobs stay ready for hours, the chains add up to one pass per second per finished job;
each pass re-evaluates the params of every ready job and the sizes of their inputs. Measured on the
default grid (docs/performance.md, 'Where the whole grid's time went before'): the scheduler's process took
41-50 % of one of the two cores in the second half of the run; on a copy of its results with 320 ready
lifts, 51 timer threads were alive after 46 finished jobs.

On one machine the cores already bound how many jobs start, so the limiter has nothing to do there;
on a cluster it keeps a submission rate, and stays. :func:`unthrottle_local` removes it from the
scheduler of a local run; ``trace3d bench scheduler`` measures the scheduler's CPU time with and
without it on a workflow of sleeping jobs.
"""
from __future__ import annotations


def unthrottle_local(workflow) -> str | None:
    """Remove the job-rate limiter from ``workflow``'s scheduler when the jobs run on this machine.

    Returns the line to log when it did, None when there was nothing to do (no scheduler yet, no limiter,
    a dry run, or an executor that submits elsewhere, e.g. SLURM)."""
    scheduler = getattr(workflow, "scheduler", None)
    if getattr(scheduler, "job_rate_limiter", None) is None:
        return None
    if not getattr(workflow, "local_exec", False):
        return None
    scheduler.job_rate_limiter = None
    return ("trace3d: Snakemake's job-rate limiter is off for this local run (its re-evaluation timers "
            "add up to one scheduling pass per second per finished job; trace3d/tooling/scheduling.py)")
