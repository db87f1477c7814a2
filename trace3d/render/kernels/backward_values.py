"""The values-only backward: the same back-to-front walk as :mod:`.backward` for the value gradients
alone, when nothing upstream of the geometry needs a gradient (lifting's frozen scene, GIT through
autograd).  (Part of the former ``render/kernels.py``, moved unchanged.)"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from .tiles import (FASTMATH, TILE, TILE_PIXELS, _box_in_tile, _lane_position, _lane_unblend, _live_rows,
                    _tile_bounds, eval_lane, splat_geometry)

# the values-only backward's flat tile buffer: transmittance before the splats still to come, last
# blended list position (tile-relative, + 1), the current rows' blend weights, then the current
# splat's value sums (n_cols) and after them the upstream gradient pixel-major (n_cols per pixel)
V_TRANS = np.uint64(0 * TILE_PIXELS)
V_LAST = np.uint64(1 * TILE_PIXELS)
V_W = np.uint64(2 * TILE_PIXELS)
V_ACC = np.uint64(3 * TILE_PIXELS)


@njit(parallel=True, cache=True, fastmath=FASTMATH)
def backward_values_kernel(egeom, ebox, lists, n, offsets, width, height, tiles_x, near, n_chunks, final_t, last,
                           v_head, v_tail, n_cols):
    """Back-to-front gradients of the blended values only (the geometry needs none: lifting's frozen
    scene, GIT through autograd): d vals[g, c] = sum over pixels of w_gp v[p, c], with w_gp the blend
    weight of splat g at pixel p.

    The tile walk is :func:`backward_kernel`'s without its gradient terms: per (splat, tile) one vector
    loop over the lanes of the rows where the splat was blended evaluates alpha (:func:`eval_lane`, the
    forward's decisions), moves the pixel's transmittance past the splat by the same operations and
    stores the blend weight (0 where the pair was not blended).  The value sums then go per blended
    lane, rows and lanes in ascending order as :func:`backward_kernel` adds them, all columns of a lane
    in one vector loop over the pixel-major upstream gradient: the same value gradients to the bit
    (tested).  Lanes of weight 0 are skipped, so a non-finite upstream gradient where the splat did not
    blend is ignored, as there.  Deterministic: per-chunk buffers as in :func:`backward_kernel`.

    Args:
        as :func:`backward_kernel`; ``n`` the number of splats; only the first ``n_cols`` value columns
        get gradients (the head's then the tail's).
    Returns:
        grads [n_chunks, N, n_cols] float32 (sum over axis 0).
    """
    n_tiles = offsets.shape[0] - 1
    grads = np.zeros((n_chunks, n, n_cols), np.float32)
    near32 = np.float32(near)
    zero = np.float32(0.0)
    tp = TILE_PIXELS
    n_head = min(v_head.shape[2], n_cols)
    for chunk in prange(n_chunks):
        gbuf = grads[chunk]
        gt = V_ACC + np.uint64(n_cols)  # upstream gradient, pixel p's columns at gt + p n_cols
        buf = np.zeros(gt + np.uint64(n_cols * tp), np.float32)
        rows_live = np.zeros(TILE, np.bool_)
        for t in range(chunk, n_tiles, n_chunks):
            start = offsets[t]
            end = offsets[t + 1]
            if start == end:
                continue
            px0, py0, px1, py1 = _tile_bounds(t, tiles_x, width, height)
            buf[:] = 0.0  # pixels outside the image stay zero: never blended
            max_last = 0
            for py in range(py0, py1):
                for px in range(px0, px1):
                    p = np.uint64((py - py0) * TILE + (px - px0))
                    lp = last[py, px]
                    if lp > max_last:
                        max_last = lp
                    buf[V_TRANS + p] = final_t[py, px]
                    buf[V_LAST + p] = np.float32(max(lp - start, 0))
                    at = gt + p * np.uint64(n_cols)
                    for ch in range(n_head):
                        buf[at + np.uint64(ch)] = v_head[py, px, ch]
                    for ch in range(n_head, n_cols):
                        buf[at + np.uint64(ch)] = v_tail[py, px, ch - n_head]
            for j in range(max_last - 1, start - 1, -1):
                g = lists[j]
                lx0, lx1, y0, y1 = _box_in_tile(ebox, j, px0, py0, px1, py1)
                jrel = np.float32(j - start)
                a0, a1, a2, b0, b1, b2, d0, d1, d2, tw0, tw1, tw2, mx, my, opac = splat_geometry(egeom, j)
                r_first, r_last = _live_rows(buf, V_LAST, rows_live, y0 - py0, y1 - py0, lx0, lx1, jrel)
                if r_first < 0:
                    continue
                q0 = r_first * TILE
                q1 = (r_last + 1) * TILE
                for q in range(q0, q1):
                    p, i, x, y, dy = _lane_position(q, px0, py0, my)
                    al, _, _, _, _, _, _ = eval_lane(x, a0 + d0 * y, a1 + d1 * y, a2 + d2 * y, b0, b1, b2, mx, dy * dy,
                                                     opac, tw0, tw1, tw2, near32)
                    live, t_before, _ = _lane_unblend(buf, V_TRANS, V_LAST, p, i, lx0, lx1, jrel, al)
                    buf[V_W + p] = al * t_before if live else zero
                    buf[V_TRANS + p] = t_before if live else buf[V_TRANS + p]
                # the value sums: per blended lane, rows and lanes in ascending order (as backward_kernel
                # adds them), all columns of the lane in one vector loop
                buf[V_ACC:V_ACC + np.uint64(n_cols)] = 0.0
                for r in range(r_first, r_last + 1):
                    if not rows_live[r]:
                        continue
                    row = np.uint64(r * TILE)
                    for i in range(lx0, lx1):
                        p = row + np.uint64(i)
                        w = buf[V_W + p]
                        if w != zero:
                            at = gt + p * np.uint64(n_cols)
                            for ch in range(n_cols):
                                buf[V_ACC + np.uint64(ch)] += w * buf[at + np.uint64(ch)]
                for ch in range(n_cols):
                    gbuf[g, ch] += buf[V_ACC + np.uint64(ch)]
    return grads


@njit(parallel=True, cache=True)
def sum_value_chunks(grads, k):
    """The values-only backward's per-chunk buffers [n_chunks, N, n_cols] summed in chunk order into
    [N, k] (columns past n_cols zero: nobody asked for them)."""
    n_chunks, n, cols = grads.shape
    out = np.zeros((n, k), np.float32)
    for g in prange(n):
        for c in range(cols):
            s = grads[0, g, c]
            for m in range(1, n_chunks):
                s += grads[m, g, c]
            out[g, c] = s
    return out
