"""`trace3d --threads N` caps torch, numba, OpenMP and COLMAP; every rule passes {threads} and
declares its resources; the slurm profile asks for no GPU."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numba
import pytest
import torch
import yaml

import trace3d.cli as cli
from trace3d.threads import limit_threads, resolve_threads, thread_limit

REPO = Path(__file__).resolve().parents[2]
SNAKEMAKE = shutil.which("snakemake", path=str(Path(sys.executable).parent)) or shutil.which("snakemake")


def test_limit_threads_sets_and_restores():
    before = (torch.get_num_threads(), numba.get_num_threads(), os.environ.get("OMP_NUM_THREADS"))
    with limit_threads(1):
        assert torch.get_num_threads() == 1 and numba.get_num_threads() == 1
        assert os.environ["OMP_NUM_THREADS"] == "1" and os.environ["MKL_NUM_THREADS"] == "1"
        assert thread_limit() == 1 and resolve_threads(-1) == 1 and resolve_threads(4) == 1
    assert (torch.get_num_threads(), numba.get_num_threads(), os.environ.get("OMP_NUM_THREADS")) == before
    assert thread_limit() is None and resolve_threads(-1) == -1 and resolve_threads(3) == 3


def test_cli_threads_reach_the_step(monkeypatch, tmp_path):
    seen = {}

    def fake_summary(args):
        from trace3d.poses.params import params_from

        seen["torch"], seen["numba"] = torch.get_num_threads(), numba.get_num_threads()
        seen["omp"] = os.environ.get("OMP_NUM_THREADS")
        seen["colmap"] = resolve_threads(params_from({}).num_threads)

    import trace3d.steps.summary

    monkeypatch.setattr(trace3d.steps.summary, "run", fake_summary)
    assert cli.main(["--threads", "1", "summary", str(tmp_path), "--out", str(tmp_path / "x.md")]) == 0
    assert seen == {"torch": 1, "numba": 1, "omp": "1", "colmap": 1}
    assert cli.main(["--threads", "0", "summary", str(tmp_path), "--out", str(tmp_path / "x.md")]) == 2


def test_numba_pool_is_sized_in_a_fresh_process(tmp_path):
    """In a fresh process numba is not imported yet, so NUMBA_NUM_THREADS sizes its pool too."""
    code = ("import json, trace3d.cli as c, trace3d.threads as t\n"
            "def f(a):\n"
            "    import numba, torch\n"
            "    print(json.dumps([numba.config.NUMBA_NUM_THREADS, numba.get_num_threads(),"
            " torch.get_num_threads()]))\n"
            "import trace3d.steps.summary as s\n"
            "s.run = f\n"
            f"c.main(['--threads', '1', 'summary', {str(tmp_path)!r}, '--out', 'x'])\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "[1, 1, 1]"


def rule_blocks() -> dict[str, str]:
    blocks = {}
    for path in [REPO / "Snakefile", *sorted((REPO / "rules").glob("*.smk"))]:
        for block in re.split(r"(?m)^(?=rule )", path.read_text()):
            m = re.match(r"rule (\w+):", block)
            if m:
                blocks[m.group(1)] = block
    return blocks


def test_every_step_rule_declares_threads_and_resources_and_passes_threads():
    blocks = rule_blocks()
    # every rule that runs a step (file copies for the report are local rules and run nothing)
    steps = {name: b for name, b in blocks.items() if '"trace3d ' in b}
    assert {"scene", "poses", "masks", "patches", "gaussians", "trace", "merge", "refine"} <= set(steps)
    for name, block in steps.items():
        assert re.search(r"(?m)^    threads: ", block), f"rule {name} declares no threads"
        assert "mem_mb=" in block and "runtime=" in block, f"rule {name} declares no mem_mb / runtime"
        commands = re.findall(r'"(trace3d [^"]*)', block)
        assert commands and all(c.startswith("trace3d --threads {threads} ") for c in commands), (name, commands)


def test_slurm_profile_asks_for_no_gpu():
    profile = yaml.safe_load((REPO / "workflow/profiles/slurm/config.yaml").read_text())
    text = yaml.safe_dump(profile)
    assert "gpu" not in text.lower(), text
    assert profile["default-resources"]["mem_mb"] <= 2000  # rules ask for more where they need it


@pytest.mark.skipif(SNAKEMAKE is None, reason="snakemake is not installed")
def test_dry_run_passes_threads_capped_by_cores(tmp_path):
    config = tmp_path / "c.yaml"
    config.write_text(yaml.safe_dump({"results": str(tmp_path / "r"), "scenes": {"a": {"kind": "synthetic"}}}))
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    out = subprocess.run([SNAKEMAKE, "-s", str(REPO / "Snakefile"), "-d", str(tmp_path), "-n", "-p", "--cores", "1",
                          f"--configfile={config}", f"{tmp_path}/r/a/gaussians"],
                         capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    shells = [ln for ln in out.stdout.splitlines() if "trace3d " in ln]
    assert len(shells) == 3 and all("trace3d --threads 1 " in ln for ln in shells), shells
