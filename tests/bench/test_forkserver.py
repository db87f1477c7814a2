"""``trace3d bench forkserver``: a job's CPU to its first line in a fresh process and through the fork server."""

from __future__ import annotations

import pytest

from trace3d.bench.forkserver import run_bench
from trace3d.errors import Trace3DError


def test_both_ways_are_measured_and_the_forked_job_is_the_lighter():
    result = run_bench(rounds=1, commands=["tables"])
    entry = result["commands"]["tables"]
    here, forked = entry["in_process"], entry["forked"]
    # the benchmark checks that each probe ran the way it meant (it raises otherwise): the forked job's own
    # process only waits, while the in-process one imports the step
    assert 0 < forked["job_cpu_s"] < here["job_cpu_s"]
    assert forked["first_line_cpu_s"] < here["first_line_cpu_s"]
    assert result["server_start_cpu_s"] > 0 and result["server_per_job_cpu_s"] >= 0
    assert entry["saved_cpu_s"] == pytest.approx(here["to_first_line_cpu_s"] - forked["to_first_line_cpu_s"], abs=2e-3)


def test_unknown_steps_are_one_sentence():
    with pytest.raises(Trace3DError, match="give --rounds >= 1 and steps among"):
        run_bench(rounds=1, commands=["no-such-step"])
