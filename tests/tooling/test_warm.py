"""trace3d.tooling.warm: every cached numba kernel of the package is warmed, each by one process, and a fresh
process then finds all of them in the cache."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from trace3d.tooling import warm

REPO = Path(__file__).resolve().parents[2]


def _entries(manifest: dict) -> list[tuple[str, str, str]]:
    return sorted((m, n, s) for m, functions in manifest.items() for n, sigs in functions.items() for s in sigs)


def test_every_cached_kernel_has_recorded_signatures():
    """Every module-level numba function with a cache that numba compiles on its own, in every module
    that defines a kernel, has its signatures in kernel_signatures.json, and every entry there names such
    a function (or an inlined one that Python calls directly) and reads back as the types it was."""
    manifest = warm.read_manifest()
    definers = warm.kernel_definers()
    assert set(manifest) <= set(definers), sorted(set(manifest) - set(definers))
    missing, unknown = [], []
    for module in definers:
        standalone = warm.cached_dispatchers(module, inlined=False)
        every = warm.cached_dispatchers(module)
        missing += [f"{module}.{name}" for name in standalone if name not in manifest.get(module, {})]
        unknown += [f"{module}.{name}" for name in manifest.get(module, {}) if name not in every]
    assert missing == [], ("cached kernels without recorded signatures (python -m trace3d.tooling.warm --record): "
                           f"{missing}")
    assert unknown == [], f"recorded kernels that are gone: {unknown}"
    for module, name, text in _entries(manifest):
        assert repr(warm.parse_signature(text)) == text, (module, name)
    # the walk finds the kernels of more than one stage (the render, training, lifting kernels)
    assert {"trace3d.render.kernels.forward", "trace3d.training.kernels.adam", "trace3d.lifting.kernels.contrastive",
            "trace3d.datasets.synthetic.raycast"} <= set(manifest)


def test_units_keep_a_module_with_the_kernels_it_calls(tmp_path):
    """A module that imports another's recorded function goes to the same process; the rest stay apart;
    every module is in exactly one unit."""
    package = tmp_path / "trace3d"
    (package / "sub").mkdir(parents=True)
    for path in (package / "__init__.py", package / "sub" / "__init__.py"):
        path.write_text("")
    (package / "sub" / "callee.py").write_text("def k(): pass\ndef helper(): pass\n")
    (package / "caller.py").write_text("from .sub.callee import k\n")
    (package / "plain.py").write_text("from .sub.callee import helper\n")  # helper has no signatures
    (package / "alone.py").write_text("x = 1\n")
    manifest = {"trace3d.sub.callee": {"k": ["(int64,)"]}, "trace3d.caller": {"f": ["(int64,)", "(float64,)"]},
                "trace3d.plain": {"g": ["(int64,)"]}, "trace3d.alone": {"h": ["(int64,)"]}}
    groups = warm.units(manifest, package)
    assert sorted(sorted(g) for g in groups) == [["trace3d.alone"], ["trace3d.caller", "trace3d.sub.callee"],
                                                 ["trace3d.plain"]]
    assert sorted(groups[0]) == ["trace3d.caller", "trace3d.sub.callee"]  # the largest first
    # the package's own: a partition of the manifest's modules
    real = warm.units(warm.read_manifest())
    flat = [m for g in real for m in g]
    assert sorted(flat) == sorted(warm.read_manifest()) and len(flat) == len(set(flat))


def _warm(jobs: int) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    result = subprocess.run([sys.executable, "-m", "trace3d.tooling.warm", "--jobs", str(jobs), "--json"], cwd=REPO,
                            env=env, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "trace3d warm:" not in result.stderr, result.stderr[-3000:]  # no stale signature, no shared compile
    return json.loads(result.stdout.strip().splitlines()[-1])


def test_a_fresh_process_finds_every_warmed_kernel_in_the_cache():
    """Warm over two processes (compiles what the suite's cache lacks, loads the rest), then a fresh
    process: every recorded signature of every kernel module comes from the cache, none is compiled."""
    manifest = warm.read_manifest()
    first = _warm(2)
    assert first["cache"] == os.environ.get("NUMBA_CACHE_DIR")  # the suite's keyed folder, not keyed again
    assert sorted((m, n, s) for m, n, s, _ in first["kernels"]) == _entries(manifest)  # each once
    assert {state for *_, state in first["kernels"]} <= {"compiled", "loaded"}
    assert first["foreign"] == [] and first["processes"] == 2
    assert set(first["module_cpu_s"]) == set(manifest)
    again = _warm(1)
    assert sorted((m, n, s) for m, n, s, _ in again["kernels"]) == _entries(manifest)
    compiled = [row[:3] for row in again["kernels"] if row[3] != "loaded"]
    assert compiled == [], f"not found in the cache by a fresh process: {compiled}"
    # and --record reads the same signatures back from that cache (the index files it wrote)
    recorded = warm.record(Path(os.environ["NUMBA_CACHE_DIR"]))
    assert set(_entries(manifest)) <= set(_entries(recorded))


def test_bad_arguments_are_refused(tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        warm.main(["--jobs", "0"])
    assert stop.value.code == 2 and "--jobs takes a whole number of processes, at least 1" in capsys.readouterr().err
    assert warm.main(["--record", str(tmp_path / "nowhere")]) == 2
    assert capsys.readouterr().err.strip() == (f"trace3d warm: error: {tmp_path / 'nowhere'} is not a folder "
                                               "(a keyed subfolder of NUMBA_CACHE_DIR)")
    (tmp_path / "empty").mkdir()
    assert warm.main(["--record", str(tmp_path / "empty")]) == 2
    assert "holds no compiled kernel of this code" in capsys.readouterr().err


def test_a_signature_that_does_not_read_back_is_one_sentence(tmp_path, capsys, monkeypatch):
    """record() refuses a signature parse_signature cannot rebuild; --record says so in one line, exit 2,
    and leaves the manifest as it was."""
    before = warm.MANIFEST.read_bytes()
    monkeypatch.setattr(warm, "parse_signature", lambda text: ("not", "the same"))
    assert warm.main(["--record", os.environ["NUMBA_CACHE_DIR"]]) == 2  # the suite's cache, as above
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "does not read back" in err[0] and "teach parse_signature" in err[0], err
    assert warm.MANIFEST.read_bytes() == before
