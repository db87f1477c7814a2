"""``python -m trace3d.tooling.schema``: its command line (the schema's content is checked in
tests/cli/test_bad_inputs.py)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from trace3d.tooling import schema

REPO = Path(__file__).resolve().parents[2]


def test_help_prints_usage_and_writes_nothing(tmp_path):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO)] + [p for p in os.environ.get("PYTHONPATH", "")
                                                                       .split(os.pathsep) if p]))
    result = subprocess.run([sys.executable, "-m", "trace3d.tooling.schema", "--help"], cwd=tmp_path, env=env,
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("usage: python -m trace3d.tooling.schema")
    assert list(tmp_path.iterdir()) == []  # formerly a file named --help


def test_an_unknown_option_is_refused_with_status_2(tmp_path, capsys):
    try:
        schema.main(["--bogus"])
    except SystemExit as exit:
        assert exit.code == 2
    else:
        raise AssertionError("--bogus was accepted")
    assert "unrecognized arguments: --bogus" in capsys.readouterr().err


def test_writes_the_schema_to_the_path_given(tmp_path, capsys):
    target = tmp_path / "steps.schema.yaml"
    assert schema.main([str(target)]) == 0
    assert target.read_text() == schema.schema_text()
    assert capsys.readouterr().out.strip() == f"wrote {target}"
