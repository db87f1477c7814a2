"""trace3d.tooling.scheduling: the job-rate limiter goes from a local run's scheduler, and only from there."""
from types import SimpleNamespace

from trace3d.tooling.scheduling import unthrottle_local


_LIMITER = object()


def _workflow(local: bool, limiter=_LIMITER):
    return SimpleNamespace(local_exec=local, scheduler=SimpleNamespace(job_rate_limiter=limiter))


def test_a_local_run_loses_the_limiter():
    wf = _workflow(local=True)
    line = unthrottle_local(wf)
    assert wf.scheduler.job_rate_limiter is None
    assert line and "job-rate limiter is off" in line


def test_a_cluster_run_keeps_it():
    limiter = object()
    wf = _workflow(local=False, limiter=limiter)
    assert unthrottle_local(wf) is None
    assert wf.scheduler.job_rate_limiter is limiter


def test_nothing_to_do_without_a_scheduler_or_a_limiter():
    assert unthrottle_local(SimpleNamespace(local_exec=True)) is None     # dry runs build none
    wf = _workflow(local=True, limiter=None)
    assert unthrottle_local(wf) is None and wf.scheduler.job_rate_limiter is None
