"""The trace's triplets as a coalesced sparse matrix (:func:`coalesce_triplets`) and its per-splat
argmax reduction (:func:`reduce_into_rows`).  (Part of the former ``render/kernels.py``, moved
unchanged.)"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

# Rows of one splat at most this long are sorted by insertion (a splat meets a few labels of a few
# tiles); longer ones (one label per pixel: every pixel a splat covers) by a merge sort.
INSERTION_SORT_MAX = 32


@njit(parallel=True, cache=True)
def coalesce_triplets(rows, cols, weights, n):
    """The triplets of :func:`trace_kernel` as a coalesced sparse [n, T] matrix: sorted by row, then
    column, a (row, column) that repeats across tiles summed in the order the triplets come.

    The order of that sum is fixed by the tiles, so the result does not depend on the number of
    threads (torch's ``coalesce`` sorts with an unstable sort whose order of equal keys changes with
    the thread count: the weights' last bits did). Returns rows [E'] int64, cols [E'] int64,
    weights [E'] float32 and the row pointers [n + 1] int64.
    """
    size = rows.shape[0]
    start = np.zeros(n + 1, np.int64)
    for e in range(size):
        start[rows[e] + 1] += 1
    for i in range(n):
        start[i + 1] += start[i]
    fill = start[:n].copy()
    col_of = np.empty(size, np.int64)
    w_of = np.empty(size, np.float32)
    for e in range(size):  # by row, each row's entries in the order they came (a stable counting sort)
        r = rows[e]
        k = fill[r]
        col_of[k] = cols[e]
        w_of[k] = weights[e]
        fill[r] = k + 1
    distinct = np.zeros(n + 1, np.int64)
    for r in prange(n):
        a = start[r]
        b = start[r + 1]
        if b - a > INSERTION_SORT_MAX:
            order = np.argsort(col_of[a:b], kind="mergesort")  # stable
            cs = col_of[a:b][order]
            ws = w_of[a:b][order]
            col_of[a:b] = cs
            w_of[a:b] = ws
        else:
            for i in range(a + 1, b):  # stable insertion sort by column
                c = col_of[i]
                v = w_of[i]
                k = i - 1
                while k >= a and col_of[k] > c:
                    col_of[k + 1] = col_of[k]
                    w_of[k + 1] = w_of[k]
                    k -= 1
                col_of[k + 1] = c
                w_of[k + 1] = v
        m = a
        for i in range(a + 1, b):  # equal columns summed in place, front of the row's segment
            if col_of[i] == col_of[m]:
                w_of[m] = w_of[m] + w_of[i]
            else:
                m += 1
                col_of[m] = col_of[i]
                w_of[m] = w_of[i]
        distinct[r + 1] = m - a + 1 if b > a else 0
    for i in range(n):
        distinct[i + 1] += distinct[i]
    out_rows = np.empty(distinct[n], np.int64)
    out_cols = np.empty(distinct[n], np.int64)
    out_w = np.empty(distinct[n], np.float32)
    for r in prange(n):
        a = start[r]
        o = distinct[r]
        for i in range(distinct[r + 1] - o):
            out_rows[o + i] = r
            out_cols[o + i] = col_of[a + i]
            out_w[o + i] = w_of[a + i]
    return out_rows, out_cols, out_w, distinct


@njit(inline="always")
def _reduce_row(indptr, cols, weights, r):
    tot = np.float32(0.0)
    best = np.float32(0.0)
    best_col = -1
    for i in range(indptr[r], indptr[r + 1]):
        v = weights[i]
        tot = tot + v
        if v > best:
            best = v
            best_col = cols[i]
    if tot > np.float32(0.0) and best > np.float32(0.0):
        return best_col, best / max(tot, np.float32(1e-30)), tot
    return -1, np.float32(0.0), tot


@njit(parallel=True, cache=True)
def reduce_into_rows(indptr, cols, weights, rows, label, prob, total):
    """:func:`~trace3d.render.trace_argmax` of a coalesced sparse trace over the splats ``rows`` [R]
    (ascending) of N, given as CSR over R (:func:`coalesce_triplets`), written into label [N] int32
    (the smallest column attaining the row's maximum; -1 where the splat has no weight or is not in
    ``rows``), prob [N] float32 (max / total, 0 there) and total [N] float32; strided views allowed
    (a column of an [N, views] table). Bit for bit trace_argmax: a row's total adds its columns in
    ascending order from zero, as ``index_add_`` does (tested)."""
    n = label.shape[0]
    for i in prange(n):
        label[i] = -1
        prob[i] = np.float32(0.0)
        total[i] = np.float32(0.0)
    for r in prange(rows.shape[0]):
        g = rows[r]
        label[g], prob[g], total[g] = _reduce_row(indptr, cols, weights, r)
