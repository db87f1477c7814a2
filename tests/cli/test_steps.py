"""The step registry (trace3d.steps) and the code hashes derived from the import graph (trace3d.tooling.codehash)."""

from __future__ import annotations

import dataclasses
import importlib
import json
import os
import re
import shutil
import subprocess
import sys
import typing
from pathlib import Path

import pytest

from trace3d.tooling import codehash
from trace3d.steps import (BY_COMMAND, LIFT_METHODS, SIMULATE_PARAMS, STEPS, Variant, default_inconsistency,
                           fields_static, handler, lift_keys, lift_params_for, load_class, variant_defaults)

REPO = Path(__file__).resolve().parents[2]
SNAKEMAKE = shutil.which("snakemake", path=str(Path(sys.executable).parent)) or shutil.which("snakemake")


def _all_refs() -> list[str]:
    refs = {ref for s in STEPS for refs in s.params.values() for ref in refs}
    return sorted(refs | set(LIFT_METHODS.values()) | {SIMULATE_PARAMS})


# ----------------------------------------------------------------------------------------------
# the registry
# ----------------------------------------------------------------------------------------------


def test_every_command_has_a_handler_and_its_entry_functions_exist():
    for s in STEPS:
        assert callable(handler(s.command)), s.command
        for entry in s.entry:
            module, name = entry.split(":")
            assert callable(getattr(importlib.import_module(module), name)), entry


def test_static_fields_are_the_dataclasses_fields():
    """The Snakemake process reads the dataclasses' fields from their source; they are the imported ones."""
    for ref in _all_refs():
        cls = load_class(ref)
        static = fields_static(ref)
        assert [name for name, _ in static] == [f.name for f in dataclasses.fields(cls)], ref
        for (name, default), f in zip(static, dataclasses.fields(cls)):
            if default is not ... and default is not dataclasses.MISSING:
                assert default == f.default, (ref, name)


def test_lift_methods_are_the_librarys():
    from trace3d.lifting.step import METHODS, parse_lift_params

    assert tuple(LIFT_METHODS) == METHODS
    for method, ref in LIFT_METHODS.items():
        assert type(parse_lift_params({"method": method})) is load_class(ref)


def test_lift_params_keep_each_methods_own_keys():
    shared = {"iterations": 30, "pool_pixels": 512, "points": 5, "prompt_source": "graph", "min_confidence": 0.5,
              "near": 0.02, "seed": 3, "preset": "paper"}
    assert lift_params_for("labels", shared) == {"min_confidence": 0.5, "near": 0.02, "method": "labels"}
    assert lift_params_for("self_prompt", shared) == {"points": 5, "prompt_source": "graph", "near": 0.02, "seed": 3,
                                                      "preset": "paper", "method": "self_prompt"}
    assert lift_params_for("contrastive", shared) == {"iterations": 30, "pool_pixels": 512, "near": 0.02, "seed": 3,
                                                      "preset": "paper", "method": "contrastive"}
    for method, keys in lift_keys().items():  # the result parses as the method's parameters
        from trace3d.lifting.step import parse_lift_params

        parse_lift_params(lift_params_for(method, {k: v for k, v in shared.items() if k in keys}))


def test_variant_and_inconsistency_defaults_are_the_librarys():
    from trace3d.masks.simulate import SimulateParams

    assert default_inconsistency() == SimulateParams().inconsistency
    assert variant_defaults() == {"preset": "paper", "consistent_masks": True, "density_control": True,
                                  "lifting": "contrastive", "overlay": False, "merge_candidates": "coarser_mask",
                                  "merge_method": "vote", "merge_threshold": None}
    assert set(typing.get_args(typing.get_type_hints(Variant)["lifting"])) == set(LIFT_METHODS)


def test_describe_json_lists_steps_parameters_and_lift_keys(capsys):
    from trace3d.cli import main

    assert main(["describe", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert set(info["steps"]) == set(BY_COMMAND)
    lift = info["steps"]["lift"]
    assert lift["rules"] == ["lift"] and lift["entry"] == ["trace3d.lifting.step:run_lift"]
    rows = lift["params"]["lift"]["trace3d.lifting.contrastive:ContrastiveParams"]
    pool_pixels = [r for r in rows if r["name"] == "pool_pixels"][0]
    assert {"name": "pool_pixels", "default": 8192}.items() <= pool_pixels.items()
    assert info["lift_methods"]["labels"]["keys"] == ["min_confidence", "near"]
    assert info["variant"]["defaults"]["lifting"] == "contrastive"
    assert "masks.simulated" in info["steps"]["masks"]["params"]


def test_every_step_rule_hashes_the_command_it_runs():
    """Each rule that runs `trace3d <command>` hashes that command's code (step_code), and the registry
    names the rule."""
    text = "\n".join(p.read_text() for p in sorted((REPO / "rules").glob("*.smk")))
    blocks = re.split(r"\n(?=rule |use rule )", "\n" + text)
    runs: dict[str, str] = {}
    for block in blocks:
        head = re.match(r"\s*(?:rule (\w+):|use rule (\w+) as (\w+) with:)", block)
        if not head:
            continue
        name = head.group(1) or head.group(3)
        shell = re.search(r'"trace3d --threads \{threads\} ([\w-]+)', block)
        command = shell.group(1) if shell else runs.get(head.group(2) or "")
        if command is None:
            continue
        runs[name] = command
        code = re.search(r'code=step_code\("([\w-]+)"\)', block)
        if shell or "params:" in block:
            assert code and code.group(1) == command, name
        assert name in BY_COMMAND[command].rules, (name, command)
    assert {rule for s in STEPS for rule in s.rules} == set(runs)


# ----------------------------------------------------------------------------------------------
# derived code hashes
# ----------------------------------------------------------------------------------------------


def test_closures_hold_the_imports_the_hand_lists_missed():
    lift = codehash.step_modules("lift")
    for module in ("trace3d.training.kernels.adam", "trace3d.training.loop", "trace3d.training.strategy",
                   "trace3d.training.losses", "trace3d.training.kernels.losses", "trace3d.lifting.kernels.contrastive"):
        assert module in lift, module
    assert "trace3d.training.step" in codehash.step_modules("merge")  # tracing.git -> read_pose_cameras
    for command in ("evaluate", "evaluate-nvos", "segment"):
        assert "trace3d.training" in codehash.step_modules(command), command
    for command in ("evaluate", "evaluate-nvos"):  # every lifting method's loader, imported by name
        assert {"trace3d.lifting.query", "trace3d.lifting.self_prompt", "trace3d.lifting.labels"} <= set(
            codehash.step_modules(command)), command
    for command in ("scene", "poses", "masks", "patches", "overlay", "tables", "summary"):
        assert "trace3d.training.kernels.adam" not in codehash.step_modules(command), command
    for command in ("tables", "summary", "reconstruction-table"):  # no step's handler, no benchmark, no schema
        modules = codehash.step_modules(command)
        assert not [m for m in modules if m.startswith("trace3d.steps.")
                    and m not in (BY_COMMAND[command].module, "trace3d.steps.registry")]
        assert "trace3d.tooling.schema" not in modules and not [m for m in modules if m.endswith(".bench")]


def test_relative_and_function_level_imports_are_followed(tmp_path):
    package = tmp_path / "trace3d"
    (package / "sub").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "sub" / "__init__.py").write_text("from .. import leaf\n")
    (package / "sub" / "a.py").write_text("def f():\n    from .b import g\n    from ..top import h\n")
    (package / "sub" / "b.py").write_text("import os\n")
    (package / "top.py").write_text("from trace3d.sub import b\n")
    (package / "leaf.py").write_text("")
    (package / "unused.py").write_text("")
    assert codehash.closure(("trace3d.sub.a",), package) == [
        "trace3d", "trace3d.leaf", "trace3d.sub", "trace3d.sub.a", "trace3d.sub.b", "trace3d.top"]


@pytest.mark.parametrize("command", ["gaussians", "refine", "trace", "lift", "evaluate", "segment"])
def test_closure_covers_what_importing_the_step_loads(command):
    """What a fresh interpreter loads when it imports the step's handler and entry modules is inside the
    statically found closure (which also holds the imports made inside functions)."""
    s = BY_COMMAND[command]
    modules = [s.module] + [e.split(":")[0] for e in s.entry]
    # the evaluation imports every lifting method's module by name when it runs
    run = "from trace3d.evaluation.step import register_lifting_methods; register_lifting_methods()\n"
    script = (f"import sys, importlib\nfor m in {modules!r}: importlib.import_module(m)\n"
              + (run if command == "evaluate" else "") +
              "print(' '.join(sorted(m for m in sys.modules if m == 'trace3d' or m.startswith('trace3d.'))))")
    loaded = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True, cwd=REPO,
                            env=dict(os.environ, PYTHONPATH=str(REPO))).stdout.split()
    loaded = [m for m in loaded if codehash.module_file(m) is not None]  # a namespace package has no file
    missing = sorted(set(loaded) - set(codehash.step_modules(command)))
    assert not missing, f"{command}: the derived code hash misses {missing}"


def _copy_checkout(dest: Path) -> Path:
    skip = shutil.ignore_patterns("__pycache__", "*.pyc", "*.nbi", "*.nbc")
    for name in ("trace3d", "rules", "workflow"):
        shutil.copytree(REPO / name, dest / name, ignore=skip)
    shutil.copy(REPO / "Snakefile", dest / "Snakefile")
    return dest


def test_a_change_deep_in_a_closure_changes_exactly_the_steps_that_import_it(tmp_path):
    package = _copy_checkout(tmp_path) / "trace3d"
    before = {s.command: codehash.step_hash(s.command, package) for s in STEPS}
    with open(package / "training" / "kernels" / "adam.py", "a") as fh:
        fh.write("# a comment\n")
    after = {s.command: codehash.step_hash(s.command, package) for s in STEPS}
    changed = {c for c in before if before[c] != after[c]}
    assert {"gaussians", "trace", "merge", "refine", "lift", "evaluate", "evaluate-nvos", "segment"} <= changed
    assert not changed & {"scene", "poses", "masks", "patches", "overlay", "tables", "summary", "tracing-table"}


FAKE_TRACE3D = """#!/bin/sh
# stand-in for the trace3d command: makes the folders --out and --objects name
while [ $# -gt 0 ]; do
  case "$1" in --out|--objects) mkdir -p "$2"; shift;; esac
  shift
done
"""


@pytest.mark.skipif(SNAKEMAKE is None, reason="snakemake is not installed")
def test_dry_run_reruns_the_lift_after_a_change_to_the_adam_kernel(tmp_path):
    """A tiny results state (the steps up to a lift, made by a stand-in `trace3d` so that Snakemake records
    their parameters), then a comment appended to training/kernels/adam.py: the lift's code version changed
    (it imports the kernel through lifting.contrastive), the scene, poses, masks and patches' did not."""
    root = _copy_checkout(tmp_path / "checkout")
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "trace3d").write_text(FAKE_TRACE3D)
    (bin_dir / "trace3d").chmod(0o755)
    (root / "config.yaml").write_text("scenes: {a: {kind: synthetic}}\nvariants: {full: {}}\n")
    env = dict(os.environ, PATH=f"{bin_dir}{os.pathsep}{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",
               PYTHONPATH=str(root))
    targets = ["results/a/full/lift", "results/a/patches"]

    def snakemake(*args):
        result = subprocess.run([SNAKEMAKE, "--configfile=config.yaml", *args, *targets], cwd=root, env=env,
                                capture_output=True, text=True)
        assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
        return result.stdout + result.stderr

    snakemake("--cores", "1")
    assert "Nothing to be done" in snakemake("-n")
    with open(root / "trace3d" / "training" / "kernels" / "adam.py", "a") as fh:
        fh.write("# a comment\n")
    changed = {line.strip() for line in snakemake("--list-changes", "params").splitlines()
               if line.startswith("results/")}
    assert "results/a/full/lift" in changed and "results/a/gaussians" in changed
    assert not changed & {f"results/a/{step}" for step in ("scene", "poses", "masks", "patches")}
    assert re.search(r"^lift +1$", snakemake("-n"), re.M)


def _package_copy(tmp_path):
    import shutil

    from trace3d.tooling.codehash import PACKAGE

    copy = tmp_path / "trace3d"
    shutil.copytree(PACKAGE, copy, ignore=shutil.ignore_patterns("__pycache__"))
    return copy


def test_the_numba_cache_folder_follows_the_kernels_code(tmp_path):
    """A kernel's cached machine code must not outlive a change to a module it imports (numba stamps a
    cache entry with the kernel's own file only): the cache folder's key covers the kernels' closure."""
    from trace3d.tooling.codehash import kernel_cache_key, kernel_modules

    package = _package_copy(tmp_path)
    modules = kernel_modules(package)
    # the per-lane helpers and the projection constants the render kernels inline, not the reports
    assert {"trace3d.render.kernels.tiles", "trace3d.render.projection", "trace3d.training.kernels.adam",
            "trace3d.lifting.kernels.contrastive"} <= set(modules)
    assert not any(m.startswith(("trace3d.report", "trace3d.bench")) for m in modules), modules
    key = kernel_cache_key(package)
    with open(package / "report" / "effects.py", "a") as f:
        f.write("\n# not a kernel\n")
    assert kernel_cache_key(package) == key
    with open(package / "render" / "projection.py", "a") as f:
        f.write("\n# imported by the kernels\n")
    assert kernel_cache_key(package) != key


def test_key_numba_cache_is_idempotent_and_memoised(tmp_path):
    from trace3d.tooling.codehash import key_numba_cache

    package = _package_copy(tmp_path)
    env = {"NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    first = key_numba_cache(env, package)
    assert Path(first).parent == tmp_path / "cache" and env["NUMBA_CACHE_DIR"] == first
    assert key_numba_cache(env, package) == first  # a keyed folder is not keyed again
    memo = tmp_path / "cache" / "kernel-key.json"
    assert memo.exists()
    # a fresh process with the same package reads the memo; a changed kernel file gets a new folder
    assert key_numba_cache({"NUMBA_CACHE_DIR": str(tmp_path / "cache")}, package) == first
    with open(package / "render" / "kernels" / "tiles.py", "a") as f:
        f.write("\n# changed\n")
    second = key_numba_cache({"NUMBA_CACHE_DIR": str(tmp_path / "cache")}, package)
    assert second != first and Path(second).parent == tmp_path / "cache"
    assert key_numba_cache({}, package) is None  # no cache folder set: numba's default
