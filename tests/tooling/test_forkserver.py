"""The fork server of the ``trace3d`` command (trace3d/tooling/forkserver.py): a job runs in a fork of it or,
when it must not or cannot, in-process; its bytes, exit status, stderr and signals are the command's own.

One server (key ``default``: jobs without ``--threads``) is started for the module, from this process's
environment; the jobs are ``python -m trace3d.cli ...`` processes, as a user's or a rule's command. The
comparison of a whole DAG run both ways is tests/workflow/test_forkserver.py.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from trace3d.cli import main
from trace3d.tooling.forkclient import job_key, job_request
from trace3d.tooling.forkserver import Server, check_folder, effective_environment, start, stop, unsafe

REPO = Path(__file__).resolve().parents[2]
SCENE = {"width": 48, "height": 36, "num_views": 6, "test_every": 3, "num_objects": 10, "supersample": 1}
# a scene step that renders for a few seconds: long enough to be signalled mid-run
SLOW_SCENE = {"width": 240, "height": 180, "num_views": 32, "supersample": 2}


@pytest.fixture(scope="module")
def server():
    folder = Path(tempfile.mkdtemp(prefix="trace3d-fork-")) / "s"
    (pid,) = start(folder, ("default",))
    try:
        yield folder, pid
    finally:
        stop(folder)
        shutil.rmtree(folder.parent, ignore_errors=True)


def job_env(folder: Path | str | None, **extra: str) -> dict:
    """This process's environment (the server's: a job started from this folder imports the same trace3d),
    naming the server folder ``folder`` (None: none), with ``extra`` set."""
    env = dict(os.environ, **extra)
    if folder is None:
        env.pop("TRACE3D_FORKSERVER", None)
    else:
        env["TRACE3D_FORKSERVER"] = str(folder)
    return env


def trace3d(args: list[str], env: dict, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "trace3d.cli", *args], capture_output=True, text=True, env=env,
                          cwd=REPO, timeout=300, **kwargs)


def server_log(folder: Path) -> str:
    return (folder / "default.log").read_text()


def folder_bytes(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_job_keys():
    assert job_key(["scene", "synthetic", "--out", "x"]) == "default"
    assert job_key(["--threads", "2", "scene", "synthetic"]) == "2"
    assert job_key(["-v", "--threads=1", "lift", "--out", "x"]) == "1-spin"  # the lift's workers spin
    # not pipeline steps, or asking for help: in-process
    for argv in (["bench", "startup"], ["describe"], ["scene", "--help"], ["--threads", "0", "scene"], []):
        assert job_key(argv) is None, argv


def test_a_step_runs_in_the_server_and_writes_the_bytes_of_an_in_process_run(server, tmp_path):
    folder, pid = server
    params = json.dumps(SCENE)
    ran = trace3d(["-v", "scene", "synthetic", "--params", params, "--out", str(tmp_path / "forked")], job_env(folder))
    assert ran.returncode == 0, ran.stderr[-3000:]
    assert f"trace3d scene: ran in a fork of the fork server {pid}" in ran.stderr, ran.stderr[:3000]
    assert "wrote scene" in ran.stderr  # the job's own log lines, on the job's stderr
    assert main(["scene", "synthetic", "--params", params, "--out", str(tmp_path / "here")]) == 0
    forked, here = folder_bytes(tmp_path / "forked"), folder_bytes(tmp_path / "here")
    assert len(forked) > 10 and forked == here


def test_bad_input_is_one_sentence_and_exit_2_through_the_server(server, tmp_path):
    folder, _ = server
    ran = trace3d(["scene", "synthetic", "--params", '{"nope": 1}', "--out", str(tmp_path / "x")], job_env(folder))
    assert ran.returncode == 2
    assert ran.stdout == ""
    assert ran.stderr.startswith("trace3d scene: error: synthetic params: unknown parameter(s) ['nope']")
    assert ran.stderr.count("\n") == 1 and "Traceback" not in ran.stderr
    assert not (tmp_path / "x").exists()
    assert re.search(r"\(trace3d scene synthetic --params \.\.\. in \S+\): \{'exit': 2\}", server_log(folder))


def test_no_server_runs_in_process(tmp_path):
    empty = tmp_path / "none"
    empty.mkdir(mode=0o700)
    ran = trace3d(["-v", "scene", "synthetic", "--params", '{"nope": 1}', "--out", str(tmp_path / "x")],
                  job_env(empty))
    assert ran.returncode == 2
    assert f"trace3d scene: ran in-process (no fork server at {empty / 'default.sock'}" in ran.stderr
    assert ran.stderr.splitlines()[-1].startswith("trace3d scene: error: synthetic params: unknown parameter(s)")


def test_another_environment_runs_in_process(server, tmp_path):
    """A variable an OpenMP runtime reads when it loads, set for the job only: the server declines it."""
    folder, _ = server
    ran = trace3d(["-v", "scene", "synthetic", "--params", '{"nope": 1}', "--out", str(tmp_path / "x")],
                  job_env(folder, OMP_DYNAMIC="false"))
    assert ran.returncode == 2
    assert ("ran in-process (the fork server declined: the environment differs: OMP_DYNAMIC='false' here, None "
            "in the server)") in ran.stderr, ran.stderr[-2000:]
    assert "declined trace3d -v scene synthetic ...: the environment differs: OMP_DYNAMIC" in server_log(folder)


def test_changed_sources_and_another_checkout_are_declined(tmp_path):
    """The server's checks, on a server state made here over a copy of the package."""
    package = tmp_path / "checkout" / "trace3d"
    shutil.copytree(REPO / "trace3d", package, ignore=shutil.ignore_patterns("__pycache__"))
    state = Server("default", effective_environment(os.environ, "default"), package=package)
    request = job_request(["scene", "synthetic", "--out", "x"], "default")
    assert unsafe(state, request) is None
    # a job with another environment, another interpreter's flags, another server's key
    assert "the environment differs: NUMBA_OPT" in unsafe(state, {**request, "environ": {**os.environ,
                                                                                          "NUMBA_OPT": "0"}})
    assert "another interpreter" in unsafe(state, {**request, "interpreter": {**request["interpreter"],
                                                                              "executable": "/usr/bin/python3"}})
    assert "needs the server '1'" in unsafe(state, {**request, "key": "1"})
    # a job whose sys.path finds trace3d in another checkout (the copy) than the server has loaded
    moved = {**request, "path": [str(package.parent), *request["path"]]}
    assert unsafe(state, moved) == (f"module trace3d would be imported from {package / '__init__.py'}, the server "
                                    f"has {REPO / 'trace3d' / '__init__.py'}")
    # a source file edited (its time stamp moves), then one added: the server is stale
    errors = package / "errors.py"
    info = errors.stat()
    os.utime(errors, ns=(info.st_atime_ns, info.st_mtime_ns + 1_000_000_000))
    assert unsafe(state, request) == f"the package's sources changed since the server loaded them ({errors})"
    os.utime(errors, ns=(info.st_atime_ns, info.st_mtime_ns))
    assert unsafe(state, request) is None
    (package / "extra.py").write_text("")
    assert "sources changed since the server loaded them" in unsafe(state, request)


def test_a_batch_job_runs_in_process():
    """A SLURM job's work stays in its allocation: the job id is an environment difference."""
    state = Server("default", effective_environment(os.environ, "default"))
    request = job_request(["scene", "synthetic", "--out", "x"], "default")
    request["environ"] = {**os.environ, "SLURM_JOB_ID": "17"}
    assert unsafe(state, request) == "the environment differs: SLURM_JOB_ID='17' here, None in the server"


def test_the_folder_must_be_private(tmp_path):
    open_folder = tmp_path / "open"
    open_folder.mkdir(mode=0o755)
    open_folder.chmod(0o755)
    with pytest.raises(PermissionError, match="mode 0700"):
        check_folder(open_folder)
    check_folder(tmp_path / "private")
    assert (tmp_path / "private").stat().st_mode & 0o777 == 0o700


def _children(pid: int) -> list[int]:
    """The live processes whose parent is ``pid``."""
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid and fields[0] != "Z":
                out.append(int(entry.name))
    return out


def _start_slow_scene(folder: Path, out: Path) -> subprocess.Popen:
    """A scene job in the server, returned once it has made its temporary output."""
    proc = subprocess.Popen([sys.executable, "-m", "trace3d.cli", "scene", "synthetic", "--params",
                             json.dumps(SLOW_SCENE), "--out", str(out)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=job_env(folder), cwd=REPO)
    deadline = time.monotonic() + 120
    while not list(out.parent.glob(f".{out.name}.tmp-*")):
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "the step made no temporary output"
        time.sleep(0.01)
    return proc


@contextlib.contextmanager
def _blocked_job(folder: Path, tmp_path: Path):
    """A patches job in the server, held while it checks its input: its scene folder's manifest lists a
    file that is a named pipe, which the job reads to hash it (plain Python, no kernel running) until the
    pipe's writer closes. Yields the job's process once its child reads the pipe."""
    scene = tmp_path / "scene"
    scene.mkdir()
    os.mkfifo(scene / "cameras.json")
    (scene / ".trace3d-step").write_text(json.dumps({"step": "scene", "rules": ["scene"],
                                                     "files": {"cameras.json": [0, "0" * 64]}}))
    (tmp_path / "masks").mkdir()
    proc = subprocess.Popen([sys.executable, "-m", "trace3d.cli", "patches", "--scene", str(scene), "--masks",
                             str(tmp_path / "masks"), "--out", str(tmp_path / "patches")], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=job_env(folder), cwd=REPO)
    deadline = time.monotonic() + 120
    writer = None
    while writer is None:  # a non-blocking open for writing succeeds once a reader has the pipe open
        try:
            writer = os.open(scene / "cameras.json", os.O_WRONLY | os.O_NONBLOCK)
        except OSError:
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "the job never read its input"
            time.sleep(0.01)
    try:
        yield proc
    finally:
        os.close(writer)
        if proc.poll() is None:
            proc.kill()
        proc.communicate()


def _gone(pids: list[int], timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if not any(Path(f"/proc/{p}").exists() and _children_state(p) != "Z" for p in pids):
            return True
        time.sleep(0.02)
    return False


def _children_state(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return "Z"


def test_sigterm_reaches_the_child_and_the_job_exits_with_its_status(server, tmp_path):
    folder, pid = server
    with _blocked_job(folder, tmp_path) as proc:
        children = _children(pid)
        assert len(children) == 1, children  # the job's work runs in the server's child, not in the job
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=120)
        assert proc.returncode == 143, err
        assert err.splitlines() == ["trace3d patches: stopped (SIGTERM); nothing was written (an earlier output, "
                                    "if any, is unchanged)."]
        assert _gone(children)
    assert re.search(r"\(trace3d patches --scene \S+ \.\.\. in \S+\): \{'exit': 143\}", server_log(folder))


def test_a_killed_job_leaves_no_child_running(server, tmp_path):
    folder, pid = server
    with _blocked_job(folder, tmp_path) as proc:
        children = _children(pid)
        assert len(children) == 1, children
        proc.kill()  # SIGKILL: nothing forwarded; the server sees the job's connection close
        proc.wait()
        assert _gone(children), "the job's child still runs after the job was killed"
    assert re.search(r"\(trace3d patches --scene \S+ \.\.\. in \S+\): \{'signal': 9\}", server_log(folder))


def test_a_child_leaves_with_its_server(tmp_path):
    """A server stopped mid-job takes its child with it; the job runs the step again in-process."""
    folder = Path(tempfile.mkdtemp(prefix="trace3d-fork-")) / "s"
    (pid,) = start(folder, ("default",))
    try:
        out = tmp_path / "scene"
        proc = _start_slow_scene(folder, out)
        children = _children(pid)
        os.kill(pid, signal.SIGKILL)
        assert _gone(children)
        _, err = proc.communicate(timeout=300)
        assert proc.returncode == 0, err[-3000:]
        assert out.is_dir() and (out / "cameras.json").is_file()
    finally:
        stop(folder)
        with contextlib.suppress(ChildProcessError):
            os.waitpid(pid, 0)
        shutil.rmtree(folder.parent, ignore_errors=True)
