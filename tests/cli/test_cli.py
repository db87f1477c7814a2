"""The `trace3d` command line: help, and one-sentence errors with exit status 2."""

from __future__ import annotations

import subprocess
import sys

import pytest

from trace3d.cli import build_parser, main


def test_help_lists_steps(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for step in ("scene", "masks", "patches", "poses", "gaussians", "summary", "bench"):
        assert step in out


def test_console_script_runs():
    result = subprocess.run([sys.executable, "-m", "trace3d.cli", "--help"], capture_output=True, text=True)
    assert result.returncode == 0 and "STEP" in result.stdout


def test_missing_scene_is_one_sentence(tmp_path, capsys):
    missing = tmp_path / "nowhere"
    code = main(["poses", "--scene", str(missing), "--out", str(tmp_path / "poses")])
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert err == f"trace3d poses: error: {missing}: scene directory does not exist."
    assert not (tmp_path / "poses").exists()


def test_bad_params_refused(tmp_path, capsys):
    code = main(["scene", "synthetic", "--out", str(tmp_path / "s"), "--params", "[1, 2]"])
    assert code == 2
    assert "expected a mapping of parameters" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()


def test_importer_needs_source(tmp_path, capsys):
    code = main(["scene", "replica", "--out", str(tmp_path / "s")])
    assert code == 2
    assert "needs --source" in capsys.readouterr().err


def test_parser_rejects_unknown_step():
    with pytest.raises(SystemExit):
        build_parser().parse_args(["fly"])
