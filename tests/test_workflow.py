"""The Snakemake workflow: config validation, lint, and a tiny end-to-end run."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parent.parent
SNAKEMAKE = shutil.which("snakemake", path=str(Path(sys.executable).parent)) or shutil.which("snakemake")

pytestmark = pytest.mark.skipif(SNAKEMAKE is None, reason="snakemake is not installed")


def run_snakemake(workdir: Path, *args: str, config: dict | None = None, timeout: int = 600):
    cmd = [SNAKEMAKE, "-s", str(REPO / "Snakefile"), "--directory", str(workdir)]
    if config is not None:
        path = workdir / "config.yaml"
        path.write_text(yaml.safe_dump(config))
        cmd += ["--configfile", str(path)]
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env.setdefault("NUMBA_CACHE_DIR", str(REPO / ".numba_cache"))
    return subprocess.run(cmd + list(args), capture_output=True, text=True, env=env, timeout=timeout)


@pytest.mark.parametrize(
    "config, message",
    [
        ({"scenes": {"r0": {"kind": "synthetic", "synthtic": {"seed": 0}}}}, "'synthtic' was unexpected"),
        ({"scenes": {"r0": {"kind": "mesh"}}}, "'mesh' is not one of"),
        ({"scenes": {"r0": {"kind": "replica"}}}, "'source' is a required property"),
        ({"scenes": {"r0": {"kind": "synthetic"}}, "results": 3}, "3 is not of type 'string'"),
        ({"scenes": {}}, "should be non-empty"),
    ],
)
def test_schema_refuses_bad_config(tmp_path, config, message):
    result = run_snakemake(tmp_path, "-n", config=config)
    assert result.returncode != 0
    assert "Error validating config file" in result.stderr + result.stdout
    assert message in result.stderr + result.stdout


def test_lint_is_clean(tmp_path):
    result = subprocess.run(
        [SNAKEMAKE, "--lint"], cwd=REPO, capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 0, result.stdout + result.stderr


def test_dry_run_default_config():
    result = subprocess.run(
        [SNAKEMAKE, "-n", "reproduce"], cwd=REPO, capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 0, result.stderr
    for scene in ("room0", "room1", "room2", "room3"):
        assert f"scene={scene}" in result.stdout
