"""The CPU target the entry points choose for numba (512-bit vectors on AVX-512 CPUs): when it is set,
what it respects, that the benchmark's baseline makes its own choice, and that it changes no value."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from trace3d.tooling import cputarget

REPO = Path(__file__).resolve().parents[2]


class _FeatureMap(dict):
    """llvmlite's feature map: a dict of feature -> enabled with ``flatten()``."""

    def flatten(self):
        return ",".join(("+" if on else "-") + name for name, on in self.items())


def test_wide_vectors_only_on_avx512_and_only_when_no_target_is_named(monkeypatch):
    monkeypatch.setattr(cputarget, "host_features", lambda: _FeatureMap(avx2=True, avx512f=True, sse4_2=True))
    env = {}
    value = cputarget.set_wide_vectors(env)
    assert value == "+avx2,+avx512f,+sse4_2,-prefer-256-bit" and env == {"NUMBA_CPU_FEATURES": value}
    for named in ({"NUMBA_CPU_NAME": "skylake"}, {"NUMBA_CPU_FEATURES": "+avx2"}, {"NUMBA_ENABLE_AVX": "0"}):
        env = dict(named)
        assert cputarget.set_wide_vectors(env) is None and env == named
    # no AVX-512, or LLVM cannot tell: nothing to widen, nothing set
    monkeypatch.setattr(cputarget, "host_features", lambda: _FeatureMap(avx2=True, avx512f=False))
    env = {}
    assert cputarget.set_wide_vectors(env) is None and env == {}
    monkeypatch.setattr(cputarget, "host_features", lambda: None)
    assert cputarget.set_wide_vectors(env) is None and env == {}


def _env_without_target() -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CPU_FEATURES", "NUMBA_CPU_NAME", "NUMBA_ENABLE_AVX")}
    env["PYTHONPATH"] = os.pathsep.join([str(REPO)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    return env


def test_cli_sets_the_target_before_numba_loads():
    script = ("import os, sys; from trace3d import cli; sys.argv = ['trace3d', '--help']\n"
              "try:\n    cli.main()\nexcept SystemExit:\n    pass\n"
              "import numba, json\n"
              "print(json.dumps([os.environ.get('NUMBA_CPU_FEATURES'), numba.config.CPU_FEATURES]))")
    result = subprocess.run([sys.executable, "-c", script], cwd=REPO, env=_env_without_target(), capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-3000:]
    in_env, in_numba = json.loads(result.stdout.strip().splitlines()[-1])
    expected = cputarget.wide_vector_features()
    assert in_env == expected and in_numba == expected
    # an explicit value stays
    env = {**_env_without_target(), "NUMBA_CPU_FEATURES": "+sse2"}
    result = subprocess.run([sys.executable, "-c", script], cwd=REPO, env=env, capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stderr[-3000:]
    assert json.loads(result.stdout.strip().splitlines()[-1]) == ["+sse2", "+sse2"]


def test_bench_baseline_runs_without_the_current_entry_points_target(monkeypatch, tmp_path):
    """`bench fit --baseline`: the baseline's own entry point chooses its target; a value the user put in
    the environment is passed on."""
    import subprocess as sp

    from trace3d.bench import fit as bench

    checkout = tmp_path / "checkout"
    (checkout / "trace3d" / "training").mkdir(parents=True)
    (checkout / "trace3d" / "training" / "bench.py").write_text("")
    seen = []

    def fake_run(cmd, cwd=None, env=None, **kwargs):
        if cmd[0] == "git":
            return sp.CompletedProcess(cmd, 1, "", "")
        seen.append(env.get("NUMBA_CPU_FEATURES"))
        out = Path(cmd[cmd.index("--out") + 1])
        out.write_text(json.dumps({"sizes": {}}))
        return sp.CompletedProcess(cmd, 0, "", "")

    monkeypatch.setattr(sp, "run", fake_run)
    monkeypatch.setattr(cputarget, "_set_here", "+avx512f,-prefer-256-bit")
    monkeypatch.setenv("NUMBA_CPU_FEATURES", "+avx512f,-prefer-256-bit")
    bench.run_baseline(checkout, None, None, quick=True)
    monkeypatch.setenv("NUMBA_CPU_FEATURES", "+avx2")  # the user's own
    bench.run_baseline(checkout, None, None, quick=True)
    monkeypatch.setattr(cputarget, "_set_here", None)
    monkeypatch.setenv("NUMBA_CPU_FEATURES", "+avx512f,-prefer-256-bit")
    bench.run_baseline(checkout, None, None, quick=True)
    assert seen == [None, "+avx2", "+avx512f,-prefer-256-bit"]


# A short fit on a small generated room with every kernel of the training loop in it (projection, SH
# colours, binning, forward and backward with the normal term, the loss kernels, Adam, density control),
# then a 16-channel render and its gradients: hashes of everything, and of every stage on the way (the
# generated images, the initial Gaussians, the parameters after each iteration) so that a mismatch says
# where two runs parted.
FIT_SCRIPT = r"""
import hashlib, json, sys, tempfile
from pathlib import Path
import torch
from trace3d.datasets import synthetic
from trace3d.gaussians import init_from_depth
from trace3d.params import from_mapping
from trace3d.render import render
from trace3d.scene import Scene
from trace3d.training.loop import fit, scene_extent
from trace3d.training.params import TrainParams
from trace3d.training.step import load_images

def digest(tensors):
    return hashlib.sha256(b"".join(t.detach().contiguous().numpy().tobytes() for t in tensors)).hexdigest()

stages = []
with tempfile.TemporaryDirectory() as tmp:
    synthetic.generate_scene(Path(tmp) / "room", synthetic.params_from({"width": 64, "height": 48, "num_views": 6,
                                                                          "seed": 3}))
    scene = Scene.read(Path(tmp) / "room")
    train = list(scene.train_cameras)
    images = load_images(scene, train)
    stages.append(["images", digest(images)])
    base = TrainParams()
    model = init_from_depth(scene, train, stride=1, max_points=4000, sh_degree=base.sh_degree,
                            opacity=base.init_opacity, seed=0)
    stages.append(["initial Gaussians", {n: digest([getattr(model, n)])[:16] for n in model.PARAM_NAMES}])
params = from_mapping(TrainParams, {"iterations": 12, "schedule_scale": 1.0, "densify_from": 0, "densify_until": 13,
                                    "densify_interval": 5, "normal_from": 0, "distortion_from": 0,
                                    "initial_sh_degree": base.sh_degree, "log_interval": 1,
                                    "checkpoint_interval": 12}, "params")

def after(iteration, state):
    m = state.model
    stages.append([f"iteration {iteration} ({len(m)} Gaussians)",
                   {n: digest([getattr(m, n)])[:16] for n in m.PARAM_NAMES}])

result = fit(model, train, images, params, extent=scene_extent(train), progress=False, callback=after)
stages.append(["fit", digest([getattr(result.model, n) for n in result.model.PARAM_NAMES])])
splats = result.model.splats()
feats = torch.rand(len(result.model), 16, generator=torch.Generator().manual_seed(0)).requires_grad_()
out = render(splats, train[0], feats)
(grad,) = torch.autograd.grad((out.features * torch.linspace(0.1, 1.0, 16)).sum(), [feats])
stages.append(["16-channel render and gradient", digest([out.features, grad])])
print(json.dumps(stages))
"""


def first_difference(a: list, b: list) -> str | None:
    """The first stage at which two FIT_SCRIPT runs differ, described (None if they agree)."""
    for (name_a, value_a), (name_b, value_b) in zip(a, b):
        if name_a != name_b or value_a != value_b:
            if isinstance(value_a, dict) and isinstance(value_b, dict) and name_a == name_b:
                fields = sorted(k for k in value_a if value_a[k] != value_b.get(k))
                return f"{name_a}: {', '.join(fields)} differ"
            return f"{name_a} ({value_a}) against {name_b} ({value_b})"
    return None if len(a) == len(b) else f"{len(a)} stages against {len(b)}"


@pytest.mark.skipif(cputarget.wide_vector_features() is None, reason="no AVX-512 on this CPU: nothing is widened")
def test_wide_vectors_change_no_value():
    """The same fit and 16-channel render compiled with LLVM's default (256-bit) preference and with
    512-bit vectors give the same bits: the kernels allow no reassociation, so only the instructions'
    width differs.  (Fails if a kernel's fastmath flags let LLVM reorder a sum by vector width.)"""
    outputs = []
    narrow = cputarget.host_features().flatten()
    for features in (narrow, cputarget.wide_vector_features()):
        env = {**_env_without_target(), "NUMBA_CPU_FEATURES": features}
        result = subprocess.run([sys.executable, "-c", FIT_SCRIPT], cwd=REPO, env=env, capture_output=True,
                                text=True)  # no time limit: a cold compile on a busy machine (tests/conftest.py)
        assert result.returncode == 0, result.stderr[-3000:]
        outputs.append(json.loads(result.stdout.strip().splitlines()[-1]))
    difference = first_difference(*outputs)
    assert difference is None, f"256-bit and 512-bit runs first differ at {difference}"
    assert len(outputs[0]) == 2 + 12 + 2


def test_first_difference_names_the_stage():
    run = [["images", "a"], ["iteration 1 (5 Gaussians)", {"means": "1", "quats": "2"}], ["fit", "f"]]
    assert first_difference(run, [list(s) for s in run]) is None
    other = [run[0], ["iteration 1 (5 Gaussians)", {"means": "1", "quats": "3"}], ["fit", "g"]]
    assert first_difference(run, other) == "iteration 1 (5 Gaussians): quats differ"
    assert first_difference(run, [["images", "b"]] + run[1:]) == "images (a) against images (b)"
    assert first_difference(run, run[:2]) == "3 stages against 2"


def test_describe_reports_the_target_numba_compiles_for():
    import numba

    info = cputarget.describe()
    assert set(info) == {"model", "llvm_cpu", "avx512", "prefer_512_bit"}
    assert info["avx512"] == (cputarget.wide_vector_features() is not None)
    if cputarget.set_here() is not None:  # tests/conftest.py chose the target, as the entry points do
        assert numba.config.CPU_FEATURES == cputarget.set_here() and info["prefer_512_bit"]
    if not info["avx512"]:
        assert not info["prefer_512_bit"]
