"""Compact gradients: a training view differentiates only the Gaussians it sees.

A 160x120 view of a default room renders about 15k of its 80k Gaussians, yet the dense path runs
every backward stage over all of them: the renderer's gradients are scattered into [N, ...] zeros,
then the projection's and the SH colours' backward passes and the activations' backward read and
write every row, most of them zeros. With compact gradients (``TrainParams.sparse_grad``) the
iteration instead

1. finds the Gaussians the view sees without gradient (``visible_rows``: one numba pass over all N
   that gives the renderer's ``visible`` bit for bit without storing the projection);
2. gathers the seen rows of the raw parameters into small leaf tensors (:class:`CompactView`) and
   renders those, so autograd works on R rows;
3. hands the compact gradients to :meth:`GaussianOptimizer.sparse_step`, which writes them into
   persistent dense gradient buffers (the other rows stay zero), takes the same dense Adam step and
   clears the rows again.

The update is the dense path's, bit for bit: every per-row computation is the same kernel on the
same inputs; the activations are computed once over all N (their values gathered, their backward the
same elementwise formula), so no value depends on where a row sits in a vector loop; and a row the
view did not see gets exactly the zero gradient the dense path gives it. Tests compare the two paths
(parameters, moments and density statistics after a fit with densification).
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

from ..gaussians import GaussianModel
from ..render import Splats
from ..render.kernels.binning import copy_rows
from ..render.projection import visible_mask
from ..scene import Camera


# ----------------------------------------------------------------------------------------------
# Row copies (torch's index_select / index_copy_ / index_fill_ run on one thread in the fit and
# took 4.4 ms per iteration at 160x120 for these; each is a plain copy, so the result is the same)
# ----------------------------------------------------------------------------------------------


@njit(parallel=True, cache=True)
def _clear(dsts, rows):
    """dsts[k][rows[j]] = 0 for every array k."""
    for j in prange(rows.shape[0]):
        i = rows[j]
        for k in range(len(dsts)):
            dst = dsts[k]
            for c in range(dst.shape[1]):
                dst[i, c] = 0


def _rows_2d(t: torch.Tensor) -> np.ndarray | None:
    """A contiguous float32 CPU tensor as a writable [N, D] numpy view (None where the kernels do not
    apply)."""
    if (t.device.type != "cpu" or not t.is_contiguous() or t.dtype != torch.float32 or t.dim() == 0
            or t.numel() == 0):  # empty: torch's index operations (a view that sees no Gaussian)
        return None
    return t.detach().reshape(t.shape[0], -1).numpy()


def gather_rows(tensors: list[torch.Tensor], rows: torch.Tensor) -> list[torch.Tensor]:
    """``[t.index_select(0, rows) for t in tensors]`` (detached); one parallel copy for the contiguous
    float32 CPU tensors."""
    if rows.numel() == 0:
        return [t.detach().index_select(0, rows) for t in tensors]
    outs = [None] * len(tensors)
    fast = []
    for k, t in enumerate(tensors):
        if _rows_2d(t) is None:
            outs[k] = t.detach().index_select(0, rows)
        else:
            outs[k] = torch.empty((rows.shape[0],) + tuple(t.shape[1:]), dtype=t.dtype)
            fast.append(k)
    if fast:
        copy_rows(tuple(outs[k].reshape(rows.shape[0], -1).numpy() for k in fast),
                   tuple(_rows_2d(tensors[k]) for k in fast), rows.numpy(), False)
    return outs


def scatter_rows(dsts: list[torch.Tensor], rows: torch.Tensor, srcs: list[torch.Tensor]) -> None:
    """``dst.index_copy_(0, rows, src)`` for every pair, in place; one parallel copy for the
    contiguous float32 CPU tensors."""
    if rows.numel() == 0:
        return
    fast = []
    for d, s in zip(dsts, srcs):
        s = s.contiguous()
        if _rows_2d(d) is None or _rows_2d(s) is None:
            d.index_copy_(0, rows, s.to(d.dtype))
        else:
            fast.append((_rows_2d(d), _rows_2d(s)))
    if fast:
        copy_rows(tuple(d for d, _ in fast), tuple(s for _, s in fast), rows.numpy(), True)


def clear_rows(dsts: list[torch.Tensor], rows: torch.Tensor) -> None:
    """``dst.index_fill_(0, rows, 0)`` for every tensor, in place; one parallel pass for the contiguous
    float32 CPU tensors."""
    if rows.numel() == 0:
        return
    fast = []
    for d in dsts:
        if _rows_2d(d) is None:
            d.index_fill_(0, rows, 0)
        else:
            fast.append(_rows_2d(d))
    if fast:
        _clear(tuple(fast), rows.numpy())


class _Gathered(torch.autograd.Function):
    """``value`` (the activation of ``raw``, computed over all N and gathered) with the activation's
    backward: ``exp`` (d = grad * value) or ``sigmoid`` (torch's sigmoid_backward)."""

    @staticmethod
    def forward(ctx, raw, value, kind):
        ctx.save_for_backward(value)
        ctx.kind = kind
        return value.clone()

    @staticmethod
    def backward(ctx, grad):
        (value,) = ctx.saved_tensors
        if ctx.kind == "exp":
            return grad * value, None, None
        return torch.ops.aten.sigmoid_backward(grad, value), None, None


def sparse_applies(model: GaussianModel) -> bool:
    """Whether compact gradients apply: the numba renderer (the default back end) and a CPU model."""
    from ..render import core

    return core._backend(None) == "numba" and model.device.type == "cpu"


def visible_rows(model: GaussianModel, camera: Camera, near: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The rows of the Gaussians ``camera`` sees ([R] int64, ascending: in front of ``near`` with a
    footprint inside the image, the renderer's ``visible``), and the activated scales [N, 2] and
    opacities [N] (no gradient)."""
    with torch.no_grad():
        scales = torch.exp(model.log_scales)
        opacities = torch.sigmoid(model.opacity_logits)
        visible = visible_mask(Splats(model.means.detach(), model.quats.detach(), scales, opacities), camera, near)
        return torch.nonzero(visible).squeeze(1), scales, opacities


class CompactView:
    """The Gaussians ``rows`` of ``model`` as leaf tensors of their own (the attributes named in
    ``trainable`` require gradients), with the model's ``splats`` and ``colors`` for them.

    Args:
        model: the Gaussians (only the core parameters are gathered).
        rows: [R] int64 ascending.
        scales, opacities: the activations of all N (from :func:`visible_rows`).
        trainable: the attributes to differentiate.
    """

    def __init__(self, model: GaussianModel, rows: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                 trainable: set[str]):
        self.rows = rows
        self.sources = {name: model.get(name) for name in GaussianModel.PARAM_NAMES}
        names = list(self.sources)
        gathered = gather_rows([self.sources[n] for n in names] + [scales, opacities], rows)
        self.leaves = {name: leaf.requires_grad_(True) if name in trainable else leaf
                       for name, leaf in zip(names, gathered)}
        self.model = GaussianModel(**self.leaves)
        self._scales, self._opacities = gathered[-2], gathered[-1]

    def splats(self) -> Splats:
        m = self.leaves
        scales = (_Gathered.apply(m["log_scales"], self._scales, "exp") if m["log_scales"].requires_grad
                  else self._scales)
        opac = (_Gathered.apply(m["opacity_logits"], self._opacities, "sigmoid") if m["opacity_logits"].requires_grad
                else self._opacities)
        return Splats(means=m["means"], quats=m["quats"], scales=scales, opacities=opac)

    @property
    def means(self) -> torch.Tensor:
        return self.leaves["means"]

    @property
    def device(self) -> torch.device:
        return self.leaves["means"].device

    def colors(self, center: torch.Tensor, degree: int, rows: torch.Tensor | None = None) -> torch.Tensor:
        return self.model.colors(center, degree, rows)

    def grads(self) -> dict[str, torch.Tensor]:
        """The compact gradient [R, ...] of every trainable attribute that received one."""
        return {name: leaf.grad for name, leaf in self.leaves.items() if leaf.requires_grad and leaf.grad is not None}
