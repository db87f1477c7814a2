"""A DAG run through the fork server writes the bytes of an in-process run (trace3d/tooling/forkserver.py).

The SLURM test's tiny room (tests/workflow/test_slurm.py) to its standard evaluation -- scene, poses, masks,
patches, fit, trace, merge, refine, lift, evaluation: every step with kernels -- once with the session's
servers (tests/workflow/conftest.py) and once with none, on the same machine; every file is compared as the
SLURM test compares a cluster run with a local one (byte for byte, but for wall-clock fields and the
per-job logs and timings).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.workflow.test_slurm import TIMED_FILES, TIMED_PREFIXES, TINY_CONFIG, _digests, _without_times
from tests.workflow.test_workflow import run_snakemake
from trace3d.io import MANIFEST

TARGETS = ("results/a/full/eval",)


def _run(root: Path, env_folder: str | None, monkeypatch) -> None:
    root.mkdir()
    if env_folder is None:
        monkeypatch.delenv("TRACE3D_FORKSERVER", raising=False)
    else:
        monkeypatch.setenv("TRACE3D_FORKSERVER", env_folder)
    ran = run_snakemake(root, "--cores", "2", *TARGETS, config=TINY_CONFIG)
    assert ran.returncode == 0, ran.stderr[-4000:]


@pytest.mark.slow
@pytest.mark.xdist_group("whole_dag")  # whole-DAG runs take turns on one worker (tests/conftest.py)
def test_forked_jobs_write_the_bytes_of_in_process_jobs(tmp_path, forkserver_folder, monkeypatch):
    if forkserver_folder is None:
        pytest.skip("TRACE3D_TEST_FORKSERVER=off: no fork server to compare with")
    _run(tmp_path / "forked", forkserver_folder, monkeypatch)
    # the servers are the session's (other tests' runs may use them at the same time): this run's jobs are
    # the job lines naming its folder
    ran = {key: _jobs(Path(forkserver_folder), key, tmp_path / "forked") for key in ("1", "1-spin", "2")}
    # every job of the run went through a server (10 steps; the lift's on the spinning one)
    assert ran["1"] == 9 and ran["1-spin"] == 1, ran
    _run(tmp_path / "here", None, monkeypatch)

    forked, here = (tmp_path / name / "results" for name in ("forked", "here"))
    a, b = _digests(forked), _digests(here)
    assert set(a) == set(b), sorted(set(a) ^ set(b))
    compared = [f for f in a if not f.startswith(TIMED_PREFIXES) and f not in TIMED_FILES]
    timed = [f for f in compared if a[f] != b[f] and not f.endswith(MANIFEST)]
    for f in timed:  # equal once their wall-clock fields are dropped
        assert _without_times(forked / f) == _without_times(here / f), f
    for f in (f for f in compared if f.endswith(MANIFEST) and a[f] != b[f]):
        ours, theirs = (json.loads((root / f).read_text()) for root in (forked, here))
        folder = f[: -len(MANIFEST)]
        other = {name for name in ours["files"] if ours["files"][name] != theirs["files"].get(name)}
        assert other and all(folder + name in timed or folder + name in TIMED_FILES for name in other), (f, other)
    assert len(compared) > 60 and "a/full/lift/features.npy" in compared and "a/gaussians/point_cloud.ply" in compared
    assert a["a/full/lift/features.npy"] == b["a/full/lift/features.npy"]
    print(f"{len(compared)} files compared, {len(timed)} equal without their time fields ({', '.join(timed)})")


def _jobs(folder: Path, key: str, where: Path) -> int:
    """How many jobs the server ``key`` of ``folder`` has run in the folder ``where`` (its log's job lines)."""
    log = folder / f"{key}.log"
    lines = log.read_text().splitlines() if log.exists() else []
    return sum(" job " in line and f" in {where}" in line for line in lines)

