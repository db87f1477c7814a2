"""Importing the library changes nothing in the process: no environment variable is set or changed."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent

# import every module of the package, then report the environment variables that differ; the third-party
# libraries are imported first because some change the environment themselves (OpenCV extends
# LD_LIBRARY_PATH), which is not the library's doing
SCRIPT = """
import os
import trace3d
print(os.environ.get("OMP_WAIT_POLICY"))
import importlib, json, pkgutil
import cv2, numba, numpy, torch
before = dict(os.environ)
for info in pkgutil.walk_packages(trace3d.__path__, "trace3d."):
    importlib.import_module(info.name)
after = dict(os.environ)
print(json.dumps(sorted(k for k in set(before) | set(after) if before.get(k) != after.get(k))))
"""


def test_import_sets_no_environment_variable():
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "NUMBA_CACHE_DIR")}
    env["PYTHONPATH"] = os.pathsep.join([str(REPO)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    result = subprocess.run([sys.executable, "-c", SCRIPT], cwd=REPO, env=env, capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    first, changed = result.stdout.strip().splitlines()[-2:]
    assert first == "None"
    assert json.loads(changed) == []


def test_cli_sets_the_omp_wait_policy_before_the_library_loads():
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    env["PYTHONPATH"] = os.pathsep.join([str(REPO)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    script = ("import os, sys; from trace3d import cli; sys.argv = ['trace3d', '--help']\n"
              "try:\n    cli.main()\nexcept SystemExit:\n    pass\nprint(os.environ.get('OMP_WAIT_POLICY'))")
    result = subprocess.run([sys.executable, "-c", script], cwd=REPO, env=env, capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.strip().splitlines()[-1] == "PASSIVE"


def test_cli_lets_only_the_lift_commands_spin():
    env = {k: v for k, v in os.environ.items() if k != "GOMP_SPINCOUNT"}
    env["PYTHONPATH"] = os.pathsep.join([str(REPO)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    commands = [["lift", "--scene", "s", "--poses", "p", "--gaussians", "g", "--out", "o"], ["bench", "lift"],
                ["gaussians", "--scene", "s", "--poses", "p", "--out", "o"]]
    script = ("import json, os, sys; from trace3d import cli\n"
              "for argv in json.loads(sys.argv[1]):\n"
              "    os.environ.pop('GOMP_SPINCOUNT', None)\n"
              "    cli._command_environment(cli.build_parser().parse_args(argv))\n"
              "    print(os.environ.get('GOMP_SPINCOUNT'))")
    result = subprocess.run([sys.executable, "-c", script, json.dumps(commands)], cwd=REPO, env=env,
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.strip().splitlines()[-3:] == ["10000", "10000", "None"]
