"""Tests of trace3d.training.sparse: compact gradients (row copies, and fits equal to the dense path bit for bit)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.plane_scene import PLANE_Z, look_at, plane_points, plane_views, single_thread, tiny_params  # noqa: F401
from trace3d.gaussians import GaussianModel, init_from_points
from trace3d.scene import Camera
from trace3d.training import fit


def test_row_copies_equal_torch_index_operations():
    from trace3d.training.sparse import clear_rows, gather_rows, scatter_rows

    g = torch.Generator().manual_seed(0)
    n = 500
    tensors = [torch.randn(n, 3, generator=g), torch.randn(n, 15, 3, generator=g), torch.randn(n, generator=g),
               torch.randint(0, 9, (n, 2), generator=g), torch.randn(n, 4, generator=g, dtype=torch.float64)]
    rows = torch.nonzero(torch.rand(n, generator=g) < 0.3).squeeze(1)
    gathered = gather_rows(tensors, rows)
    for t, out in zip(tensors, gathered):
        assert out.dtype == t.dtype and torch.equal(out, t.index_select(0, rows))
    ours = [t.clone() for t in tensors]
    twin = [t.clone() for t in tensors]
    sources = [torch.randn(out.shape, generator=g).to(out.dtype) for out in gathered]
    scatter_rows(ours, rows, sources)
    for t, s in zip(twin, sources):
        t.index_copy_(0, rows, s)
    assert all(torch.equal(a, b) for a, b in zip(ours, twin))
    clear_rows(ours, rows)
    for t in twin:
        t.index_fill_(0, rows, 0)
    assert all(torch.equal(a, b) for a, b in zip(ours, twin))
    untouched = 0 if 0 not in rows else 1
    assert not torch.equal(ours[1], tensors[1]) and torch.equal(ours[1][untouched], tensors[1][untouched])


@pytest.mark.parametrize("overrides", [{}, {"visible_adam": True}])
def test_compact_gradients_give_the_dense_fit_bit_for_bit(overrides, monkeypatch):
    """A fit with compact gradients (the default on the CPU) equals the dense autograd path exactly:
    parameters, history and density events, through clones, splits, prunes and an opacity reset, with
    views that see only part of the Gaussians."""
    from trace3d.training import loop, sparse

    cameras, images = plane_views(6)
    model = init_from_points(plane_points(), np.full((300, 3), 0.5), sh_degree=1, seed=0)
    rows, _, _ = sparse.visible_rows(model, cameras[0], 0.01)
    assert 0 < rows.numel() < len(model)  # the views see part of the plane
    params = dict(iterations=90, densify_from=20, densify_until=80, densify_interval=10, opacity_reset_interval=40,
                  normal_from=30, sh_degree_interval=30, log_interval=1, **overrides)
    views = []
    monkeypatch.setattr(loop, "CompactView", lambda *a: views.append(1) or sparse.CompactView(*a))
    states = {False: [], True: []}

    def record(kind):
        def callback(iteration, state):  # every iteration: density statistics and the means' Adam moments
            moments = state.optimizer.state[state.model.means]
            states[kind].append([t.clone() for t in state.statistics.values()]
                                + [moments["exp_avg"].clone(), moments["exp_avg_sq"].clone()])
        return callback

    dense = fit(model, cameras, images, tiny_params(sparse_grad=False, **params), progress=False,
                callback=record(False))
    assert not views
    compact = fit(model, cameras, images, tiny_params(**params), progress=False, callback=record(True))
    assert len(views) == 90
    assert len(states[True]) == 90
    for a, b in zip(states[False], states[True]):
        assert all(torch.equal(x, y) for x, y in zip(a, b))
    assert any(e["split"] + e["cloned"] > 0 for e in compact.densify_events)
    assert any(e.get("pruned", 0) > 0 for e in compact.densify_events)
    for name in GaussianModel.PARAM_NAMES:
        assert torch.equal(getattr(dense.model, name), getattr(compact.model, name)), name
    assert [{k: v for k, v in r.items() if k != "seconds"} for r in dense.history] == \
        [{k: v for k, v in r.items() if k != "seconds"} for r in compact.history]
    assert dense.densify_events == compact.densify_events


def test_compact_gradients_with_a_view_that_sees_nothing():
    """A training view facing away from every Gaussian: the compact path renders zero rows and still
    gives the dense fit exactly (and the row copies accept empty row sets)."""
    from trace3d.training.sparse import clear_rows, gather_rows, scatter_rows, visible_rows

    cameras, images = plane_views(4)
    c = cameras[0]
    away = Camera("away", "train", c.width, c.height, c.K,
                  look_at(np.zeros(3), np.array([0.0, 0.0, -PLANE_Z])))
    cameras.append(away)
    images.append(torch.zeros_like(images[0]))
    model = init_from_points(plane_points(), np.full((300, 3), 0.5), sh_degree=1, seed=0)
    assert visible_rows(model, away, 0.01)[0].numel() == 0
    fits = [fit(model, cameras, images, tiny_params(iterations=40, densify_from=10, densify_interval=10,
                                                     sparse_grad=sparse), progress=False) for sparse in (False, True)]
    for name in GaussianModel.PARAM_NAMES:
        assert torch.equal(getattr(fits[0].model, name), getattr(fits[1].model, name)), name
    empty = torch.zeros(0, dtype=torch.int64)
    t = torch.randn(10, 3)
    assert gather_rows([t], empty)[0].shape == (0, 3)
    before = t.clone()
    scatter_rows([t], empty, [torch.zeros(0, 3)])
    clear_rows([t], empty)
    assert torch.equal(t, before)
