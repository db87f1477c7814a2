"""A :class:`~trace3d.gaussians.GaussianModel` under Adam, with the edits density control needs.

:class:`GaussianOptimizer` knows nothing of *when* or *why* Gaussians are added or removed (that is
a :mod:`~trace3d.training.strategy`); it only keeps the model's tensors, their Adam moments and
any per-Gaussian statistics consistent when they are. Every attribute of the model follows an
edit — the core parameters, the extras (lifting features, tracing statistics) and the strategies'
statistics registered with :meth:`GaussianOptimizer.add_statistic`.
"""

from __future__ import annotations

import math
from typing import Callable

import torch

from ..gaussians import GaussianModel
from ..threads import torch_threads
from .params import TrainParams

ADAM_THREADS = 1  # torch threads of the Adam step (see GaussianOptimizer.__init__)


def learning_rates(params: TrainParams, extent: float) -> dict[str, float]:
    """The 2DGS learning rate of every core parameter group (positions scaled by the extent)."""
    return {
        "means": params.position_lr_init * extent,
        "quats": params.rotation_lr,
        "log_scales": params.scaling_lr,
        "opacity_logits": params.opacity_lr,
        "sh_dc": params.feature_lr,
        "sh_rest": params.feature_lr / params.sh_rest_lr_divisor,
    }


class GaussianOptimizer:
    """Adam over the attributes of a :class:`GaussianModel` (one parameter group per attribute).

    ``model``'s optimised tensors are replaced by ``torch.nn.Parameter`` objects; attributes without
    a learning rate (e.g. extras that only need to follow edits) stay plain tensors. :meth:`append`
    and :meth:`keep` edit parameters, Adam moments (new Gaussians start with zero moments) and the
    registered statistics together.

    Args:
        model: the Gaussians (their tensors are copied).
        lrs: learning rate by attribute name; attributes not named are not optimised.
        params: the training parameters (strategies read them from here).
        extent: the scene extent (strategies' size thresholds).
    """

    def __init__(self, model: GaussianModel, lrs: dict[str, float], params: TrainParams, extent: float):
        self.params = params
        self.extent = float(extent)
        unknown = sorted(set(lrs) - set(model.names))
        if unknown:
            raise ValueError(f"GaussianOptimizer: learning rates for unknown attributes {unknown}.")

        def wrap(name: str, t: torch.Tensor) -> torch.Tensor:
            t = t.detach().clone().contiguous()
            return torch.nn.Parameter(t) if name in lrs else t

        self.model = GaussianModel(**{n: wrap(n, getattr(model, n)) for n in GaussianModel.PARAM_NAMES},
                                   extras={n: wrap(n, t) for n, t in model.extras.items()})
        groups = [{"params": [self.model.get(name)], "lr": lr, "name": name} for name, lr in lrs.items()]
        # torch's fused Adam (one multi-threaded pass per tensor instead of seven element-wise ops):
        # the same update up to rounding, several times faster on the CPU for 80k Gaussians
        fused = params.fused_adam and all(p.dtype in (torch.float32, torch.float64) and
                                          p.device.type in ("cpu", "cuda") for g in groups for p in g["params"])
        self.optimizer = torch.optim.Adam(groups, lr=0.0, eps=1e-15, fused=fused or None)
        self.statistics: dict[str, torch.Tensor] = {}
        self._fills: dict[str, float] = {}
        # torch threads for the default density control (0: the caller's): work that streams every
        # Gaussian's tensors, element by element, so its result does not depend on the thread count
        # (tested); the training loop sets the process's thread budget here. The Adam step runs on
        # ADAM_THREADS whatever the budget: in a fit (48x36 pixels, 10k Gaussians, 40 iterations) torch's
        # fused CPU Adam on 2 threads gave other bits than on 1, which an isolated Adam step on the same
        # shapes does not show; on 1 thread the fit's files cannot depend on --threads (docs/performance.md,
        # 'Rule threads'), and they are those of every fit made so far at 1 or 2 threads on the rooms
        self.bulk_threads = 0
        self._grad_buffers: dict[str, torch.Tensor] = {}  # sparse_step's dense gradients (zero between steps)

    # --- bookkeeping ---------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.model)

    def add_statistic(self, name: str, fill: float = 0.0, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """Register (or reset) a per-Gaussian statistic [N] that follows appends (``fill``) and keeps."""
        value = torch.full((len(self.model),), fill, dtype=dtype, device=self.model.device)
        self.statistics[name] = value
        self._fills[name] = fill
        return value

    def set_lr(self, name: str, lr: float) -> None:
        for group in self.optimizer.param_groups:
            if group["name"] == name:
                group["lr"] = lr

    def set_position_lr(self, lr: float) -> None:
        self.set_lr("means", lr)

    def lr(self, name: str) -> float:
        return next(g["lr"] for g in self.optimizer.param_groups if g["name"] == name)

    def step(self, visible: torch.Tensor | None = None, rows: torch.Tensor | None = None) -> None:
        """One Adam step, then the gradients are cleared.

        Args:
            visible: [N] bool, the Gaussians the view rendered: with ``params.visible_adam`` only
                their parameters and moments are updated (see :meth:`visible_step`); ignored
                otherwise, or when its length is not the model's (density control just edited it).
            rows: instead of ``visible``, the rendered Gaussians' rows (ascending).
        """
        if self.params.visible_adam and rows is None and visible is not None and visible.shape[0] == len(self.model):
            rows = torch.nonzero(visible).squeeze(1)
        if self.params.visible_adam and rows is not None:
            self.visible_step(rows)
        else:
            with torch_threads(ADAM_THREADS):
                self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)

    @torch.no_grad()
    def sparse_step(self, rows: torch.Tensor, grads: dict[str, torch.Tensor], sources: dict[str, torch.Tensor],
                    visible: torch.Tensor | None = None) -> None:
        """:meth:`step` from compact gradients (:mod:`trace3d.training.sparse`): ``grads[name]`` [R, ...]
        is the gradient of the rows ``rows`` of the attribute that was ``sources[name]`` when the view
        was rendered; every other row's gradient is zero. An attribute an edit has replaced since
        (density control, an opacity reset) gets no step, as its fresh parameter gets none in
        :meth:`step` (it has no gradient). ``visible`` [R] bool: which of the rows the view rendered
        (``params.visible_adam`` updates those only).

        The gradients go into persistent dense buffers that are zero outside a step (only the rows
        are written and cleared), so the dense Adam step sees exactly the dense path's gradients.
        """
        from .sparse import clear_rows, scatter_rows

        touched = []
        for group in self.optimizer.param_groups:
            name, param = group["name"], group["params"][0]
            grad = grads.get(name)
            if grad is None or sources.get(name) is not param:
                continue
            buffer = self._grad_buffers.get(name)
            if (buffer is None or buffer.shape != param.shape or buffer.dtype != param.dtype
                    or buffer.device != param.device):
                buffer = torch.zeros_like(param, memory_format=torch.contiguous_format)
                self._grad_buffers[name] = buffer
            param.grad = buffer
            touched.append((buffer, grad))
        scatter_rows([b for b, _ in touched], rows, [g for _, g in touched])
        try:
            self.step(rows=rows if visible is None else rows[visible])
        finally:
            clear_rows([b for b, _ in touched], rows)

    @torch.no_grad()
    def visible_step(self, rows: torch.Tensor) -> None:
        """Adam on the Gaussians ``rows`` only (gsplat's "visible Adam"): the same update as
        ``torch.optim.Adam`` for those rows, with the step count (and so the bias corrections) of
        every step; the other rows' parameters and moments stay as they are."""
        from .kernels.adam import adam_rows

        for group in self.optimizer.param_groups:
            param = group["params"][0]
            if param.grad is None:
                continue
            state = self.optimizer.state[param]
            if not state:  # torch's own initial state, so that dense and visible steps can mix
                state["step"] = torch.tensor(0.0, dtype=torch.float32)
                state["exp_avg"] = torch.zeros_like(param, memory_format=torch.preserve_format)
                state["exp_avg_sq"] = torch.zeros_like(param, memory_format=torch.preserve_format)
            state["step"] += 1
            t = float(state["step"])
            b1, b2 = group["betas"]
            adam_rows(param, param.grad, state["exp_avg"], state["exp_avg_sq"], rows.to(param.device),
                      group["lr"] / (1.0 - b1 ** t), b1, b2, 1.0 / math.sqrt(1.0 - b2 ** t), group["eps"])

    def _group(self, name: str) -> dict | None:
        return next((g for g in self.optimizer.param_groups if g["name"] == name), None)

    def replace(self, name: str, new_value: torch.Tensor,
                moment_fn: Callable[[torch.Tensor], torch.Tensor] | None = None) -> None:
        """Swap attribute ``name`` for ``new_value``; ``moment_fn`` maps each old Adam moment to the
        new one (default: zero moments of the new shape)."""
        group = self._group(name)
        if group is None:
            self.model.set(name, new_value.detach().contiguous())
            return
        old = group["params"][0]
        new = torch.nn.Parameter(new_value.detach().contiguous())
        state = self.optimizer.state.pop(old, None)
        if state:
            fn = moment_fn if moment_fn is not None else (lambda m: torch.zeros_like(new))
            state["exp_avg"] = fn(state["exp_avg"]).contiguous()
            state["exp_avg_sq"] = fn(state["exp_avg_sq"]).contiguous()
            self.optimizer.state[new] = state
        group["params"][0] = new
        self.model.set(name, new)

    def append(self, new: GaussianModel) -> None:
        """Add the Gaussians of ``new`` (zero Adam moments; statistics take their fill value).

        ``new`` must carry the same extras as the model.
        """
        self.edit(None, new)

    def keep(self, mask: torch.Tensor) -> None:
        """Keep only the Gaussians where ``mask`` [N] bool is true (attributes, moments, statistics)."""
        self.edit(mask)

    def edit(self, keep: torch.Tensor | None, new: GaussianModel | None = None) -> None:
        """Keep the Gaussians where ``keep`` [N] bool is true (None: all), then append ``new`` (zero
        Adam moments, statistics at their fill values), in one copy of every tensor.

        ``new`` must carry the same extras as the model.
        """
        if new is not None and set(new.extras) != set(self.model.extras):
            raise ValueError(f"GaussianOptimizer: the new Gaussians' extras {sorted(new.extras)} differ from the "
                             f"model's {sorted(self.model.extras)}.")
        rows = None if keep is None else torch.nonzero(keep.to(self.model.device)).squeeze(1)

        def edited(t: torch.Tensor, fill: torch.Tensor | None) -> torch.Tensor:
            kept = t if rows is None else t.index_select(0, rows)
            return kept if fill is None else torch.cat([kept, fill], dim=0)

        for name in self.model.names:
            old = self.model.get(name)
            extra = None if new is None else new.get(name).detach().to(old.device, old.dtype)
            self.replace(name, edited(old.detach(), extra),
                         lambda moment, extra=extra: edited(moment, None if extra is None else torch.zeros_like(extra)))
        count = 0 if new is None else len(new)
        for name, value in self.statistics.items():
            pad = torch.full((count,), self._fills[name], dtype=value.dtype, device=value.device)
            self.statistics[name] = edited(value, pad if count else None)

    @torch.no_grad()
    def reset_opacity(self, max_opacity: float = 0.01) -> None:
        """Clamp every opacity to at most ``max_opacity`` and zero its Adam moments (3DGS reset)."""
        logits = self.model.opacity_logits.detach()
        limit = math.log(max_opacity / (1.0 - max_opacity))
        self.replace("opacity_logits", torch.minimum(logits, torch.full_like(logits, limit)), torch.zeros_like)
