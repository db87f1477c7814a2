"""The numba kernels of :mod:`trace3d.lifting.query`: the distances of every pixel's feature to the query
features (and the masks they threshold), and the blending weights summed over a mask's pixels. Their
twins are numpy, in :mod:`trace3d.lifting.query` (``_query_distances_numpy``, ``object_weights_numpy``)."""

from __future__ import annotations

import numpy as np
from numba import njit, prange


# ----------------------------------------------------------------------------------------------
# Distances to the query features as numba kernels: the evaluation asks for every training view's
# mask of every object (63 views x 27 objects per variant on a default room), and numpy built an
# [Q, H, W, D] difference array for each.  The kernels give numpy's values to the bit: the same
# float32 differences and squares, their sum over D in numpy's pairwise order (``np.add.reduce``
# over a contiguous axis: eight running sums for n >= 8, combined as ((r0 + r1) + (r2 + r3)) +
# ((r4 + r5) + (r6 + r7)), then the n % 8 rest one by one; one running sum for n < 8), the same
# correctly rounded square root (tested against numpy for several D, ties at the thresholds
# included).
# ----------------------------------------------------------------------------------------------

_PAIRWISE_BLOCK = 128  # numpy's PW_BLOCKSIZE: longer sums are split in halves (not done here)


def _kernel_applies(feature_map: np.ndarray, features: np.ndarray) -> bool:
    return (isinstance(feature_map, np.ndarray) and feature_map.dtype == np.float32 and feature_map.ndim == 3
            and feature_map.flags.c_contiguous and features.dtype == np.float32 and features.ndim == 2
            and features.flags.c_contiguous and features.shape[1] == feature_map.shape[2]
            and 0 < features.shape[1] <= _PAIRWISE_BLOCK)


@njit(cache=True, inline="always")
def _first_lanes(fmap, y, x, feats, k):
    """The eight running sums of squares after the first eight dimensions (D >= 8), in scalars (an
    np.empty(8) here was a heap allocation per pixel and query)."""
    e0 = fmap[y, x, 0] - feats[k, 0]
    e1 = fmap[y, x, 1] - feats[k, 1]
    e2 = fmap[y, x, 2] - feats[k, 2]
    e3 = fmap[y, x, 3] - feats[k, 3]
    e4 = fmap[y, x, 4] - feats[k, 4]
    e5 = fmap[y, x, 5] - feats[k, 5]
    e6 = fmap[y, x, 6] - feats[k, 6]
    e7 = fmap[y, x, 7] - feats[k, 7]
    return e0 * e0, e1 * e1, e2 * e2, e3 * e3, e4 * e4, e5 * e5, e6 * e6, e7 * e7


@njit(cache=True, inline="always")
def _combine(lanes):
    """numpy's pairwise combination of the eight running sums."""
    r0, r1, r2, r3, r4, r5, r6, r7 = lanes
    return ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))


@njit(cache=True, inline="always")
def _finish(fmap, y, x, feats, k, lanes):
    """The full sum of squares from :func:`_first_lanes`: the other dimensions in blocks of eight, the
    eight sums combined pairwise, then the remainder one by one (numpy's order)."""
    n = feats.shape[1]
    r0, r1, r2, r3, r4, r5, r6, r7 = lanes
    full = n - n % 8
    for i in range(8, full, 8):
        e0 = fmap[y, x, i] - feats[k, i]
        e1 = fmap[y, x, i + 1] - feats[k, i + 1]
        e2 = fmap[y, x, i + 2] - feats[k, i + 2]
        e3 = fmap[y, x, i + 3] - feats[k, i + 3]
        e4 = fmap[y, x, i + 4] - feats[k, i + 4]
        e5 = fmap[y, x, i + 5] - feats[k, i + 5]
        e6 = fmap[y, x, i + 6] - feats[k, i + 6]
        e7 = fmap[y, x, i + 7] - feats[k, i + 7]
        r0 += e0 * e0
        r1 += e1 * e1
        r2 += e2 * e2
        r3 += e3 * e3
        r4 += e4 * e4
        r5 += e5 * e5
        r6 += e6 * e6
        r7 += e7 * e7
    res = _combine((r0, r1, r2, r3, r4, r5, r6, r7))
    for i in range(full, n):
        e = fmap[y, x, i] - feats[k, i]
        res += e * e
    return res


@njit(cache=True, inline="always")
def _squared_distance(fmap, y, x, feats, k):
    """sum over d of (fmap[y, x, d] - feats[k, d])^2 in float32, in numpy's pairwise order (D <= 128)."""
    n = feats.shape[1]
    if n < 8:
        res = np.float32(0.0)
        for d in range(n):
            e = fmap[y, x, d] - feats[k, d]
            res += e * e
        return res
    return _finish(fmap, y, x, feats, k, _first_lanes(fmap, y, x, feats, k))


@njit(cache=True, inline="always")
def _within(fmap, y, x, feats, k, t):
    """sqrt(:func:`_squared_distance`) <= t, the same float32 operations, but a pixel is rejected after
    the first eight dimensions when their eight running sums alone already exceed t: every later
    operation adds a non-negative square and rounding is monotone, so the full sum is at least that
    partial sum (the answer is exactly the full test's)."""
    n = feats.shape[1]
    if n < 8:
        return np.sqrt(_squared_distance(fmap, y, x, feats, k)) <= t
    lanes = _first_lanes(fmap, y, x, feats, k)
    if np.sqrt(_combine(lanes)) > t:
        return False
    return np.sqrt(_finish(fmap, y, x, feats, k, lanes)) <= t


@njit(parallel=True, cache=True)
def _query_distances(fmap, feats, out):
    """out[k, y, x] = |fmap[y, x] - feats[k]| (float32, numpy's values)."""
    h, w, _ = fmap.shape
    for y in prange(h):
        for k in range(feats.shape[0]):
            for x in range(w):
                out[k, y, x] = np.sqrt(_squared_distance(fmap, y, x, feats, k))


@njit(parallel=True, cache=True)
def _query_mask(fmap, feats, thresholds, out):
    """out[y, x] = any over k of |fmap[y, x] - feats[k]| <= thresholds[k] (the distances of
    :func:`_query_distances`; a pixel stops at its first hit)."""
    h, w, _ = fmap.shape
    for y in prange(h):
        for x in range(w):
            hit = False
            for k in range(feats.shape[0]):
                if _within(fmap, y, x, feats, k, thresholds[k]):
                    hit = True
                    break
            out[y, x] = hit


@njit(parallel=True, cache=True)
def _query_mask_stack(stack, feats, thresholds, out):
    """:func:`_query_mask` of every view of ``stack`` [V, H, W, D] into ``out`` [V, H, W] in one call
    (one parallel launch per object instead of one per view: on a loaded machine each launch waits for
    both threads to be scheduled)."""
    v, h, w, _ = stack.shape
    for vy in prange(v * h):
        i = vy // h
        y = vy - i * h
        fmap = stack[i]
        for x in range(w):
            hit = False
            for k in range(feats.shape[0]):
                if _within(fmap, y, x, feats, k, thresholds[k]):
                    hit = True
                    break
            out[i, y, x] = hit


@njit(parallel=True, cache=True)
def _query_mask_objects(fmap, feats, thresholds, starts, centres, radii, out):
    """:func:`_query_mask` of several objects' query points at one view in one call: object ``o`` has
    the points ``starts[o]:starts[o + 1]`` of ``feats`` [sum Q_o, D] and ``thresholds``; ``out`` is
    [O, H, W] (the evaluation's pass asks every object's mask at each view; one parallel launch per
    view).

    ``centres`` [O, D] and ``radii`` [O] (:func:`object_balls`) bound each object's points: a pixel whose
    first eight dimensions alone put it farther than ``radii[o]`` from ``centres[o]`` is outside every
    point's ball, so it is refused after one partial distance instead of one per point (the answer is
    exactly the points' own test's: the radius has a margin above every rounding, :func:`object_balls`).
    An object with one point, fewer than eight dimensions or an infinite radius is tested point by
    point."""
    o_count = out.shape[0]
    h, w, d = fmap.shape
    for oy in prange(o_count * h):
        o = oy // h
        y = oy - o * h
        bound = d >= 8 and starts[o + 1] - starts[o] > 1 and radii[o] < np.inf
        for x in range(w):
            hit = False
            if bound and np.sqrt(_combine(_first_lanes(fmap, y, x, centres, o))) > radii[o]:
                out[o, y, x] = False
                continue
            for k in range(starts[o], starts[o + 1]):
                if _within(fmap, y, x, feats, k, thresholds[k]):
                    hit = True
                    break
            out[o, y, x] = hit


def object_balls(feats: np.ndarray, thresholds: np.ndarray, starts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per object (points ``starts[o]:starts[o + 1]`` of ``feats`` [Q, D] float32 with ``thresholds`` [Q]):
    the centre [O, D] float32 (the points' mean) and a radius [O] float32 such that a feature farther
    than it from the centre, by :func:`_query_mask_objects`'s partial float32 sum, is farther than
    ``thresholds[k]`` from every point ``k`` by :func:`_within`'s float32 test.

    By the triangle inequality a feature at true distance r from the centre is at least
    r - |centre - f_k| from point k; R = max_k (|centre - f_k| + t_k) (float64) bounds the balls, and the
    radius R (1 + 1e-3) leaves room for the float32 roundings of both tests (relative errors below 1e-5
    for D <= 128: a partial sum of squares is at most the full one, rounding is monotone). An object with
    no point, or non-finite values, gets an infinite radius (tested point by point)."""
    starts = np.asarray(starts, np.int64)
    o_count = starts.shape[0] - 1
    counts = np.diff(starts)
    centres = np.zeros((o_count, feats.shape[1]), np.float32)
    radii = np.full(o_count, np.inf, np.float32)
    full = np.flatnonzero(counts > 0)
    if not full.size:
        return centres, radii
    f64 = np.asarray(feats, np.float64)
    centres[full] = (np.add.reduceat(f64, starts[full], axis=0) / counts[full, None]).astype(np.float32)
    owner = np.repeat(np.arange(o_count), counts)
    reach = np.sqrt(((f64 - centres[owner].astype(np.float64)) ** 2).sum(1)) + np.asarray(thresholds, np.float64)
    bound = np.maximum.reduceat(reach, starts[full]) * (1.0 + 1e-3)
    with np.errstate(over="ignore", invalid="ignore"):
        r32 = bound.astype(np.float32)
        r32 = np.where(r32 >= bound, r32, np.nextafter(r32, np.float32(np.inf)))  # never below the float64 bound
    ok = np.isfinite(bound) & np.isfinite(centres[full]).all(1)
    radii[full[ok]] = r32[ok]
    return centres, radii


@njit(parallel=True, cache=True)
def _row_distances(rows, query, out):
    """out[s] = |rows[s, 0] - query[0]| for ``rows`` [S, 1, D] and ``query`` [1, D] (float64): the float64
    version of :func:`_query_distances`, numpy's values to the bit (:func:`row_distances`)."""
    for s in prange(rows.shape[0]):
        out[s] = np.sqrt(_squared_distance(rows, s, 0, query, 0))


def row_distances(features: np.ndarray, query: np.ndarray) -> np.ndarray:
    """[S] float64: ``np.sqrt(((features - query) ** 2).sum(1))`` for ``features`` [S, D] and ``query`` [D]
    (float64; numpy's pairwise sum over D), by :func:`_row_distances` without numpy's two [S, D]
    temporaries when D is 8..128 and both are float64 (a click scores 80k Gaussians); else numpy itself
    (the twin)."""
    features = np.asarray(features)
    query = np.asarray(query, np.float64)
    d = features.shape[1] if features.ndim == 2 else 0
    if features.dtype == np.float64 and features.flags.c_contiguous and 8 <= d <= _PAIRWISE_BLOCK \
            and query.shape == (d,):
        out = np.empty(features.shape[0], np.float64)
        _row_distances(features.reshape(features.shape[0], 1, d), np.ascontiguousarray(query.reshape(1, d)), out)
        return out
    return np.sqrt(((features - query[None, :]) ** 2).sum(1))


@njit(cache=True)
def _add_masked_rows(inside, pixels, indptr, indices, weights, fg, view, touched, order):
    """fg += the per-Gaussian sums over the rows whose pixel is ``inside`` (``view``, ``touched`` and
    ``order`` are scratch: zero / False on entry and on return)."""
    count = 0
    for r in range(pixels.shape[0]):
        if not inside[pixels[r]]:
            continue
        for e in range(indptr[r], indptr[r + 1]):
            g = indices[e]
            if not touched[g]:
                touched[g] = True
                order[count] = g
                count += 1
            view[g] += np.float64(weights[e])
    for k in range(count):
        g = order[k]
        fg[g] += view[g]
        view[g] = 0.0
        touched[g] = False
