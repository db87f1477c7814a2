"""Tests of trace3d.training.strategy: the 2DGS adaptive density control on constructed cases and
against its former append/keep form."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.plane_scene import single_thread, tiny_params  # noqa: F401  (autouse fixture)
from trace3d.gaussians import GaussianModel
from trace3d.training import GaussianOptimizer, densify_and_prune, learning_rates, split_gaussians


def constructed_model() -> GaussianModel:
    """Six Gaussians, ordered: small-hot, large-hot, cold, transparent, huge, ordinary."""
    n = 6
    scales = torch.tensor([[0.005, 0.002], [0.05, 0.03], [0.005, 0.005], [0.005, 0.005], [0.5, 0.1], [0.02, 0.02]])
    opac = torch.tensor([0.5, 0.5, 0.5, 0.01, 0.5, 0.5])
    return GaussianModel(
        means=torch.arange(n, dtype=torch.float32)[:, None] * torch.tensor([1.0, 0.0, 0.0]),
        quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
        log_scales=scales.log(),
        opacity_logits=torch.logit(opac),
        sh_dc=torch.arange(n, dtype=torch.float32)[:, None, None].repeat(1, 1, 3),
        sh_rest=torch.zeros(n, 3, 3),
    )


def densify_stats(state: GaussianOptimizer) -> None:
    from trace3d.training.strategy import reset_stats

    reset_stats(state)


def constructed_state(**overrides) -> GaussianOptimizer:
    # extent 1: clone when max scale <= 0.01, split above; world-size prune above 0.1
    params = tiny_params(**overrides)
    state = GaussianOptimizer(constructed_model(), learning_rates(params, 1.0), params, extent=1.0)
    densify_stats(state)
    # mean NDC gradients: hot = 1e-3 (above 2e-4), cold = 1e-5; seen by 2 views
    hot = torch.tensor([1e-3, 1e-3, 1e-5, 1e-5, 1e-5, 1e-5])
    state.statistics["grad_accum"] = hot * 2
    state.statistics["grad_count"] = torch.full((6,), 2.0)
    state.statistics["max_radii"] = torch.tensor([1.0, 5.0, 1.0, 1.0, 4.0, 30.0])  # the last is too large on screen
    # give Adam moments we can follow through the edits
    for group in state.optimizer.param_groups:
        param = group["params"][0]
        state.optimizer.state[param] = {
            "step": torch.tensor(3.0),
            "exp_avg": torch.ones_like(param) * torch.arange(6).view(-1, *[1] * (param.ndim - 1)),
            "exp_avg_sq": torch.ones_like(param),
        }
    return state


def test_densify_clones_splits_and_prunes_without_size_limits():
    state = constructed_state()
    before = state.model.detached_copy()
    event = densify_and_prune(state, use_size_limits=False, generator=torch.Generator().manual_seed(0))
    assert event == {"cloned": 1, "split": 1, "pruned": 1, "total": 7}
    ids = state.model.sh_dc[:, 0, 0].round().long().tolist()
    # originals except the split (1) and the transparent (3) one, then the clone of 0, then 2 children of 1
    assert ids == [0, 2, 4, 5, 0, 1, 1]
    # clone: identical copy
    torch.testing.assert_close(state.model.means[4], before.means[0])
    torch.testing.assert_close(state.model.log_scales[4], before.log_scales[0])
    # split children: scales / (0.8 * 2), centres on the parent's disk (z offset 0: normal is +z)
    torch.testing.assert_close(state.model.scales[5:], before.scales[1].expand(2, 2) / 1.6)
    offsets = state.model.means[5:] - before.means[1]
    assert (offsets[:, 2].abs() < 1e-7).all() and (offsets[:, :2].abs() > 0).any()
    assert not torch.allclose(state.model.means[5], state.model.means[6])
    # Adam moments follow the survivors; new Gaussians start at zero
    exp_avg = state.optimizer.state[state.model.means]["exp_avg"][:, 0]
    torch.testing.assert_close(exp_avg, torch.tensor([0.0, 2, 4, 5, 0, 0, 0]))
    for group in state.optimizer.param_groups:
        assert group["params"][0] is getattr(state.model, group["name"])
        assert state.optimizer.state[group["params"][0]]["exp_avg"].shape == group["params"][0].shape
    # statistics are reset
    assert state.statistics["grad_accum"].shape == (7,) and float(state.statistics["grad_accum"].abs().sum()) == 0.0


def test_densify_size_limits_prune_huge_and_screen_large():
    state = constructed_state()
    event = densify_and_prune(state, use_size_limits=True, generator=torch.Generator().manual_seed(0))
    # also pruned: 4 (world size 0.5 > 0.1 x extent) and 5 (30 px > 20 px on screen)
    assert event["pruned"] == 3
    assert state.model.sh_dc[:, 0, 0].round().long().tolist() == [0, 2, 0, 1, 1]


def test_densify_respects_opacity_grace_and_growth_cap():
    state = constructed_state()
    event = densify_and_prune(state, use_size_limits=False, prune_by_opacity=False)
    assert event["pruned"] == 0 and event["total"] == 8
    capped = constructed_state(max_gaussians=7)  # room for one more: the clone (same gradient; cheaper first)
    event = densify_and_prune(capped, use_size_limits=False)
    assert event["cloned"] + event["split"] == 1 and len(capped) <= 7


def test_split_gaussians_statistics():
    parent = constructed_model().subset(torch.tensor([1]))
    parent.quats[:] = torch.tensor([0.7071068, 0.7071068, 0.0, 0.0])  # 90 deg about x: t_v -> z
    children = split_gaussians(parent, 2, torch.Generator().manual_seed(0))
    assert len(children) == 2
    many = split_gaussians(parent.map(lambda t: t.repeat(*([4000] + [1] * (t.ndim - 1)))), 2,
                           torch.Generator().manual_seed(1))
    offsets = many.means - parent.means
    std = offsets.std(dim=0)
    # s_u = 0.05 along x, s_v = 0.03 along t_v = z after the rotation, nothing along the normal (y)
    torch.testing.assert_close(std, torch.tensor([0.05, 0.0, 0.03]), atol=2e-3, rtol=0)


def test_reset_opacity_caps_and_zeroes_moments():
    state = constructed_state()
    state.reset_opacity(0.01)
    opacities = state.model.opacities.detach()
    assert float(opacities.max()) == pytest.approx(0.01, rel=1e-4)
    moments = state.optimizer.state[state.model.opacity_logits]
    assert float(moments["exp_avg"].abs().sum()) == 0.0


def test_density_statistics_kernel_matches_torch_lines():
    """add_stats' fused pass gives bit for bit the statistics of its masked torch updates."""
    from trace3d.training import strategy as st

    g = torch.Generator().manual_seed(0)
    n = 5000
    accum = torch.rand(n, generator=g)
    count = torch.randint(0, 5, (n,), generator=g).float()
    radii_max = torch.randint(0, 9, (n,), generator=g).float()
    norms = torch.rand(n, generator=g) * 1e-3
    visible = torch.rand(n, generator=g) < 0.3
    radii = torch.randint(0, 12, (n,), generator=g, dtype=torch.int32)
    assert st._stats_kernel_applies(accum, count, radii_max, norms, visible, radii)
    a, c, r = accum.clone(), count.clone(), radii_max.clone()
    st._accumulate_stats(a.numpy(), c.numpy(), r.numpy(), np.arange(n), norms.numpy(), visible.numpy(),
                         radii.numpy())
    accum[visible] += norms[visible]
    count[visible] += 1
    radii_max[visible] = torch.maximum(radii_max[visible], radii[visible].to(radii_max.dtype))
    assert torch.equal(a, accum) and torch.equal(c, count) and torch.equal(r, radii_max)
    assert not torch.equal(r, torch.maximum(radii_max, radii.float()))  # hidden rows kept their maxima
    assert not st._stats_kernel_applies(accum, count, radii_max, norms.double(), visible, radii)


def _append_reference(state, new):
    """GaussianOptimizer.append as written before edit(): concatenate, zero moments, fill statistics."""
    for name in state.model.names:
        old = state.model.get(name)
        extra = new.get(name).detach()
        state.replace(name, torch.cat([old.detach(), extra]),
                      lambda moment, extra=extra: torch.cat([moment, torch.zeros_like(extra)]))
    for name, value in state.statistics.items():
        state.statistics[name] = torch.cat([value, torch.full((len(new),), state._fills[name], dtype=value.dtype)])


def _keep_reference(state, mask):
    """GaussianOptimizer.keep as written before edit(): boolean indexing of everything."""
    for name in state.model.names:
        state.replace(name, state.model.get(name).detach()[mask], lambda moment: moment[mask])
    for name, value in state.statistics.items():
        state.statistics[name] = value[mask]


def _densify_reference(state, use_size_limits, generator, prune_by_opacity=True):
    """densify_and_prune as three edits (clone: append, split: append + keep, prune: keep), the
    way it was written before the single-copy edit, with the edits as they were written then: its
    twin."""
    from trace3d.training.strategy import densify_candidates, reset_stats, split_gaussians

    p = state.params
    clone_mask, split_mask = densify_candidates(state)
    cloned = int(clone_mask.sum())
    if cloned:
        _append_reference(state, state.model.subset(clone_mask))
        split_mask = torch.cat([split_mask, torch.zeros(cloned, dtype=torch.bool)])
    split = int(split_mask.sum())
    if split:
        _append_reference(state, split_gaussians(state.model.subset(split_mask), p.split_count, generator))
        _keep_reference(state, torch.cat([~split_mask, torch.ones(split * p.split_count, dtype=torch.bool)]))
    prune_mask = state.model.opacities < p.opacity_cull
    if not prune_by_opacity:
        prune_mask[:] = False
    if use_size_limits:
        prune_mask |= state.statistics["max_radii"] > p.max_screen_size
        prune_mask |= state.model.scales.max(dim=1).values > p.max_world_size * state.extent
    if bool(prune_mask.all()):
        prune_mask[:] = False
    pruned = int(prune_mask.sum())
    if pruned:
        _keep_reference(state, ~prune_mask)
    reset_stats(state)
    return {"cloned": cloned, "split": split, "pruned": pruned, "total": len(state)}


@pytest.mark.parametrize("case", ["all", "no_split", "nothing_pruned", "size_limits_off", "extras"])
def test_densify_single_edit_equals_append_and_keep(case):
    """densify_and_prune's one-copy edit gives bit for bit the parameters, Adam moments, statistics
    and counts of clone, split and prune done one after another with append and keep."""
    from trace3d.gaussians import GaussianModel
    from trace3d.training.optimizer import GaussianOptimizer, learning_rates
    from trace3d.training.params import TrainParams
    from trace3d.training.strategy import densify_and_prune, reset_stats

    g = torch.Generator().manual_seed(5)
    n = 3000
    log_scales = torch.randn(n, 2, generator=g) - 4.0
    if case == "no_split":
        log_scales = log_scales.clamp_max(-6.0)  # all small: clones only
    extras = {"features": torch.randn(n, 4, generator=g)} if case == "extras" else {}
    model = GaussianModel(means=torch.randn(n, 3, generator=g), quats=torch.randn(n, 4, generator=g),
                          log_scales=log_scales, opacity_logits=torch.randn(n, generator=g) * 3,
                          sh_dc=torch.randn(n, 1, 3, generator=g), sh_rest=torch.randn(n, 15, 3, generator=g),
                          extras=extras)
    if case == "nothing_pruned":
        model.opacity_logits = model.opacity_logits.abs() + 1.0
    params = TrainParams(max_gaussians=n + 700, max_screen_size=15.0, max_world_size=0.01)
    stats = (torch.rand(n, generator=g) * 1.2e-3, torch.randint(0, 30, (n,), generator=g).float())
    grads = {name: torch.randn(getattr(model, name).shape, generator=g) * 1e-2 for name in GaussianModel.PARAM_NAMES}
    results = []
    for fn in (densify_and_prune, _densify_reference):
        state = GaussianOptimizer(model, learning_rates(params, 2.0), params, 2.0)
        for name, grad in grads.items():
            state.model.get(name).grad = grad.clone()
        state.step()
        reset_stats(state)
        state.add_statistic("other", fill=7.0)
        state.statistics["grad_accum"] += stats[0]
        state.statistics["grad_count"] += 1
        state.statistics["max_radii"] += stats[1] if case != "nothing_pruned" else 0
        state.statistics["other"] += torch.arange(n, dtype=torch.float32)
        use_limits = case not in ("size_limits_off", "nothing_pruned")
        event = fn(state, use_limits, torch.Generator().manual_seed(0))
        moments = [state.optimizer.state[gr["params"][0]][k] for gr in state.optimizer.param_groups
                   for k in ("exp_avg", "exp_avg_sq")]
        results.append((event, state.model.tensors(), moments, dict(state.statistics)))
    (e1, t1, m1, s1), (e2, t2, m2, s2) = results
    assert e1 == e2
    assert e1["cloned"] > 0 and (e1["split"] > 0) == (case != "no_split")
    assert (e1["pruned"] > 0) == (case != "nothing_pruned")
    assert t1.keys() == t2.keys() and s1.keys() == s2.keys()
    for name in t1:
        assert torch.equal(t1[name].detach(), t2[name].detach()), name
    for a, b in zip(m1, m2):
        assert torch.equal(a, b)
    for name in s1:
        assert torch.equal(s1[name], s2[name]), name
