"""Fused CPU kernel of the contrastive loss and its gradient (numba), the fast twin of
:func:`trace3d.lifting.contrastive.contrastive_loss` (torch autograd, which stays the reference and the
path on other devices).

For P sampled pixels sorted by instance (block [s_u, e_u) = u's instance), features f [P, D]:

    den_u = sum_v k_uv,  num_u = sum_{v in block(u)} k_uv,  L = 1/P sum_u (log den_u - log num_u)

with k_uv = k_pos(d2_uv) inside a block and k_neg(d2_uv) across blocks, d2_uv = ||f_u - f_v||^2. Because
k is symmetric in (u, v), the gradient collects both roles of a pair:

    dL/df_u = 2/P sum_v  c_uv (f_u - f_v),
    c_uv = k'(d2_uv) (1/den_u + 1/den_v) - [v in block(u)] k_pos'(d2_uv) (1/num_u + 1/num_v)

The Gram matrix f f^T comes from one BLAS product; then two passes over the P x P pairs, rows in parallel
(``prange``): kernel values and k' (sums per row in float64), then the coefficients and the gradient
rows. Every row writes only its own outputs, so the result does not depend on the thread count.
Float32 pair arithmetic with an own vectorisable exp (relative error ~1e-6). Kernels (``kind``):
0 = exp(-a d2) (``official`` with a_pos = 1/tau_pos, a_neg = 1/tau_neg; ``gaussian`` with a = tau), 1 =
exp(exp(-a d2)) (``printed``).
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from ..errors import Trace3DError
from ..render.kernels import exp_neg

# Reassociation lets the per-row sums vectorise (a fixed order per compiled loop: results stay
# deterministic and independent of the thread count); the exp keeps value-preserving flags only.
PAIR_MATH = {"nsz", "reassoc", "contract", "arcp"}


@njit(inline="always", fastmath={"nsz"})
def _exp_neg(s):
    """exp(-s) for s >= 0 in float32, vectorisable, down to exp(-80): the rasterizer's
    :func:`trace3d.render.kernels.exp_neg` (exact to ~1e-6, but clamped at exp(-20), where far negative
    pairs must weigh ~0) taken at s / 4 and raised to the 4th power (relative error ~4e-6)."""
    e = exp_neg(s * np.float32(0.25))
    e2 = e * e
    return e2 * e2


@njit(inline="always", fastmath=PAIR_MATH)
def _k(d2, a, kind):
    """(kernel value, derivative w.r.t. d2) in float32."""
    e = _exp_neg(a * d2)
    if kind == 0:
        return e, -a * e
    k = np.float32(1.0) / _exp_neg(e)  # exp(e), e in (0, 1]
    return k, -a * e * k


@njit(inline="always", fastmath=PAIR_MATH)
def _row(gram, norms, u, d2):
    nu = norms[u]
    for v in range(d2.shape[0]):
        d2[v] = max(nu + norms[v] - np.float32(2.0) * gram[u, v], np.float32(0.0))


@njit(parallel=True, cache=True, fastmath=PAIR_MATH)
def _pairs(gram, norms, ft, starts, ends, a_pos, a_neg, kind, want_grad):
    """The loss terms and gradient over the P x P pairs of pixels sorted by instance.

    Args:
        gram: [P, P] float32 f f^T; norms: [P] float32 ||f||^2 (its diagonal); ft: [D, P] float32 f^T.
        starts, ends: [P] block bounds of each pixel's instance.
    Returns:
        terms [P] float64 (log den - log num per anchor) and, if ``want_grad``, grad [P, D] float32 =
        dL/df (module docstring); else an empty grad.
    """
    p = norms.shape[0]
    dim = ft.shape[0]
    a_pos = np.float32(a_pos)
    a_neg = np.float32(a_neg)
    den = np.empty(p)
    num = np.empty(p)
    dks = np.empty((p if want_grad else 0, p), np.float32)  # k'(d2) per pair, for the second pass
    for u in prange(p):
        d2 = np.empty(p, np.float32)
        _row(gram, norms, u, d2)
        s, e = starts[u], ends[u]
        s_num = 0.0
        s_den = 0.0
        if want_grad:
            for v in range(s):
                k, dk = _k(d2[v], a_neg, kind)
                s_den += k
                dks[u, v] = dk
            for v in range(s, e):  # the anchor's instance (branch-free ranges, so the loops vectorise)
                k, dk = _k(d2[v], a_pos, kind)
                s_num += k
                dks[u, v] = dk
            for v in range(e, p):
                k, dk = _k(d2[v], a_neg, kind)
                s_den += k
                dks[u, v] = dk
        else:
            for v in range(s):
                s_den += _k(d2[v], a_neg, kind)[0]
            for v in range(s, e):
                s_num += _k(d2[v], a_pos, kind)[0]
            for v in range(e, p):
                s_den += _k(d2[v], a_neg, kind)[0]
        den[u] = s_den + s_num
        num[u] = s_num
    terms = np.log(den) - np.log(num)
    grad = np.zeros((p if want_grad else 0, dim), np.float32)
    if want_grad:
        inv_den = (1.0 / den).astype(np.float32)
        inv_num = (1.0 / num).astype(np.float32)
        scale = np.float32(2.0 / p)
        for u in prange(p):
            coef = dks[u]
            s, e = starts[u], ends[u]
            iu = inv_den[u]
            nu = inv_num[u]
            for v in range(s):
                coef[v] *= iu + inv_den[v]
            for v in range(s, e):
                coef[v] *= iu + inv_den[v] - nu - inv_num[v]
            for v in range(e, p):
                coef[v] *= iu + inv_den[v]
            total = np.float32(0.0)
            for v in range(p):
                total += coef[v]
            for c in range(dim):
                acc = np.float32(0.0)
                row = ft[c]
                for v in range(p):
                    acc += coef[v] * row[v]
                grad[u, c] = scale * (total * row[u] - acc)
    return terms, grad


def kernel_constants(kernel: str, temperature: float, temperature_pos: float, temperature_neg: float):
    """(a_pos, a_neg, kind) of the fused kernel for a kernel name and its temperatures."""
    if kernel == "official":
        return 1.0 / temperature_pos, 1.0 / temperature_neg, 0
    if kernel == "gaussian":
        return float(temperature), float(temperature), 0
    if kernel == "printed":
        return float(temperature), float(temperature), 1
    raise Trace3DError(f"contrastive loss: unknown kernel {kernel!r}.")


class _FusedLoss(torch.autograd.Function):
    @staticmethod
    def forward(ctx, features: Tensor, labels: Tensor, consts: tuple) -> Tensor:
        lab, order = torch.sort(labels, stable=True)
        lab_np = lab.numpy()
        # block bounds of each sorted pixel's instance
        change = np.flatnonzero(np.diff(lab_np)) + 1
        bounds = np.concatenate([[0], change, [lab_np.size]]).astype(np.int64)
        block = np.repeat(np.arange(bounds.size - 1), np.diff(bounds))
        starts, ends = bounds[block], bounds[block + 1]
        f = features.detach()[order].float()
        gram = f @ f.t()
        a_pos, a_neg, kind = consts
        want = features.requires_grad
        terms, grad = _pairs(gram.numpy(), torch.diagonal(gram).contiguous().numpy(), f.t().contiguous().numpy(),
                             starts, ends, a_pos, a_neg, kind, want)
        if want:
            out = torch.empty_like(features)
            out[order] = torch.from_numpy(grad).to(features.dtype)
            ctx.save_for_backward(out)
        return torch.tensor(float(terms.mean()), dtype=features.dtype)

    @staticmethod
    def backward(ctx, v_loss: Tensor):
        (g,) = ctx.saved_tensors
        return g * v_loss, None, None


def fused_contrastive_loss(features: Tensor, labels: Tensor, kernel: str = "official", temperature: float = 0.01,
                           temperature_pos: float = 100.0, temperature_neg: float = 1.0) -> Tensor:
    """The contrastive loss of :func:`trace3d.lifting.contrastive.contrastive_loss` by the fused CPU
    kernel: same value and gradient w.r.t. ``features`` ([P, D], CPU), the gradient computed in the same
    call (module docstring)."""
    if features.device.type != "cpu":
        raise Trace3DError("fused contrastive loss: CPU tensors only (other devices use the torch form).")
    if features.shape[0] == 0:
        return features.sum() * 0.0
    consts = kernel_constants(kernel, temperature, temperature_pos, temperature_neg)
    return _FusedLoss.apply(features, labels.to(torch.int64), consts)
