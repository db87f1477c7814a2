"""Tests of trace3d.training.optimizer and its Adam kernel (trace3d.training.kernels.adam)."""

from __future__ import annotations

import torch

from tests.plane_scene import single_thread  # noqa: F401  (autouse fixture)


def test_adam_rows_kernel_matches_its_twin_and_leaves_other_rows():
    """The visible-Adam row kernel against its torch twin over several steps; rows not selected keep
    their parameters and moments bit for bit."""
    import math

    from trace3d.training.kernels.adam import adam_rows, adam_rows_torch

    g = torch.Generator().manual_seed(0)
    n = 3000
    start = torch.randn(n, 16, 3, generator=g)
    ours, twin = start.clone(), start.clone()
    m1, v1 = torch.zeros_like(start), torch.zeros_like(start)
    m2, v2 = torch.zeros_like(start), torch.zeros_like(start)
    picked = torch.zeros(n, dtype=torch.bool)
    for t in range(1, 6):
        rows = torch.nonzero(torch.rand(n, generator=g) < 0.3).squeeze(1)
        picked[rows] = True
        grad = torch.randn(n, 16, 3, generator=g)
        step_size, inv = 0.01 / (1 - 0.9 ** t), 1 / math.sqrt(1 - 0.999 ** t)
        adam_rows(ours, grad, m1, v1, rows, step_size, 0.9, 0.999, inv, 1e-15)
        adam_rows_torch(twin, grad, m2, v2, rows, step_size, 0.9, 0.999, inv, 1e-15)
    for a, b in ((ours, twin), (m1, m2), (v1, v2)):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    assert 0 < int(picked.sum()) < n
    assert torch.equal(ours[~picked], start[~picked]) and bool((m1[~picked] == 0).all())
    assert bool((ours[picked] != start[picked]).any())


def test_visible_adam_equals_torch_adam_when_everything_is_visible():
    """GaussianOptimizer.step(visible) with visible_adam: all rows visible = torch's Adam; some rows
    hidden = those rows untouched (parameters and moments) while the others still match Adam."""
    from trace3d.gaussians import GaussianModel
    from trace3d.training.optimizer import GaussianOptimizer
    from trace3d.training.params import TrainParams

    g = torch.Generator().manual_seed(1)
    n = 400
    model = GaussianModel(means=torch.randn(n, 3, generator=g), quats=torch.randn(n, 4, generator=g),
                          log_scales=torch.randn(n, 2, generator=g), opacity_logits=torch.randn(n, generator=g),
                          sh_dc=torch.randn(n, 1, 3, generator=g), sh_rest=torch.randn(n, 15, 3, generator=g))
    lrs = {"means": 0.01, "quats": 0.002, "log_scales": 0.005, "opacity_logits": 0.05, "sh_dc": 0.0025,
           "sh_rest": 0.000125}
    dense = GaussianOptimizer(model, lrs, TrainParams(fused_adam=False), 1.0)
    vis = GaussianOptimizer(model, lrs, TrainParams(fused_adam=False, visible_adam=True), 1.0)
    hidden = torch.arange(n) % 4 == 0
    for step in range(4):
        grads = {name: torch.randn(getattr(model, name).shape, generator=g) for name in lrs}
        for state in (dense, vis):
            for name in lrs:
                state.model.get(name).grad = grads[name].clone()
        before = {name: vis.model.get(name).detach().clone() for name in lrs}
        dense.step()
        visible = torch.ones(n, dtype=torch.bool) if step < 2 else ~hidden
        vis.step(visible)
        for name in lrs:
            a, b = vis.model.get(name).detach(), dense.model.get(name).detach()
            if step < 2:
                torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6, msg=name)
            else:
                assert torch.equal(a[hidden], before[name][hidden]), name
                # each element's update is its own, so the rendered rows still follow dense Adam
                torch.testing.assert_close(a[~hidden], b[~hidden], rtol=1e-5, atol=1e-6, msg=name)
            assert vis.model.get(name).grad is None


def test_bulk_phases_do_not_depend_on_the_torch_thread_count():
    """Adam (torch's fused kernel) and the default density control run with the process's torch
    threads inside the fit: their results must be bit-identical to one thread's."""
    import hashlib

    from trace3d.gaussians import GaussianModel
    from trace3d.threads import torch_threads
    from trace3d.training.optimizer import GaussianOptimizer, learning_rates
    from trace3d.training.params import TrainParams
    from trace3d.training.strategy import densify_and_prune, reset_stats

    g = torch.Generator().manual_seed(3)
    n = 60_000  # large enough for torch to split its loops between threads
    model = GaussianModel(means=torch.randn(n, 3, generator=g), quats=torch.randn(n, 4, generator=g),
                          log_scales=torch.randn(n, 2, generator=g) - 4.0, opacity_logits=torch.randn(n, generator=g),
                          sh_dc=torch.randn(n, 1, 3, generator=g), sh_rest=torch.randn(n, 15, 3, generator=g))
    params = TrainParams(max_gaussians=n + 5000)
    stats = torch.rand(n, generator=g) * 2e-3

    def run(threads: int) -> str:
        state = GaussianOptimizer(model, learning_rates(params, 2.0), params, 2.0)
        state.bulk_threads = threads
        noise = torch.Generator().manual_seed(7)
        for _ in range(3):
            for group in state.optimizer.param_groups:
                p = group["params"][0]
                p.grad = torch.randn(p.shape, generator=noise) * 1e-2
            state.step()
        reset_stats(state)
        state.statistics["grad_accum"] += stats
        state.statistics["grad_count"] += 1
        with torch_threads(threads):
            event = densify_and_prune(state, True, torch.Generator().manual_seed(0))
        assert event["cloned"] + event["split"] > 0 and event["pruned"] > 0
        h = hashlib.sha1()
        for name, t in sorted(state.model.tensors().items()):
            h.update(name.encode())
            h.update(t.detach().contiguous().numpy().tobytes())
        for group in state.optimizer.param_groups:
            for key in ("exp_avg", "exp_avg_sq"):
                h.update(state.optimizer.state[group["params"][0]][key].numpy().tobytes())
        return h.hexdigest()

    assert run(1) == run(2)
