"""The hand-written backward of the forward tile kernel: back to front over each tile's list, the
gradients of the geometry columns and the values, one buffer per worker chunk, summed afterwards
(:func:`sum_chunks`); and the background's share of the transmittance gradient
(:func:`fold_background_grad`).  (Part of the former ``render/kernels.py``, moved unchanged.)"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..projection import ALPHA_MAX
from .tiles import (FASTMATH, GEOM_GRAD_COLS, TILE, TILE_PIXELS, _box_in_tile, _lane_position, _lane_unblend,
                    _live_rows, _scaled_add, _tile_bounds, eval_lane, first_values, splat_geometry)

# field offsets in the backward kernel's flat tile buffer, one TILE_PIXELS plane each: the pixel's
# transmittance before the splats still to come, the running "what comes after" sum, its last blended
# list position (tile-relative, + 1), reference depth, upstream v_z, v_z2, v_final_t * final_t, median
# splat (tile-relative, -1 none) and v_median; then, for the current splat row, whether the pair was
# blended, its weight and its terms of the splat's gradient sums; then the per-lane values kept between
# the two passes when there are more than 8 channels; then one plane per channel of the upstream gradient
# of the blended channels
B_TRANS = np.uint64(0 * TILE_PIXELS)
B_AFTER = np.uint64(1 * TILE_PIXELS)
B_LAST = np.uint64(2 * TILE_PIXELS)
B_REF = np.uint64(3 * TILE_PIXELS)
B_VZ = np.uint64(4 * TILE_PIXELS)
B_VZ2 = np.uint64(5 * TILE_PIXELS)
B_VFT = np.uint64(6 * TILE_PIXELS)
B_MED = np.uint64(7 * TILE_PIXELS)
B_VMED = np.uint64(8 * TILE_PIXELS)
B_LIVE = np.uint64(9 * TILE_PIXELS)
B_W = np.uint64(10 * TILE_PIXELS)  # 0 where the pair was not blended
B_TOP = np.uint64(11 * TILE_PIXELS)  # the gradient-sum terms (0 where they do not apply)
B_TTW0 = np.uint64(12 * TILE_PIXELS)
B_TTW1 = np.uint64(13 * TILE_PIXELS)
B_TTW2 = np.uint64(14 * TILE_PIXELS)
B_TC0 = np.uint64(15 * TILE_PIXELS)
B_TC1 = np.uint64(16 * TILE_PIXELS)
B_TC2 = np.uint64(17 * TILE_PIXELS)
B_TB0 = np.uint64(18 * TILE_PIXELS)
B_TB1 = np.uint64(19 * TILE_PIXELS)
B_TB2 = np.uint64(20 * TILE_PIXELS)
B_TMX = np.uint64(21 * TILE_PIXELS)
B_TMY = np.uint64(22 * TILE_PIXELS)
B_A = np.uint64(23 * TILE_PIXELS)  # kept between the passes (more than 8 channels)
B_Z = np.uint64(24 * TILE_PIXELS)
B_U = np.uint64(25 * TILE_PIXELS)
B_V_ = np.uint64(26 * TILE_PIXELS)
B_INV = np.uint64(27 * TILE_PIXELS)
B_DISK = np.uint64(28 * TILE_PIXELS)
B_GAUSS = np.uint64(29 * TILE_PIXELS)
B_TB = np.uint64(30 * TILE_PIXELS)
B_IOM = np.uint64(31 * TILE_PIXELS)
B_DZ = np.uint64(32 * TILE_PIXELS)
B_DOT = np.uint64(33 * TILE_PIXELS)
B_G0 = np.uint64(34 * TILE_PIXELS)  # upstream channel gradients, one plane per channel (at least 8)
B_G1 = np.uint64(35 * TILE_PIXELS)
B_G2 = np.uint64(36 * TILE_PIXELS)
B_G3 = np.uint64(37 * TILE_PIXELS)
B_G4 = np.uint64(38 * TILE_PIXELS)
B_G5 = np.uint64(39 * TILE_PIXELS)
B_G6 = np.uint64(40 * TILE_PIXELS)
B_G7 = np.uint64(41 * TILE_PIXELS)


@njit(inline="always", fastmath=FASTMATH)
def _lane_front(buf, p, i, x, lx0, lx1, jrel, e0, e1, e2, b0, b1, b2, mx, dy2, opac, tw0, tw1, tw2, near32,
                v0, v1, v2, v3, v4, v5, v6, v7):
    """One lane of a splat row in the backward, up to the dot product of the upstream gradient with the
    splat's values over the first 8 channels (zero values and planes past K add nothing)."""
    al, zz, uu, vv, iv, dk, gs = eval_lane(x, e0, e1, e2, b0, b1, b2, mx, dy2, opac, tw0, tw1, tw2, near32)
    live, t_before, inv_one_minus = _lane_unblend(buf, B_TRANS, B_LAST, p, i, lx0, lx1, jrel, al)
    dz = zz - buf[B_REF + p]
    dot = buf[B_VZ + p] * zz + buf[B_VZ2 + p] * dz * dz
    dot += buf[B_G0 + p] * v0
    dot += buf[B_G1 + p] * v1
    dot += buf[B_G2 + p] * v2
    dot += buf[B_G3 + p] * v3
    dot += buf[B_G4 + p] * v4
    dot += buf[B_G5 + p] * v5
    dot += buf[B_G6 + p] * v6
    dot += buf[B_G7 + p] * v7
    return live, al, zz, uu, vv, iv, dk, gs, t_before, inv_one_minus, dz, dot


@njit(inline="always", fastmath=FASTMATH)
def _lane_terms(buf, p, x, live, alpha, z, u, v, inv_c2, disk, gauss, t_before, inv_one_minus, dz, dot, jrel,
                opac, tw0, tw1, mx, dy):
    """The rest of one lane: the pixel's transmittance and "what comes after" sum move past the splat
    where the pair was blended, and the lane's terms of the splat's gradient sums go to the buffer
    (zero where a term does not apply), computed as the scalar backward computed them."""
    zero = np.float32(0.0)
    two = np.float32(2.0)
    w = alpha * t_before
    after = buf[B_AFTER + p]
    g_alpha = t_before * dot - (after + buf[B_VFT + p]) * inv_one_minus
    buf[B_AFTER + p] = after + w * dot if live else after
    buf[B_TRANS + p] = t_before if live else buf[B_TRANS + p]
    g_z = w * (buf[B_VZ + p] + two * dz * buf[B_VZ2 + p])
    g_z = g_z + buf[B_VMED + p] if buf[B_MED + p] == jrel else g_z
    unclamped = not opac * gauss > np.float32(ALPHA_MAX)
    g_sigma = -g_alpha * alpha if unclamped else zero
    on_disk = live & disk
    on_filter = live & (not disk)
    g_u = g_z * tw0 + g_sigma * u
    g_v = g_z * tw1 + g_sigma * v
    g_c0 = g_u * inv_c2
    g_c1 = g_v * inv_c2
    g_c2 = -(g_u * u + g_v * v) * inv_c2
    dx = x - mx
    buf[B_LIVE + p] = np.float32(1.0) if live else zero
    buf[B_W + p] = w if live else zero
    buf[B_TOP + p] = g_alpha * gauss if live & unclamped else zero
    buf[B_TTW0 + p] = g_z * u if on_disk else zero
    buf[B_TTW1 + p] = g_z * v if on_disk else zero
    buf[B_TTW2 + p] = g_z if live else zero
    buf[B_TC0 + p] = g_c0 if on_disk else zero
    buf[B_TC1 + p] = g_c1 if on_disk else zero
    buf[B_TC2 + p] = g_c2 if on_disk else zero
    buf[B_TB0 + p] = g_c0 * x if on_disk else zero
    buf[B_TB1 + p] = g_c1 * x if on_disk else zero
    buf[B_TB2 + p] = g_c2 * x if on_disk else zero
    buf[B_TMX + p] = two * dx * g_sigma if on_filter else zero
    buf[B_TMY + p] = two * dy * g_sigma if on_filter else zero


@njit(parallel=True, cache=True, fastmath=FASTMATH)
def backward_kernel(egeom, ebox, lists, vals, offsets, width, height, tiles_x, near, n_chunks,
                    final_t, depth_ref, last, median_at, v_head, v_tail, v_z, v_z2, v_final_t, v_median):
    """Back-to-front gradients of every tile.

    Per (splat, tile): first the tile rows where the splat was blended into some pixel; then one
    vector loop over every lane of those rows (the lanes are independent, so rows overlap in the
    pipeline) evaluates the pair (:func:`eval_lane`) and computes, with selects instead of branches,
    the transmittance before the splat, the upstream gradient's dot product with the splat's values,
    the pixel's state moved past the splat and the lane's terms of the splat's gradient sums (one flat
    tile buffer at constant field offsets, unsigned indices, as in the forward); with more than 8
    channels that loop stops after the first 8 channels' dot product, the other channels are added one
    loop each and a second loop does the rest.  Then, row by row, the terms are added into the splat's
    sums lane by lane in ascending order: the order of the scalar loop this replaced, so the sums are
    the same bit for bit (a lane the splat did not blend adds zero terms, which leave a
    sum unchanged; the channels' sums skip it, so a non-finite upstream gradient there is ignored as
    before).

    Args:
        as :func:`forward_kernel`, plus its saved final_t, depth_ref, last, median_at [H, W] and
        the upstream gradients of the blended channels v_head [H, W, S] and v_tail [H, W, K - S] (the
        forward's head and tail), v_z, v_z2, v_final_t, v_median [H, W].
    Returns:
        grads [n_chunks, N, 15 + K] float32 (sum over axis 0): d/d geom[:, :15] then d/d vals.
    """
    n = vals.shape[0]
    k_ch = vals.shape[1]
    n_cols = GEOM_GRAD_COLS + k_ch
    n_tiles = offsets.shape[0] - 1
    grads = np.zeros((n_chunks, n, n_cols), np.float32)
    near32 = np.float32(near)
    zero = np.float32(0.0)
    half = np.float32(0.5)
    tp = TILE_PIXELS
    n_planes = max(k_ch, 8)
    n_head = v_head.shape[2]
    for chunk in prange(n_chunks):
        gbuf = grads[chunk]
        buf = np.zeros(B_G0 + np.uint64(n_planes * tp), np.float32)
        g_vals = np.zeros(k_ch, np.float32)
        rows_live = np.zeros(TILE, np.bool_)
        for t in range(chunk, n_tiles, n_chunks):
            start = offsets[t]
            end = offsets[t + 1]
            if start == end:
                continue
            px0, py0, px1, py1 = _tile_bounds(t, tiles_x, width, height)
            # the tile's pixels (those outside the image stay zero: never blended)
            buf[:B_VMED + np.uint64(tp)] = 0.0
            buf[B_G0:B_G0 + np.uint64(k_ch * tp)] = 0.0
            max_last = 0
            for py in range(py0, py1):
                for px in range(px0, px1):
                    p = np.uint64((py - py0) * TILE + (px - px0))
                    lp = last[py, px]
                    if lp > max_last:
                        max_last = lp
                    buf[B_TRANS + p] = final_t[py, px]
                    buf[B_LAST + p] = np.float32(max(lp - start, 0))
                    buf[B_REF + p] = depth_ref[py, px]
                    buf[B_VZ + p] = v_z[py, px]
                    buf[B_VZ2 + p] = v_z2[py, px]
                    buf[B_VFT + p] = v_final_t[py, px] * final_t[py, px]
                    mp = median_at[py, px]
                    buf[B_MED + p] = np.float32(mp - start) if mp >= start else np.float32(-1.0)
                    buf[B_VMED + p] = v_median[py, px]
                    for ch in range(n_head):
                        buf[B_G0 + np.uint64(ch * tp) + p] = v_head[py, px, ch]
                    for ch in range(n_head, k_ch):
                        buf[B_G0 + np.uint64(ch * tp) + p] = v_tail[py, px, ch - n_head]
            for j in range(max_last - 1, start - 1, -1):
                g = lists[j]
                lx0, lx1, y0, y1 = _box_in_tile(ebox, j, px0, py0, px1, py1)
                jrel = np.float32(j - start)
                a0, a1, a2, b0, b1, b2, d0, d1, d2, tw0, tw1, tw2, mx, my, opac = splat_geometry(egeom, j)
                v0, v1, v2, v3, v4, v5, v6, v7 = first_values(vals, g)
                # per-splat gradient sums over this tile
                ga0 = zero
                ga1 = zero
                ga2 = zero
                gb0 = zero
                gb1 = zero
                gb2 = zero
                gd0 = zero
                gd1 = zero
                gd2 = zero
                gtw0 = zero
                gtw1 = zero
                gtw2 = zero
                gmx = zero
                gmy = zero
                gop = zero
                gv0 = zero
                gv1 = zero
                gv2 = zero
                gv3 = zero
                gv4 = zero
                gv5 = zero
                gv6 = zero
                gv7 = zero
                for ch in range(8, k_ch):
                    g_vals[ch] = 0
                # the rows of the tile where this splat was blended into some pixel
                r_first, r_last = _live_rows(buf, B_LAST, rows_live, y0 - py0, y1 - py0, lx0, lx1, jrel)
                if r_first < 0:
                    continue
                # every lane of those rows at once (independent lanes: the vector loop overlaps rows)
                q0 = r_first * TILE
                q1 = (r_last + 1) * TILE
                if k_ch <= 8:
                    # pass 1, whole
                    for q in range(q0, q1):
                        p, i, x, y, dy = _lane_position(q, px0, py0, my)
                        live, al, zz, uu, vv, iv, dk, gs, tb, iom, dz, dot = _lane_front(
                            buf, p, i, x, lx0, lx1, jrel, a0 + d0 * y, a1 + d1 * y, a2 + d2 * y, b0, b1, b2, mx,
                            dy * dy, opac, tw0, tw1, tw2, near32, v0, v1, v2, v3, v4, v5, v6, v7)
                        _lane_terms(buf, p, x, live, al, zz, uu, vv, iv, dk, gs, tb, iom, dz, dot, jrel, opac,
                                    tw0, tw1, mx, dy)
                else:
                    # pass 1 up to the first 8 channels' dot product
                    for q in range(q0, q1):
                        p, i, x, y, dy = _lane_position(q, px0, py0, my)
                        live, al, zz, uu, vv, iv, dk, gs, tb, iom, dz, dot = _lane_front(
                            buf, p, i, x, lx0, lx1, jrel, a0 + d0 * y, a1 + d1 * y, a2 + d2 * y, b0, b1, b2, mx,
                            dy * dy, opac, tw0, tw1, tw2, near32, v0, v1, v2, v3, v4, v5, v6, v7)
                        buf[B_LIVE + p] = np.float32(1.0) if live else zero
                        buf[B_A + p] = al
                        buf[B_Z + p] = zz
                        buf[B_U + p] = uu
                        buf[B_V_ + p] = vv
                        buf[B_INV + p] = iv
                        buf[B_DISK + p] = np.float32(1.0) if dk else zero
                        buf[B_GAUSS + p] = gs
                        buf[B_TB + p] = tb
                        buf[B_IOM + p] = iom
                        buf[B_DZ + p] = dz
                        buf[B_DOT + p] = dot
                    # the other channels' dot products, in channel order
                    for ch in range(8, k_ch):
                        _scaled_add(buf, B_DOT, B_G0 + np.uint64(ch * tp), vals[g, ch], q0, q1)
                    # pass 2
                    for q in range(q0, q1):
                        p, _, x, _, dy = _lane_position(q, px0, py0, my)
                        _lane_terms(buf, p, x, buf[B_LIVE + p] != zero, buf[B_A + p], buf[B_Z + p],
                                    buf[B_U + p], buf[B_V_ + p], buf[B_INV + p], buf[B_DISK + p] != zero,
                                    buf[B_GAUSS + p], buf[B_TB + p], buf[B_IOM + p], buf[B_DZ + p],
                                    buf[B_DOT + p], jrel, opac, tw0, tw1, mx, dy)
                # the sums, row by row and lane by lane in ascending order
                for r in range(r_first, r_last + 1):
                    if not rows_live[r]:
                        continue
                    row = np.uint64(r * TILE)
                    y = np.float32(py0 + r) + half
                    rc0 = zero
                    rc1 = zero
                    rc2 = zero
                    for i in range(lx0, lx1):
                        p = row + np.uint64(i)
                        gop += buf[B_TOP + p]
                        gtw0 += buf[B_TTW0 + p]
                        gtw1 += buf[B_TTW1 + p]
                        gtw2 += buf[B_TTW2 + p]
                        rc0 += buf[B_TC0 + p]
                        rc1 += buf[B_TC1 + p]
                        rc2 += buf[B_TC2 + p]
                        gb0 += buf[B_TB0 + p]
                        gb1 += buf[B_TB1 + p]
                        gb2 += buf[B_TB2 + p]
                        gmx -= buf[B_TMX + p]
                        gmy -= buf[B_TMY + p]
                        live = buf[B_LIVE + p] != zero
                        w = buf[B_W + p]
                        gv0 += w * buf[B_G0 + p] if live else zero
                        gv1 += w * buf[B_G1 + p] if live else zero
                        gv2 += w * buf[B_G2 + p] if live else zero
                        gv3 += w * buf[B_G3 + p] if live else zero
                        gv4 += w * buf[B_G4 + p] if live else zero
                        gv5 += w * buf[B_G5 + p] if live else zero
                        if k_ch > 6:  # the colour and normal channels of a fit are 6
                            gv6 += w * buf[B_G6 + p] if live else zero
                            gv7 += w * buf[B_G7 + p] if live else zero
                    if k_ch > 8:
                        # channels past the first 8: per blended lane, all of them
                        for i in range(lx0, lx1):
                            p = row + np.uint64(i)
                            if buf[B_LIVE + p] != zero:
                                w = buf[B_W + p]
                                for ch in range(8, k_ch):
                                    g_vals[ch] += w * buf[B_G0 + np.uint64(ch * tp) + p]
                    ga0 += rc0
                    ga1 += rc1
                    ga2 += rc2
                    gd0 += rc0 * y
                    gd1 += rc1 * y
                    gd2 += rc2 * y
                gbuf[g, 0] += ga0
                gbuf[g, 1] += ga1
                gbuf[g, 2] += ga2
                gbuf[g, 3] += gb0
                gbuf[g, 4] += gb1
                gbuf[g, 5] += gb2
                gbuf[g, 6] += gd0
                gbuf[g, 7] += gd1
                gbuf[g, 8] += gd2
                gbuf[g, 9] += gtw0
                gbuf[g, 10] += gtw1
                gbuf[g, 11] += gtw2
                gbuf[g, 12] += gmx
                gbuf[g, 13] += gmy
                gbuf[g, 14] += gop
                gv = (gv0, gv1, gv2, gv3, gv4, gv5, gv6, gv7)
                for ch in range(min(k_ch, 8)):
                    gbuf[g, GEOM_GRAD_COLS + ch] += gv[ch]
                for ch in range(8, k_ch):
                    gbuf[g, GEOM_GRAD_COLS + ch] += g_vals[ch]
    return grads



@njit(parallel=True, cache=True)
def sum_chunks(grads):
    """The backward kernel's per-chunk buffers [n_chunks, N, 15 + K] summed in chunk order and split
    into the geometry [N, 15] and value [N, K] gradients, in one parallel pass over the rows."""
    n_chunks, n, cols = grads.shape
    g_geom = np.empty((n, GEOM_GRAD_COLS), np.float32)
    g_vals = np.empty((n, cols - GEOM_GRAD_COLS), np.float32)
    for g in prange(n):
        for c in range(cols):
            acc = grads[0, g, c]
            for k in range(1, n_chunks):
                acc += grads[k, g, c]
            if c < GEOM_GRAD_COLS:
                g_geom[g, c] = acc
            else:
                g_vals[g, c - GEOM_GRAD_COLS] = acc
    return g_geom, g_vals


@njit(parallel=True, cache=True)
def fold_background_grad(v_head, v_final_t, background):
    """Add the blended background's share of the gradient to ``v_final_t`` in place:
    ``((g_0 b_0 + g_1 b_1) + g_2 b_2)`` per pixel, in torch's order of its broadcast sum."""
    h, w, split = v_head.shape
    for i in prange(h):
        for j in range(w):
            share = v_head[i, j, 0] * background[0]
            for c in range(1, split):
                share += v_head[i, j, c] * background[c]
            v_final_t[i, j] += share
