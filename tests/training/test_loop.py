"""Tests of trace3d.training.loop: learning-rate schedule, scene extent, fit() on the tiny plane and divergence."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.plane_scene import plane_points, plane_views, single_thread, tiny_params  # noqa: F401  (autouse fixture)
from trace3d.gaussians import init_from_points
from trace3d.scene import Camera
from trace3d.training import TrainingDiverged, evaluate_views, exponential_lr, fit, points_extent, scene_extent


def test_exponential_lr_endpoints_and_monotone():
    assert exponential_lr(0, 1.6e-4, 1.6e-6, 100) == pytest.approx(1.6e-4)
    assert exponential_lr(100, 1.6e-4, 1.6e-6, 100) == pytest.approx(1.6e-6)
    assert exponential_lr(50, 1.6e-4, 1.6e-6, 100) == pytest.approx(1.6e-5)
    assert exponential_lr(500, 1.6e-4, 1.6e-6, 100) == pytest.approx(1.6e-6)


def test_scene_extent():
    cams = [Camera(f"c{i}", "train", 4, 4, np.eye(3), np.eye(4)) for i in range(2)]
    cams[1].world_to_camera[0, 3] = -2.0  # centre at x = 2
    assert scene_extent(cams) == pytest.approx(1.1)
    assert scene_extent(cams[:1]) == 1.0
    # inside-out: points on a sphere of radius 3 around the camera centroid (1, 0, 0)
    dirs = torch.nn.functional.normalize(torch.randn(501, 3, generator=torch.Generator().manual_seed(0)), dim=-1)
    points = dirs * 3.0 + torch.tensor([1.0, 0.0, 0.0])
    assert points_extent(points, cams) == pytest.approx(3.3, rel=1e-5)


def test_fit_reduces_loss_and_reaches_psnr_on_tiny_scene():
    cameras, images = plane_views(6)
    model = init_from_points(plane_points(), np.full((300, 3), 0.5), sh_degree=1, seed=0)
    params = tiny_params()
    before, _ = evaluate_views(model, cameras, images, 1, None)
    result = fit(model, cameras, images, params, progress=False)
    after, _ = evaluate_views(result.model, cameras, images, 1, None)
    assert result.history[-1]["loss"] < 0.5 * result.history[0]["loss"]
    assert np.mean([r["psnr"] for r in before]) < 15.0
    assert np.mean([r["psnr"] for r in after]) > 25.0
    assert any(e["split"] + e["cloned"] > 0 for e in result.densify_events)
    assert len(result.model) > 300
    # deterministic from the seed
    again = fit(model, cameras, images, tiny_params(iterations=20, densify=False), progress=False)
    again2 = fit(model, cameras, images, tiny_params(iterations=20, densify=False), progress=False)
    torch.testing.assert_close(again.model.means, again2.model.means)


def test_fit_gives_the_same_bits_at_one_and_two_threads():
    """The fit's files do not depend on ``--threads`` (the rasterizer's backward sums a fixed number of
    gradient buffers, TrainParams.grad_buffers): the `gaussians` and `refine` rules run as 1-thread jobs
    with the bits of a 2-thread run. Densification, the normal loss and SH degree 1 are all inside the run."""
    from trace3d.threads import limit_threads

    cameras, images = plane_views(4)
    model = init_from_points(plane_points(), np.full((300, 3), 0.5), sh_degree=1, seed=0)
    params = tiny_params(iterations=60, densify_from=10, densify_until=50, densify_interval=10, normal_from=20,
                         sh_degree_interval=30)
    models = []
    for threads in (1, 2):
        with limit_threads(threads):
            models.append(fit(model, cameras, images, params, progress=False).model)
    one, two = models
    assert len(one) == len(two) > 300  # densified
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest"):
        assert torch.equal(getattr(one, name), getattr(two, name)), name


def test_fit_divergence_raises_with_last_good_checkpoint():
    cameras, images = plane_views(4)
    images[2] = images[2].clone()
    images[2][3, 4, 1] = float("nan")  # the loss is NaN whenever view 2 is drawn
    model = init_from_points(plane_points(60), np.full((60, 3), 0.5), sh_degree=0, seed=0)
    with pytest.raises(TrainingDiverged, match="diverged") as info:
        fit(model, cameras, images, tiny_params(iterations=50, checkpoint_interval=1, densify=False, log_interval=1),
            progress=False)
    exc = info.value
    assert exc.iteration >= 1 and exc.checkpoint_iteration == exc.iteration - 1
    assert exc.checkpoint.is_finite() and len(exc.checkpoint) == 60
    assert len(exc.history) == exc.iteration - 1


@pytest.mark.parametrize("inject_at", [3, 4])
def test_fit_divergence_from_a_gradient_is_caught_in_its_iteration(monkeypatch, inject_at):
    """With compact gradients the loop checks the view's gradients instead of every parameter, except
    at checkpoints: a non-finite gradient must still stop the fit in the iteration it appears (3: not a
    checkpoint, 4: one), with the last checkpoint finite."""
    from trace3d.training.optimizer import GaussianOptimizer

    cameras, images = plane_views(4)
    model = init_from_points(plane_points(60), np.full((60, 3), 0.5), sh_degree=0, seed=0)
    original = GaussianOptimizer.sparse_step
    calls = []

    def poisoned(self, rows, grads, sources, visible=None):
        calls.append(1)
        if len(calls) == inject_at:
            grads["means"][0, 1] = float("inf")
        return original(self, rows, grads, sources, visible)

    monkeypatch.setattr(GaussianOptimizer, "sparse_step", poisoned)
    with pytest.raises(TrainingDiverged, match="non-finite at iteration") as info:
        fit(model, cameras, images, tiny_params(iterations=20, checkpoint_interval=2, densify=False, log_interval=1),
            progress=False)
    exc = info.value
    assert exc.iteration == inject_at
    assert exc.checkpoint_iteration == 2 and exc.checkpoint.is_finite()
