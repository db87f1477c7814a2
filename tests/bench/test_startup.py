"""``trace3d bench startup``: a fresh process per step, timed to the step's first line and its kernels."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from trace3d.bench.startup import pipeline_commands, run_bench
from trace3d.errors import Trace3DError

REPO = Path(__file__).resolve().parents[2]


def test_pipeline_commands_are_the_steps_rules_run():
    commands = pipeline_commands()
    assert "evaluate" in commands and "lift" in commands and "tables" in commands
    assert "masks-stats" not in commands  # run by hand only


def test_a_step_without_kernels_loads_neither_torch_nor_numba():
    result = run_bench(rounds=2, commands=["tables"])
    entry = result["commands"]["tables"]
    assert entry["first_line"]["cpu_s"] > 0 and entry["first_line"]["wall_s"] > 0
    assert len(entry["rounds_cpu_s"]) == 2
    assert "torch" not in entry["heavy"] and "numba" not in entry["heavy"], entry["heavy"]
    assert entry["kernels"]["loaded"] == entry["kernels"]["compiled"] == 0
    assert len(result["loadavg_before"]) == 3


def test_probe_loads_the_steps_entry_modules():
    """The child imports the step's handler and entry modules: for evaluate, torch and numba."""
    proc = subprocess.run([sys.executable, "-c",
                           "import sys, time; from trace3d.startup_probe import _first_line; "
                           "r = _first_line('evaluate', time.time()); "
                           "print('trace3d.evaluation.step' in sys.modules, 'torch' in r['heavy'])"],
                          cwd=REPO, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["True", "True"]


def test_unknown_command_and_bad_rounds_are_refused():
    with pytest.raises(Trace3DError, match="not pipeline steps"):
        run_bench(rounds=1, commands=["masks-stats"])
    with pytest.raises(Trace3DError, match="--rounds"):
        run_bench(rounds=0, commands=["tables"])


def test_cli_prints_json(tmp_path):
    out = tmp_path / "startup.json"
    proc = subprocess.run([sys.executable, "-m", "trace3d.cli", "bench", "startup", "--quick", "--out", str(out)],
                          cwd=REPO, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr
    data = json.loads(out.read_text())
    assert set(data["commands"]) == {"tables", "evaluate"}
    assert "torch" in data["commands"]["evaluate"]["heavy"]
