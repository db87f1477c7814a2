"""Results early: target ``paper_tables`` (what ``make reproduce`` builds before ``reproduce``) holds the
paper's tables of the seed-0 rows and none of the study's jobs."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[2]
SNAKEMAKE = shutil.which("snakemake", path=str(Path(sys.executable).parent)) or shutil.which("snakemake")

pytestmark = pytest.mark.skipif(SNAKEMAKE is None, reason="snakemake is not installed")


def _job_stats(target: str, tmp_path: Path) -> dict[str, int]:
    result = subprocess.run([SNAKEMAKE, "-s", str(REPO / "Snakefile"), "--directory", str(tmp_path),
                             f"--configfile={REPO / 'config' / 'config.yaml'}", "-n", target],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    block = result.stdout.split("Job stats:", 1)[1].split("total", 1)[0]
    return {m.group(1): int(m.group(2)) for m in re.finditer(r"^(\w+)\s+(\d+)$", block, flags=re.M)}


def test_paper_tables_are_the_seed0_rows_only(tmp_path):
    early = _job_stats("paper_tables", tmp_path)
    assert early["tables_paper_rows"] == 1 and early["gaussians"] == 4
    # four rooms x the paper's own rows at lift seed 0: no variant beyond the paper, mask model, oracle,
    # robustness level or other seed (each would add evaluations)
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    rows = config["paper_rows"]
    assert set(rows) < set(config["variants"])
    assert early["evaluate"] == early["lift"] == 4 * len(rows)
    # the released code's settings (its own merge and refine) wait for the whole grid
    assert "full_official" not in rows and early["refine"] < 4 * 7
    for study in ("tables", "effects", "robustness", "evaluate_official", "tables_official", "reproduce"):
        assert study not in early, study
    assert early["scenes_table"] == early["reconstruction_table"] == early["tracing_table"] == 1


def test_makefile_builds_the_paper_tables_first():
    recipe = (REPO / "Makefile").read_text().split("\nreproduce:", 1)[1].split("\n\n", 1)[0]
    early = recipe.index("paper_tables")
    assert early < recipe.index("--show-failed-logs reproduce")
    assert "tables/paper/table2.md" in recipe and "tables/paper/table3.md" in recipe


def test_paper_rows_must_be_variants(tmp_path):
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    config["paper_rows"] = ["full", "no_such_row"]
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(config))
    result = subprocess.run([SNAKEMAKE, "-s", str(REPO / "Snakefile"), "--directory", str(tmp_path),
                             f"--configfile={path}", "-n", "paper_tables"], capture_output=True, text=True, timeout=300)
    assert result.returncode != 0
    assert "config paper_rows: 'no_such_row' is not one of the config's variants" in result.stdout + result.stderr
