"""The same bits from kernels compiled in the process and kernels loaded from numba's cache (issue 49).

One tiny contrastive lift runs twice in fresh processes on one empty ``NUMBA_CACHE_DIR``: the first
compiles every kernel the lift needs (and fills the cache), the second loads them all. Their outputs
must be equal byte for byte. (Before the fix, 30 of the 4,096 features differed in the last bits: the
first process ran the loss kernels right after compiling them.)
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

from trace3d.cli import main

REPO = Path(__file__).resolve().parents[2]
TINY_SCENE = {"width": 32, "height": 24, "num_views": 4, "test_every": 2, "num_objects": 6, "supersample": 1}
LIFT = {"iterations": 30, "pixels": 64, "pool_pixels": 256, "pca_views": 1}


def test_a_lift_gives_the_same_bits_from_compiled_and_cached_kernels(tmp_path):
    from trace3d.gaussians import GaussianModel

    scene, masks, patches = tmp_path / "scene", tmp_path / "masks", tmp_path / "patches"
    assert main(["scene", "synthetic", "--out", str(scene), "--params", json.dumps(TINY_SCENE)]) == 0
    assert main(["masks", "--scene", str(scene), "--out", str(masks)]) == 0
    assert main(["patches", "--scene", str(scene), "--masks", str(masks), "--out", str(patches)]) == 0
    generator = torch.Generator().manual_seed(0)
    n = 256
    model = GaussianModel(means=torch.randn(n, 3, generator=generator) * 0.5,
                          quats=torch.nn.functional.normalize(torch.randn(n, 4, generator=generator), dim=1),
                          log_scales=torch.full((n, 2), -2.0), opacity_logits=torch.zeros(n),
                          sh_dc=torch.rand(n, 1, 3, generator=generator), sh_rest=torch.zeros(n, 0, 3))
    (tmp_path / "gaussians").mkdir()
    model.write_ply(tmp_path / "gaussians" / "point_cloud.ply")
    env = {k: v for k, v in os.environ.items() if k != "TRACE3D_NUMBA_CACHE_KEYED"}
    env.update(NUMBA_CACHE_DIR=str(tmp_path / "cache"), PYTHONPATH=str(REPO))
    outputs = []
    for run in ("compiled", "cached"):
        out = tmp_path / f"lift-{run}"
        # no time limit: a cold compile on a busy machine (tests/conftest.py)
        argv = ["--threads", "2", "lift", "--scene", str(scene), "--gaussians", str(tmp_path / "gaussians"),
                "--labels", str(patches), "--out", str(out), "--params", json.dumps(LIFT)]
        result = subprocess.run([sys.executable, "-m", "trace3d.cli", *argv], capture_output=True, text=True, env=env,
                                cwd=tmp_path)
        assert result.returncode == 0, result.stderr[-3000:]
        compiled = "compiling kernels" in result.stderr
        assert compiled == (run == "compiled"), (run, result.stderr[-2000:])
        outputs.append(out)
    first, second = (np.load(out / "features.npy") for out in outputs)
    assert np.array_equal(first, second), f"{int((first != second).sum())} of {first.size} features differ"
    for name in ("features.npy", "loss.csv"):
        assert (outputs[0] / name).read_bytes() == (outputs[1] / name).read_bytes(), name
