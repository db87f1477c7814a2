"""The CUDA path: a user with a GPU gets the 2DGS fit's torch parts on CUDA (``gaussians: {device: auto}``,
the default) while the rasterizer's numba kernels run on the CPU. These tests run only where torch sees a
CUDA device (they are skipped on the CPU-only development and CI machines); run them there with
``pytest tests/training/test_cuda.py tests/render/test_render.py -k cuda``."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from trace3d.datasets.synthetic.params import params_from
from trace3d.datasets.synthetic.writer import generate_scene
from trace3d.scene import Scene
from trace3d.training.step import run_gaussians

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")

# a short 2DGS schedule from the room's depth (init auto), with every stage of the loop in it
FIT = {"schedule_scale": 1.0, "iterations": 150, "densify_from": 30, "densify_until": 120, "densify_interval": 30,
       "normal_from": 60, "sh_degree": 1, "sh_degree_interval": 50, "num_render_views": 2}


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    root = tmp_path_factory.mktemp("cuda") / "scene"
    generate_scene(root, params_from({"seed": 5, "width": 64, "height": 48, "num_views": 16, "num_objects": 6}))
    return Scene.read(root)


def _fit(room, out, device):
    run_gaussians(room, None, out, dict(FIT, device=device))
    return json.loads((out / "metrics.json").read_text())


def test_fit_on_cuda_matches_the_cpu_fit(room, tmp_path):
    cpu = _fit(room, tmp_path / "cpu", "cpu")
    cuda = _fit(room, tmp_path / "cuda", "cuda")
    auto = _fit(room, tmp_path / "auto", "auto")
    # the same schedule from the same seed: the trajectories may part in the last bits (CUDA's own
    # reductions), the fits may not
    for key in ("test_psnr", "train_psnr"):
        assert abs(cpu[key] - cuda[key]) < 1.0, (key, cpu[key], cuda[key])
    assert cpu["num_gaussians"] == pytest.approx(cuda["num_gaussians"], rel=0.2)
    assert cpu["device"] == "cpu" and cuda["device"].startswith("cuda") and auto["device"] == cuda["device"]
    # `auto` picks CUDA when torch sees it: the same numbers as asking for it
    assert abs(auto["test_psnr"] - cuda["test_psnr"]) < 1e-3
    # what the step wrote on CUDA is read back on the CPU like any other fit
    from trace3d.gaussians import GaussianModel

    model = GaussianModel.read_ply(tmp_path / "cuda" / "point_cloud.ply")
    assert model.means.device.type == "cpu" and len(model) == cuda["num_gaussians"]
    assert np.isfinite(model.means.numpy()).all()
