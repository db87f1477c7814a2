"""Fused CPU kernel of the contrastive loss and its gradient (numba), the fast twin of
:func:`trace3d.lifting.contrastive.contrastive_loss` (torch autograd, which stays the reference and the
path on other devices).

For P sampled pixels sorted by instance (block [s_u, e_u) = u's instance), features f [P, D]:

    den_u = sum_v k_uv,  num_u = sum_{v in block(u)} k_uv,  L = 1/P sum_u (log den_u - log num_u)

with k_uv = k_pos(d2_uv) inside a block and k_neg(d2_uv) across blocks, d2_uv = ||f_u - f_v||^2 (kind 2,
the released loss: num_u leaves v = u out, and an anchor whose num_u is then empty adds nothing, its
1/den_u and 1/num_u taken as 0 below). Pairs of two different instances that the caller marks as
undecided (``related``, the lift's ``undecided: ignore``) weigh ``undecided_weight`` (0: they leave den and
the gradient).
Because k is symmetric in (u, v), the gradient collects both roles of a pair:

    dL/df_u = 2/P sum_v  c_uv (f_u - f_v),
    c_uv = k'(d2_uv) (1/den_u + 1/den_v) - [v in block(u)] k_pos'(d2_uv) (1/num_u + 1/num_v)

Both k and c are symmetric, so only the tiles (I, J), I <= J, of the pair matrix are visited (64 x 64
pixels each, tiles in parallel with ``prange``): a first pass computes each tile's Gram block, the
kernel values and k' (row and column sums per tile), a second pass the coefficients and both their
products with the features (c [f, 1] for the tile's rows and c^T [f, 1] for its columns). Every tile
writes its own partial sums, added in a fixed order afterwards, so the result does not depend on the
thread count. Float32 pair arithmetic with own vectorisable exps (relative error ~4e-6); sample and
feature sizes are padded to the tile and vector widths with pixels of weight 0. Kernels (``kind``):
0 = exp(-a d2) (``gaussian``, a = tau), 1 = exp(exp(-a d2)) (``printed``), 2 = exp(exp(-a d2)) without the
anchor in its own numerator (``official``:
the released code's loss, a_pos = 1/tau_pos, a_neg = 1/tau_neg). The anchor's own pair (d2 = 0) has no
gradient; kind 2 gives it k' = 0 outright.
"""

from __future__ import annotations

import threading

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from ...errors import Trace3DError
from ...render.kernels.tiles import exp_taylor8

# No reassociation: every sum is written so that it vectorises as it stands (16 lane partials added in a
# fixed tree, or vectors along the pixels), so the bits do not depend on how LLVM vectorises a loop. With
# "reassoc" they did: numba optimises a parallel loop's body once on its own and once more inside the
# kernel's module, a process that compiled the kernel runs the first and one that loads it from the
# cache the second, and with reassociation the two summed the rows in other orders (30 of 4,096
# features of a tiny lift differed in the last bits, issue 49; tests/tooling/test_kernel_cache.py).
PAIR_MATH = {"nsz", "contract", "arcp"}


@njit(inline="always", fastmath={"nsz"})
def _exp_neg(s):
    """exp(-s) for s >= 0 in float32, vectorisable, down to exp(-80) (smaller values read as exp(-80)):
    s = (n - y') ln 2 with n the nearest integer of s log2(e), e^y by :func:`exp_taylor8` on |y| <= ln2 / 2,
    and 2^-n straight into the exponent bits (relative error ~4e-6, from rounding s log2(e))."""
    s = min(s, np.float32(80.0))
    t = s * np.float32(1.4426950408889634)
    n = np.int32(t + np.float32(0.5))
    y = (np.float32(n) - t) * np.float32(0.6931471805599453)
    return exp_taylor8(y) * np.int32((127 - n) << 23).view(np.float32)


TILE = 64  # pixels per side of a pair tile (the sample is padded to a multiple of it)
LANES = 16  # the feature dimension is padded to a multiple of this (zeros change no distance)


@njit(inline="always")
def _tile_at(ti, tj, t):
    """Tile ``t`` of the upper tiles: its block indices (I, J) and first pixels (u0, v0)."""
    i = ti[t]
    j = tj[t]
    return i, j, i * TILE, j * TILE


@njit(inline="always")
def _anchor_span(starts, ends, uu, v0):
    """The anchor ``uu``'s own instance within the tile columns starting at ``v0``: [lo, hi) clipped
    to the tile (pixels are sorted by instance, so it is one contiguous span)."""
    return min(max(starts[uu] - v0, 0), TILE), min(max(ends[uu] - v0, 0), TILE)


@njit(inline="always", fastmath=PAIR_MATH)
def _dot16(f, x, o, v):
    """sum_k x[o + k] f[o + k, v] over k < 16 written out, so that a loop over v around it vectorises
    along v with the 16 products in registers (a loop over k with += spills the partial sums)."""
    # a balanced tree (written out: no reassociation is allowed), four chains deep instead of sixteen
    s0 = (x[o + 0] * f[o + 0, v] + x[o + 1] * f[o + 1, v]) + (x[o + 2] * f[o + 2, v] + x[o + 3] * f[o + 3, v])
    s1 = (x[o + 4] * f[o + 4, v] + x[o + 5] * f[o + 5, v]) + (x[o + 6] * f[o + 6, v] + x[o + 7] * f[o + 7, v])
    s2 = (x[o + 8] * f[o + 8, v] + x[o + 9] * f[o + 9, v]) + (x[o + 10] * f[o + 10, v] + x[o + 11] * f[o + 11, v])
    s3 = (x[o + 12] * f[o + 12, v] + x[o + 13] * f[o + 13, v]) + (x[o + 14] * f[o + 14, v] + x[o + 15] * f[o + 15, v])
    return (s0 + s1) + (s2 + s3)


@njit(inline="always", fastmath=PAIR_MATH)
def _exp_unit(e):
    """exp(e) for e in [0, 1] in float32: exp(1/2) exp(e - 1/2), Taylor degree 8 on |x| <= 1/2
    (truncation < 1e-8 relative; the printed kernel's outer exp)."""
    return exp_taylor8(e - np.float32(0.5)) * np.float32(1.6487212707001282)


@njit(inline="always", fastmath=PAIR_MATH)
def _lane_sum(part):
    """The sum of 16 lane partials in a fixed tree."""
    a = (part[0] + part[1]) + (part[2] + part[3])
    b = (part[4] + part[5]) + (part[6] + part[7])
    c = (part[8] + part[9]) + (part[10] + part[11])
    d = (part[12] + part[13]) + (part[14] + part[15])
    return (a + b) + (c + d)


@njit(inline="always", fastmath=PAIR_MATH)
def _kernel_row(grow, nu, nv, wu, wv, a_pos, a_neg, kind, lo, hi, drow, col_den, col_num, part_den, part_num,
                self_col):
    """Kernel values of one anchor row over the tile's columns, scale ``a_pos`` inside the anchor's
    instance (columns [lo, hi)) and ``a_neg`` outside: k' into ``drow``, k into the column sums (and the
    numerator's inside the instance), and the row's sums of k as 16 lane partials (``part_den``, all
    columns; ``part_num``, the instance's), one vector of 16 columns at a time. Column ``self_col`` (the
    anchor itself under kind 2; -1: none) counts in the denominator only, with k' = 0. ``wv`` holds the
    columns' weights: their validity, times the anchor's row of the keep matrix when there is one (an
    undecided pair weighs ``undecided_weight``; gathered before the call, so that this loop vectorises)."""
    for lane in range(LANES):
        part_den[lane] = np.float32(0.0)
        part_num[lane] = np.float32(0.0)
    for b in range(0, TILE, LANES):
        for lane in range(LANES):
            v = b + lane
            inside = lo <= v < hi
            a = a_pos if inside else a_neg
            d2 = max(nu + nv[v] - np.float32(2.0) * grow[v], np.float32(0.0))
            e = _exp_neg(a * d2)
            w = wu * wv[v]
            if kind == 0:
                k = e * w
                dkv = -a * k
            else:
                k = _exp_unit(e) * w
                dkv = -a * e * k
            own = v == self_col
            drow[v] = np.float32(0.0) if own else dkv
            col_den[v] += k
            part_den[lane] += k
            kin = k if inside and not own else np.float32(0.0)
            col_num[v] += kin
            part_num[lane] += kin


@njit(parallel=True, cache=True, fastmath=PAIR_MATH)
def _pair_tiles(ft, norms, starts, ends, valid, a_pos, a_neg, kind, ti, tj, dkt, pden, pnum, keep, slot, related):
    """First pass, over the tiles (I, J), I <= J, of the symmetric pair matrix.

    Per pair: d2 from the tile's Gram block, the kernel value k and its derivative k'(d2) (times
    valid_u valid_v keep[slot_u, slot_v], so padding pixels and undecided pairs weigh nothing); k' is
    kept per tile (``dkt``) for the second pass. The tile's row sums go to ``pden/pnum[J, rows of I]``
    and (I < J) its column sums to ``pden/pnum[I, rows of J]``: every slot has one writer, and the
    totals are summed over J in a fixed order afterwards, so nothing depends on the thread count.
    """
    dim = ft.shape[0]
    a_pos = np.float32(a_pos)
    a_neg = np.float32(a_neg)
    for t in prange(ti.size):
        i, j, u0, v0 = _tile_at(ti, tj, t)
        dk = dkt[t]
        # the tile's Gram block, one row at a time: 16 feature lanes per pass written out (_dot16)
        gram = np.empty((TILE, TILE), np.float32)
        fv = ft[:, v0:v0 + TILE].copy()
        fut = ft[:, u0:u0 + TILE].T.copy()
        for u in range(TILE):
            x = fut[u]
            grow = gram[u]
            for v in range(TILE):
                grow[v] = _dot16(fv, x, 0, v)
            for o in range(LANES, dim, LANES):
                for v in range(TILE):
                    grow[v] += _dot16(fv, x, o, v)
        nv = norms[v0:v0 + TILE]
        wv = valid[v0:v0 + TILE]
        sv = slot[v0:v0 + TILE]
        wrow = np.empty(TILE, np.float32)  # the columns' weights for the current anchor
        if not related:
            for v in range(TILE):
                wrow[v] = wv[v]
        col_den = np.zeros(TILE, np.float32)
        col_num = np.zeros(TILE, np.float32)
        part_den = np.empty(LANES, np.float32)
        part_num = np.empty(LANES, np.float32)
        for u in range(TILE):
            nu = norms[u0 + u]
            wu = valid[u0 + u]
            lo, hi = _anchor_span(starts, ends, u0 + u, v0)
            self_col = u if kind == 2 and i == j else -1  # kind 2: the anchor itself, denominator only
            if related:  # validity times the keep matrix's row of the anchor (1 or undecided_weight)
                krow = keep[slot[u0 + u]]
                for v in range(TILE):
                    wrow[v] = wv[v] * krow[sv[v]]
            _kernel_row(gram[u], nu, nv, wu, wrow, a_pos, a_neg, kind, lo, hi, dk[u], col_den, col_num, part_den,
                        part_num, self_col)
            pden[j, u0 + u] = _lane_sum(part_den)
            pnum[j, u0 + u] = _lane_sum(part_num)
        if i != j:
            for v in range(TILE):
                pden[i, v0 + v] = col_den[v]
                pnum[i, v0 + v] = col_num[v]


@njit(parallel=True, cache=True, fastmath=PAIR_MATH)
def _grad_tiles(ft, starts, ends, inv_den, inv_num, ti, tj, dkt, gpart):
    """Second pass: per tile the gradient coefficients (module docstring)

        c_uv = k'(d2_uv) (1/den_u + 1/den_v) - same_uv k'(d2_uv) (1/num_u + 1/num_v)

    and their products with the features: rows of I get sum_v c_uv [f_v, 1] into ``gpart[J, :, rows]``,
    rows of J (I < J) get sum_u c_uv [f_u, 1] into ``gpart[I, :, rows]`` (one writer per slot)."""
    dim = ft.shape[0]
    for t in prange(ti.size):
        i, j, u0, v0 = _tile_at(ti, tj, t)
        dk = dkt[t]
        idv = inv_den[v0:v0 + TILE]
        inv = inv_num[v0:v0 + TILE]
        coef = np.empty((TILE, TILE), np.float32)
        for u in range(TILE):
            du = inv_den[u0 + u]
            nu = inv_num[u0 + u]
            drow = dk[u]
            crow = coef[u]
            lo, hi = _anchor_span(starts, ends, u0 + u, v0)
            for v in range(lo):
                crow[v] = drow[v] * (du + idv[v])
            for v in range(lo, hi):
                crow[v] = drow[v] * (du + idv[v] - (nu + inv[v]))
            for v in range(hi, TILE):
                crow[v] = drow[v] * (du + idv[v])
        fv = ft[:, v0:v0 + TILE].copy()
        fu = ft[:, u0:u0 + TILE].copy()
        out = gpart[j]
        # rows of I: sum_v c_uv [f_v, 1], accumulated as vectors along u (coef transposed)
        coef_t = coef.T.copy()
        acc = np.zeros((dim + 1, TILE), np.float32)
        for v in range(0, TILE, 8):  # eight columns per sweep: one load and store of a row per 8 products
            c0 = coef_t[v]
            c1 = coef_t[v + 1]
            c2 = coef_t[v + 2]
            c3 = coef_t[v + 3]
            c4 = coef_t[v + 4]
            c5 = coef_t[v + 5]
            c6 = coef_t[v + 6]
            c7 = coef_t[v + 7]
            for d in range(dim):
                x = fv[d]
                x0 = x[v]
                x1 = x[v + 1]
                x2 = x[v + 2]
                x3 = x[v + 3]
                x4 = x[v + 4]
                x5 = x[v + 5]
                x6 = x[v + 6]
                x7 = x[v + 7]
                arow = acc[d]
                for u in range(TILE):
                    arow[u] += (((x0 * c0[u] + x1 * c1[u]) + (x2 * c2[u] + x3 * c3[u]))
                                + ((x4 * c4[u] + x5 * c5[u]) + (x6 * c6[u] + x7 * c7[u])))
            arow = acc[dim]
            for u in range(TILE):
                arow[u] += ((c0[u] + c1[u]) + (c2[u] + c3[u])) + ((c4[u] + c5[u]) + (c6[u] + c7[u]))
        for d in range(dim + 1):
            arow = acc[d]
            for u in range(TILE):
                out[d, u0 + u] = arow[u]
        if i != j:  # rows of J: sum_u c_uv [f_u, 1], accumulated transposed (vectors along v)
            acc_t = np.zeros((dim + 1, TILE), np.float32)
            for u in range(0, TILE, 4):
                c0 = coef[u]
                c1 = coef[u + 1]
                c2 = coef[u + 2]
                c3 = coef[u + 3]
                for d in range(dim):
                    x0 = fu[d, u]
                    x1 = fu[d, u + 1]
                    x2 = fu[d, u + 2]
                    x3 = fu[d, u + 3]
                    arow = acc_t[d]
                    for v in range(TILE):
                        arow[v] += (x0 * c0[v] + x1 * c1[v]) + (x2 * c2[v] + x3 * c3[v])
                arow = acc_t[dim]
                for v in range(TILE):
                    arow[v] += (c0[v] + c1[v]) + (c2[v] + c3[v])
            out = gpart[i]
            for d in range(dim + 1):
                arow = acc_t[d]
                for v in range(TILE):
                    out[d, v0 + v] = arow[v]


@njit(cache=True)
def _instance_order(labels):
    """The order of a stable argsort of ``labels``: a counting sort when the labels span a small range
    (instance ids of one view), a merge sort otherwise."""
    p = labels.size
    if p == 0:
        return np.empty(0, np.int64)
    lo = labels.min()
    span = labels.max() - lo + 1
    if span > 4 * p + 1024:
        return np.argsort(labels, kind="mergesort")
    first = np.zeros(span + 1, np.int64)
    for u in range(p):
        first[labels[u] - lo + 1] += 1
    for b in range(span):
        first[b + 1] += first[b]
    order = np.empty(p, np.int64)
    for u in range(p):
        b = labels[u] - lo
        order[first[b]] = u
        first[b] += 1
    return order


BLOCK = 16  # pixels per block when moving between pixel-major and feature-major layouts


@njit(cache=True)
def _prepare(features, labels, pp, dp):
    """Sort the P pixels by instance (stable) and lay them out for the tile kernels: f^T padded to
    [dp, pp] with zeros, squared norms, the bounds [start, end) of each sorted pixel's instance
    (padding pixels: an instance of their own each) and validity (1 for the P pixels, 0 for padding)."""
    p, dim = features.shape
    order = _instance_order(labels)
    ft = np.zeros((dp, pp), np.float32)
    norms = np.zeros(pp, np.float32)
    starts = np.empty(pp, np.int64)
    ends = np.empty(pp, np.int64)
    valid = np.zeros(pp, np.float32)
    rows = np.empty((BLOCK, dim), np.float32)
    for u0 in range(0, p, BLOCK):  # gather BLOCK sorted rows, then write them as columns of f^T
        nb = min(BLOCK, p - u0)
        for k in range(nb):
            u = u0 + k
            src = order[u]
            starts[u] = starts[u - 1] if u > 0 and labels[src] == labels[order[u - 1]] else u
            valid[u] = 1.0
            acc = np.float32(0.0)
            for d in range(dim):
                x = np.float32(features[src, d])
                rows[k, d] = x
                acc += x * x
            norms[u] = acc
        for d in range(dim):
            for k in range(nb):
                ft[d, u0 + k] = rows[k, d]
    for u in range(p - 1, -1, -1):
        ends[u] = ends[u + 1] if u + 1 < p and starts[u + 1] == starts[u] else u + 1
    for u in range(p, pp):
        starts[u] = u
        ends[u] = u + 1
    return order, ft, norms, starts, ends, valid


@njit(cache=True)
def _sums(pden, pnum, p):
    """Per anchor den and num (the tiles' partial sums, in float64, in tile order) and the loss."""
    nb, pp = pden.shape
    den = np.zeros(p, np.float64)
    num = np.zeros(p, np.float64)
    for b in range(nb):
        for u in range(p):
            den[u] += pden[b, u]
            num[u] += pnum[b, u]
    inv_den = np.zeros(pp, np.float32)
    inv_num = np.zeros(pp, np.float32)
    loss = 0.0
    for u in range(p):
        if num[u] > 0.0:  # 0 only for kind 2's anchors alone in their instance: no term, no gradient
            loss += np.log(den[u] / num[u])
            inv_den[u] = 1.0 / den[u]
            inv_num[u] = 1.0 / num[u]
    return loss / p, inv_den, inv_num


@njit(parallel=True, cache=True, fastmath=PAIR_MATH)
def _grad_sum(ft, gpart, order, dim_out):
    """dL/df_u = 2/P (total_u f_u - sum_v c_uv f_v), the per-tile parts added in tile order (rows of
    the sums in parallel, each element's order fixed), written back in the pixels' original order."""
    nb = gpart.shape[0]
    dim = ft.shape[0]
    pp = gpart.shape[2]
    p = order.size
    acc = np.zeros((dim + 1, pp), np.float32)
    for d in prange(dim + 1):
        row = acc[d]
        for b in range(nb):
            part = gpart[b, d]
            for u in range(pp):
                row[u] += part[u]
    scale = np.float32(2.0 / p)
    total = acc[dim]
    for d in prange(dim_out):
        row = acc[d]
        frow = ft[d]
        for u in range(p):
            row[u] = scale * (total[u] * frow[u] - row[u])
    grad = np.empty((p, dim_out), np.float32)
    for u0 in range(0, p, BLOCK):  # BLOCK columns at a time into their rows (original order)
        for k in range(min(BLOCK, p - u0)):
            dst = order[u0 + k]
            for d in range(dim_out):
                grad[dst, d] = acc[d, u0 + k]
    return grad


_WORK = threading.local()


def _workspace(nb: int, dp: int):
    """Tile indices and scratch arrays for ``nb`` tiles per side and ``dp`` feature lanes, kept between
    calls (per thread): fresh multi-megabyte arrays would cost a page fault per 4 KiB on every call."""
    key = (nb, dp)
    if getattr(_WORK, "key", None) != key:
        ti, tj = np.triu_indices(nb)
        pp = nb * TILE
        _WORK.arrays = (ti.astype(np.int64), tj.astype(np.int64), np.empty((ti.size, TILE, TILE), np.float32),
                        np.empty((nb, pp), np.float32), np.empty((nb, pp), np.float32),
                        np.empty((nb, dp + 1, pp), np.float32))
        _WORK.key = key
    return _WORK.arrays


_NO_RELATION = np.ones((1, 1), np.float32)


def _keep_slots(labels: np.ndarray, order: np.ndarray, related, pp: int,
                undecided_weight: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The keep matrix [S, S] float32 (1: the pair counts, ``undecided_weight``: undecided) over the S
    distinct labels of the sample, and each sorted pixel's slot in it (padding: slot 0, its validity already 0). Without
    ``related``, one slot with keep 1 (unused: the kernel then takes the validity alone)."""
    slot = np.zeros(pp, np.int64)
    if related is None:
        return _NO_RELATION, slot
    related = np.asarray(related, bool)
    values, inverse = np.unique(labels, return_inverse=True)
    if values.size and (values.min() < 0 or values.max() >= related.shape[0]):
        raise Trace3DError(f"contrastive loss: a label ({int(values.max())}) lies outside the relation matrix "
                           f"of {related.shape[0]} labels.")
    keep = np.where(related[np.ix_(values, values)], np.float32(undecided_weight), np.float32(1.0)).astype(np.float32)
    np.fill_diagonal(keep, 1.0)  # one instance's pairs always count (lo/hi decide their kernel)
    slot[:labels.size] = inverse.reshape(-1)[order]
    return keep, slot


def loss_and_grad(features: np.ndarray, labels: np.ndarray, consts: tuple, want_grad: bool = True, related=None,
                  undecided_weight: float = 0.0):
    """The contrastive loss (float) and, if ``want_grad``, its gradient [P, D] float32 w.r.t. ``features``
    ([P, D] float, any order; ``labels`` [P] int) by the fused kernel, without torch or autograd:
    the lifting's fast step calls it directly, :func:`fused_contrastive_loss` wraps it for autograd.
    Pads P to a multiple of :data:`TILE` and D to one of :data:`LANES` (module docstring). ``related``:
    optional [L, L] bool by label value, the pairs of two different labels that weigh ``undecided_weight``."""
    p, dim = features.shape
    pp = -(-p // TILE) * TILE
    dp = -(-dim // LANES) * LANES
    labels = np.ascontiguousarray(labels, np.int64)
    order, ft, norms, starts, ends, valid = _prepare(features, labels, pp, dp)
    keep, slot = _keep_slots(labels, order, related, pp, undecided_weight)
    ti, tj, dkt, pden, pnum, gpart = _workspace(pp // TILE, dp)
    a_pos, a_neg, kind = consts
    _pair_tiles(ft, norms, starts, ends, valid, a_pos, a_neg, kind, ti, tj, dkt, pden, pnum, keep, slot,
                related is not None)
    loss, inv_den, inv_num = _sums(pden, pnum, p)
    if not want_grad:
        return float(loss), None
    _grad_tiles(ft, starts, ends, inv_den, inv_num, ti, tj, dkt, gpart)
    return float(loss), _grad_sum(ft, gpart, order, dim)


def kernel_constants(kernel: str, temperature: float, temperature_pos: float, temperature_neg: float):
    """(a_pos, a_neg, kind) of the fused kernel for a kernel name and its temperatures."""
    if kernel == "official":
        return 1.0 / temperature_pos, 1.0 / temperature_neg, 2
    if kernel == "gaussian":
        return float(temperature), float(temperature), 0
    if kernel == "printed":
        return float(temperature), float(temperature), 1
    raise Trace3DError(f"contrastive loss: unknown kernel {kernel!r}.")


class _FusedLoss(torch.autograd.Function):
    @staticmethod
    def forward(ctx, features: Tensor, labels: Tensor, consts: tuple, related, undecided_weight) -> Tensor:
        want = features.requires_grad
        loss, grad = loss_and_grad(features.detach().float().numpy(), labels.numpy(), consts, want, related,
                                   undecided_weight)
        if want:
            ctx.save_for_backward(torch.from_numpy(grad).to(features.dtype))
        return torch.tensor(loss, dtype=features.dtype)

    @staticmethod
    def backward(ctx, v_loss: Tensor):
        (g,) = ctx.saved_tensors
        return g * v_loss, None, None, None, None


def fused_contrastive_loss(features: Tensor, labels: Tensor, kernel: str = "official", temperature: float = 0.01,
                           temperature_pos: float = 100.0, temperature_neg: float = 1.0, related=None,
                           undecided_weight: float = 0.0) -> Tensor:
    """The contrastive loss of :func:`trace3d.lifting.contrastive.contrastive_loss` by the fused CPU
    kernel: same value and gradient w.r.t. ``features`` ([P, D], CPU), the gradient computed in the same
    call (module docstring)."""
    if features.device.type != "cpu":
        raise Trace3DError("fused contrastive loss: CPU tensors only (other devices use the torch form).")
    if features.shape[0] == 0:
        return features.sum() * 0.0
    consts = kernel_constants(kernel, temperature, temperature_pos, temperature_neg)
    related = None if related is None else np.asarray(related, bool)
    return _FusedLoss.apply(features, labels.to(torch.int64), consts, related, float(undecided_weight))
