"""Density-control strategies: what the training loop calls to add or remove Gaussians.

The loop (:func:`trace3d.training.fit`) knows nothing of cloning, splitting or pruning. It calls
the hooks of a :class:`Strategy` at fixed points of every iteration:

- :meth:`Strategy.initialize` once, with the :class:`~trace3d.training.GaussianOptimizer`;
- :meth:`Strategy.after_backward` after ``loss.backward()`` and before the optimiser step, with
  the render output of the view (screen-space gradients, visibility, radii);
- :meth:`Strategy.after_step` after the optimiser step.

Either hook may edit the Gaussians through the optimiser (``append`` / ``keep`` / ``replace``) and
returns an event dict (or None) that the loop logs. :class:`DefaultStrategy` is the 3DGS/2DGS
adaptive density control; the GIT-guided refinement of Trace3D
(:class:`trace3d.tracing.refine.GITStrategy`) is another strategy plugged into the same loop.
"""

from __future__ import annotations

import logging
from typing import Sequence

import numpy as np
import torch
from numba import njit, prange

from ..gaussians import GaussianModel, quat_to_rotmat
from ..scene import Camera
from ..threads import torch_threads
from .optimizer import GaussianOptimizer

log = logging.getLogger(__name__)


class Strategy:
    """Base class: a strategy that never changes the Gaussians."""

    def initialize(self, state: GaussianOptimizer, schedule: dict[str, int]) -> None:
        """Called once before the first iteration (register statistics here)."""

    def after_backward(self, iteration: int, state: GaussianOptimizer, out, camera: Camera) -> dict | None:
        """Called after the loss's backward pass, before the optimiser step."""
        return None

    def after_step(self, iteration: int, state: GaussianOptimizer) -> dict | None:
        """Called after the optimiser step."""
        return None


class Strategies(Strategy):
    """Several strategies, called in order."""

    def __init__(self, strategies: Sequence[Strategy]):
        self.strategies = list(strategies)

    def initialize(self, state, schedule):
        for s in self.strategies:
            s.initialize(state, schedule)

    def after_backward(self, iteration, state, out, camera):
        events = [s.after_backward(iteration, state, out, camera) for s in self.strategies]
        return _merge_events(events)

    def after_step(self, iteration, state):
        return _merge_events([s.after_step(iteration, state) for s in self.strategies])


def _merge_events(events: list[dict | None]) -> dict | None:
    events = [e for e in events if e]
    if not events:
        return None
    merged: dict = {}
    for e in events:
        merged.update(e)
    return merged


class DefaultStrategy(Strategy):
    """The 3DGS/2DGS adaptive density control (see :mod:`trace3d.training` for the schedule).

    Density statistics (registered on the optimiser, reset after every densification):
        grad_accum: [N] sum of the NDC-space positional gradient norms over the views that saw it.
        grad_count: [N] number of such views.
        max_radii: [N] largest screen radius (pixels) seen since the last densification.
    """

    def __init__(self, generator: torch.Generator | None = None):
        self.generator = generator
        self.last_reset = None

    def initialize(self, state: GaussianOptimizer, schedule: dict[str, int]) -> None:
        self.schedule = schedule
        self.last_reset = -state.params.opacity_reset_grace
        reset_stats(state)

    def after_backward(self, iteration: int, state: GaussianOptimizer, out, camera: Camera) -> dict | None:
        p, schedule = state.params, self.schedule
        if not p.densify or iteration >= schedule["densify_until"]:
            return None
        event = None
        grad2d = out.means2d.grad if out.means2d.grad is not None else torch.zeros_like(out.means2d)
        radii = out.radii if getattr(out, "radii", None) is not None else screen_radii(state.model, camera)
        add_stats(state, grad2d, out.visible, radii, camera.width, camera.height, getattr(out, "rows", None))
        if iteration > schedule["densify_from"] and iteration % schedule["densify_interval"] == 0:
            with torch_threads(state.bulk_threads):  # the same result with any thread count (tested)
                event = densify_and_prune(state, iteration > schedule["opacity_reset_interval"], self.generator,
                                          prune_by_opacity=iteration - self.last_reset >= p.opacity_reset_grace)
        if iteration % schedule["opacity_reset_interval"] == 0:
            state.reset_opacity()
            self.last_reset = iteration
        return event


# ----------------------------------------------------------------------------------------------
# The pieces of the 3DGS/2DGS density control (functions of the optimiser state)
# ----------------------------------------------------------------------------------------------


def reset_stats(state: GaussianOptimizer) -> None:
    for name in ("grad_accum", "grad_count", "max_radii"):
        state.add_statistic(name)


@torch.no_grad()
def add_stats(state: GaussianOptimizer, means2d_grad: torch.Tensor, visible: torch.Tensor, radii: torch.Tensor,
              width: int, height: int, rows: torch.Tensor | None = None) -> None:
    """Accumulate one view's density statistics.

    Args:
        means2d_grad: [N, 2] gradient of the loss w.r.t. the projected centres (pixels).
        visible: [N] bool, Gaussians the view rendered.
        radii: [N] screen radii (pixels) in the view.
        width, height: image size; the gradient is converted to NDC units (x W/2, x H/2).
        rows: with compact gradients, the model rows [R] (distinct) of the rendered splats: the three
            arguments above are then [R, ...], one entry per row.
    """
    stats = state.statistics
    scale = torch.tensor([width / 2.0, height / 2.0], device=means2d_grad.device, dtype=means2d_grad.dtype)
    norms = (means2d_grad * scale).norm(dim=-1)
    accum, count, radii_max = stats["grad_accum"], stats["grad_count"], stats["max_radii"]
    if (_stats_kernel_applies(norms, visible, radii) and _stats_kernel_applies(accum, count, radii_max)
            and (rows is not None or norms.shape[0] == accum.shape[0])):
        # one parallel pass instead of three masked gathers and scatters (the same additions and
        # maxima element by element, so the statistics are bit-identical to the torch lines below)
        entries = np.arange(accum.shape[0], dtype=np.int64) if rows is None else rows.numpy()
        _accumulate_stats(accum.numpy(), count.numpy(), radii_max.numpy(), entries, norms.numpy(), visible.numpy(),
                          radii.numpy())
        return
    seen = visible if rows is None else rows[visible]
    accum[seen] += norms[visible]
    count[seen] += 1
    radii_max[seen] = torch.maximum(radii_max[seen], radii[visible].to(radii_max.dtype))


def _stats_kernel_applies(*tensors) -> bool:
    """CPU contiguous 1D tensors of one length: float32, except a bool (visible) and an int32 (radii)."""
    kinds = {torch.float32, torch.bool, torch.int32}
    return (all(t.device.type == "cpu" and t.is_contiguous() and not t.requires_grad and t.dtype in kinds
                and t.dim() == 1 for t in tensors)
            and len({t.shape[0] for t in tensors}) == 1
            and sum(t.dtype == torch.bool for t in tensors) <= 1 and sum(t.dtype == torch.int32 for t in tensors) <= 1)


@njit(parallel=True, cache=True)
def _accumulate_stats(accum, count, radii_max, rows, norms, visible, radii):
    """``add_stats``' three masked updates in one pass (twin: its torch lines, tested equal); entry j
    (norms, visible, radii) belongs to Gaussian rows[j] (distinct rows: race-free)."""
    for j in prange(rows.shape[0]):
        if visible[j]:
            i = rows[j]
            accum[i] += norms[j]
            count[i] += np.float32(1.0)
            r = np.float32(radii[j])
            if r > radii_max[i]:
                radii_max[i] = r


@torch.no_grad()
def mean_grads(state: GaussianOptimizer) -> torch.Tensor:
    """[N] mean NDC positional gradient since the last densification (0 where never seen)."""
    accum, count = state.statistics["grad_accum"], state.statistics["grad_count"]
    return torch.where(count > 0, accum / count.clamp_min(1), torch.zeros_like(accum))


@torch.no_grad()
def densify_and_prune(state: GaussianOptimizer, use_size_limits: bool, generator: torch.Generator | None = None,
                      prune_by_opacity: bool = True) -> dict[str, int]:
    """One 2DGS densification step: clone, split, then prune; resets the statistics.

    Args:
        use_size_limits: also prune Gaussians larger than ``max_screen_size`` pixels or
            ``max_world_size`` x extent (2DGS: after the first opacity reset).
        generator: random source for the split positions.
        prune_by_opacity: prune Gaussians with opacity below ``opacity_cull`` (off shortly
            after an opacity reset).
    Returns:
        counts {"cloned", "split", "pruned", "total"}.
    """
    p = state.params
    clone_mask, split_mask = densify_candidates(state)
    n_before = len(state)
    cloned = int(clone_mask.sum())
    split = int(split_mask.sum())
    # The edit is clone (append copies), split (append children, drop the parents), then prune, done
    # as one copy of every tensor: the rows after cloning and splitting are the old rows without the
    # split parents, then the clones, then the children, and the pruning criteria are read from them.
    model = state.model
    parts = []
    if cloned:
        parts.append(model.subset(clone_mask))
    if split:
        parts.append(split_gaussians(model.subset(split_mask), p.split_count, generator))
    added = GaussianModel.concat(parts) if parts else None
    stay = ~split_mask
    opacities = model.opacities.detach()[stay]
    max_scale = model.scales.detach().max(dim=1).values[stay]
    radii = state.statistics["max_radii"][stay]
    if added is not None:
        opacities = torch.cat([opacities, added.opacities.detach()])
        max_scale = torch.cat([max_scale, added.scales.detach().max(dim=1).values])
        radii = torch.cat([radii, torch.full((len(added),), state._fills["max_radii"], dtype=radii.dtype,
                                             device=radii.device)])
    prune_mask = opacities < p.opacity_cull
    if not prune_by_opacity:
        prune_mask[:] = False
    if use_size_limits:
        prune_mask |= radii > p.max_screen_size
        prune_mask |= max_scale > p.max_world_size * state.extent
    if bool(prune_mask.all()):
        log.warning("density control would prune all %d Gaussians; keeping them", len(prune_mask))
        prune_mask[:] = False
    pruned = int(prune_mask.sum())
    if cloned or split or pruned:
        n_stay = int(stay.sum())
        keep_old = stay.clone()
        keep_old[stay] = ~prune_mask[:n_stay]
        if added is not None:
            added = added.subset(~prune_mask[n_stay:])
        state.edit(keep_old, added)
    reset_stats(state)
    log.debug("densify: %d -> %d (cloned %d, split %d, pruned %d)", n_before, len(state), cloned, split, pruned)
    return {"cloned": cloned, "split": split, "pruned": pruned, "total": len(state)}


def densify_candidates(state: GaussianOptimizer) -> tuple[torch.Tensor, torch.Tensor]:
    """[N] bool masks of the Gaussians to clone (mean NDC gradient at the threshold, small) and to
    split (the same, large), limited to the Gaussian budget (highest gradients first)."""
    p = state.params
    grads = mean_grads(state)
    max_scale = state.model.scales.max(dim=1).values
    high_grad = grads >= p.densify_grad_threshold
    room = max(0, p.max_gaussians - len(state))
    clone_mask = high_grad & (max_scale <= p.percent_dense * state.extent)
    split_mask = high_grad & (max_scale > p.percent_dense * state.extent)
    return _limit_growth(clone_mask, split_mask, grads, room, p.split_count)


def _limit_growth(clone_mask: torch.Tensor, split_mask: torch.Tensor, grads: torch.Tensor, room: int,
                  split_count: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Keep the highest-gradient candidates so that the model grows by at most ``room`` Gaussians."""
    growth = int(clone_mask.sum()) + int(split_mask.sum()) * (split_count - 1)
    if growth <= room:
        return clone_mask, split_mask
    candidates = torch.nonzero(clone_mask | split_mask).squeeze(1)
    order = candidates[torch.argsort(grads[candidates], descending=True)]
    cost = torch.where(split_mask[order], split_count - 1, 1)
    chosen = order[torch.cumsum(cost, 0) <= room]
    keep = torch.zeros_like(clone_mask)
    keep[chosen] = True
    return clone_mask & keep, split_mask & keep


def split_gaussians(parents: GaussianModel, count: int, generator: torch.Generator | None = None,
                    scale_divisor: float | None = None, position_std: float = 1.0) -> GaussianModel:
    """Replace each parent by ``count`` children.

    Children sample their centres from the parent disk used as a PDF (normal with std
    ``position_std`` x (s_u, s_v) along t_u, t_v and 0 along the normal, i.e. in the tangent plane),
    divide the scales by ``scale_divisor`` (default 0.8 x count, the 2DGS split) and copy every other
    attribute, extras included.

    Args:
        parents: M Gaussians.
    Returns:
        M * count Gaussians (children of parent i at rows i, M + i, 2M + i, ...).
    """
    divisor = 0.8 * count if scale_divisor is None else float(scale_divisor)
    children = parents.map(lambda t: t.detach().repeat(count, *([1] * (t.ndim - 1))))
    scales = children.scales
    stds = torch.cat([scales, torch.zeros_like(scales[:, :1])], dim=1) * position_std
    noise = torch.randn(stds.shape, generator=generator, device="cpu").to(stds.device)
    offsets = noise * stds
    rotations = quat_to_rotmat(children.quats)
    children.means = torch.bmm(rotations, offsets[..., None])[..., 0] + children.means
    children.log_scales = torch.log(scales / divisor)
    return children


def screen_radii(model: GaussianModel, camera: Camera) -> torch.Tensor:
    """[N] approximate 3-sigma screen radius (pixels) of every Gaussian in ``camera`` (0 behind it)."""
    with torch.no_grad():
        rot = torch.as_tensor(camera.rotation, dtype=model.means.dtype, device=model.device)
        trans = torch.as_tensor(camera.translation, dtype=model.means.dtype, device=model.device)
        depth = model.means.detach() @ rot[2] + trans[2]
        focal = float(max(camera.K[0, 0], camera.K[1, 1]))
        radius = 3.0 * model.scales.detach().max(dim=1).values * focal / depth.clamp_min(1e-6)
        return torch.where(depth > 0, radius, torch.zeros_like(radius))
