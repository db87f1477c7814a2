"""The forward tile kernel: front-to-back blending of every tile's splats into the blended channels,
depths, final transmittance and median depth.  (Part of the former ``render/kernels.py``, moved
unchanged.)"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..projection import TRANSMITTANCE_MIN
from .tiles import (FASTMATH, TILE, TILE_PIXELS, _box_in_tile, _lane_alpha, _scaled_add, _tile_bounds, first_values,
                    splat_geometry)

# field offsets in the forward kernel's flat tile buffer (compile-time constants: the vectoriser
# must see the distances between fields)
# must see the distances between fields)
F_OPEN = np.uint64(1 * TILE_PIXELS)
F_Z = np.uint64(2 * TILE_PIXELS)
F_Z2 = np.uint64(3 * TILE_PIXELS)
F_MED = np.uint64(4 * TILE_PIXELS)
F_REF = np.uint64(5 * TILE_PIXELS)
F_LAST = np.uint64(6 * TILE_PIXELS)
F_MAT = np.uint64(7 * TILE_PIXELS)
F_RA = np.uint64(8 * TILE_PIXELS)
F_RZ = np.uint64(9 * TILE_PIXELS)
F_RW = np.uint64(10 * TILE_PIXELS)
F_ACC = np.uint64(11 * TILE_PIXELS)  # then one plane per channel (at least 8)
F_ACC1 = np.uint64(12 * TILE_PIXELS)
F_ACC2 = np.uint64(13 * TILE_PIXELS)
F_ACC3 = np.uint64(14 * TILE_PIXELS)
F_ACC4 = np.uint64(15 * TILE_PIXELS)
F_ACC5 = np.uint64(16 * TILE_PIXELS)
F_ACC6 = np.uint64(17 * TILE_PIXELS)
F_ACC7 = np.uint64(18 * TILE_PIXELS)


@njit(parallel=True, cache=True, fastmath=FASTMATH)
def forward_kernel(egeom, ebox, lists, vals, offsets, width, height, tiles_x, near, split, background, fold):
    """Front-to-back blending of every tile.

    Per (splat, tile) both passes run over all 16 lanes of every tile row of the footprint box, one
    loop each without branches, so that they vectorise and the rows overlap in the pipeline: pass 1
    evaluates alpha and depth (alpha 0 outside the box), pass 2 blends the lanes that are still open
    (pixels are independent for a fixed splat; two loops per row instead gave the same values, slower).  All
    tile state lives in one flat float32 buffer indexed with unsigned integers at constant field
    offsets: with one base pointer and no negative-index wrap-around the compiler can prove that
    lanes never alias.  List positions are stored tile-relative (exact in float32 below 2^24; the
    binning refuses longer tile lists).  The first 8 channels are accumulated inside pass 2 at fixed
    plane offsets (vectorised); further channels follow, one loop over the same lanes per channel
    (lanes that did not blend add w = 0).

    Args:
        egeom: [E, 16] float32 geometry per tile-list entry (``geom`` gathered by ``lists``);
        ebox: [E, 4] int32 footprint boxes per entry; lists: [E] int32 splat of each entry;
        vals: [N, K] float32; offsets: [tiles + 1] int64.
        split: the channels [:split] go to ``head``, the others to ``tail``; background [split]
            float32, blended into ``head`` with the final transmittance when ``fold`` (as the
            caller's torch line ``acc + final_t * background`` would, in its order).
    Returns:
        head [H, W, split], tail [H, W, K - split] (the blended channels), acc_z [H, W] (sum w z),
        acc_z2 [H, W] (sum w (z - z_ref)^2 with z_ref the depth of the pixel's first blended splat,
        which keeps the distortion well conditioned),
        final_t [H, W], median_z [H, W], depth_ref [H, W] (z_ref), last [H, W] int32 (list
        position + 1 of the last blended splat, 0 if none), median_at [H, W] int32 (list position
        of the median splat, -1 if none), pairs [tiles] int64 (pixel-splat pairs evaluated).
    """
    k_ch = vals.shape[1]
    n_tiles = offsets.shape[0] - 1
    head = np.zeros((height, width, split), np.float32)
    tail = np.zeros((height, width, k_ch - split), np.float32)
    acc_z = np.zeros((height, width), np.float32)
    acc_z2 = np.zeros((height, width), np.float32)
    final_t = np.ones((height, width), np.float32)
    median_z = np.zeros((height, width), np.float32)
    depth_ref = np.zeros((height, width), np.float32)
    last = np.zeros((height, width), np.int32)
    median_at = np.full((height, width), -1, np.int32)
    pairs = np.zeros(n_tiles, np.int64)
    t_min = np.float32(TRANSMITTANCE_MIN)
    near32 = np.float32(near)
    zero = np.float32(0.0)
    one = np.float32(1.0)
    half = np.float32(0.5)
    tp = TILE_PIXELS
    # field offsets in the flat tile buffer: transmittance, open flag, sum w z, sum w dz^2,
    # median z, reference z, last blended (tile-relative position + 1), median position
    # (tile-relative, -1 none), the current row's alpha, z, w (at the row's pixels), then K
    # channel planes
    for t in prange(n_tiles):
        start = offsets[t]
        end = offsets[t + 1]
        px0, py0, px1, py1 = _tile_bounds(t, tiles_x, width, height)
        if start == end:
            if fold:  # nothing blended: the transmittance stays 1
                for py in range(py0, py1):
                    for px in range(px0, px1):
                        for ch in range(split):
                            head[py, px, ch] = zero + one * background[ch]
            continue
        n_pix = (px1 - px0) * (py1 - py0)
        buf = np.zeros(F_ACC + max(k_ch, 8) * tp, np.float32)
        buf[:2 * tp] = 1.0  # transmittance 1, open
        buf[7 * tp:8 * tp] = -1.0  # no median yet
        n_done = 0
        visited = 0
        for j in range(start, end):
            g = lists[j]
            lx0, lx1, y0, y1 = _box_in_tile(ebox, j, px0, py0, px1, py1)
            a0, a1, a2, b0, b1, b2, d0, d1, d2, tw0, tw1, tw2, mx, my, opac = splat_geometry(egeom, j)
            visited += (y1 - y0) * TILE
            v0, v1, v2, v3, v4, v5, v6, v7 = first_values(vals, g)
            rel = np.float32(j - start)
            rel1 = np.float32(j - start + 1)
            # every lane of the footprint's rows in the tile, one loop per pass (the lanes are
            # independent for a fixed splat, so rows overlap in the pipeline)
            q0 = (y0 - py0) * TILE
            q1 = (y1 - py0) * TILE
            # pass 1: alpha (0 outside the footprint box) and depth of every lane
            for q in range(q0, q1):
                p, al, zz = _lane_alpha(q, px0, py0, lx0, lx1, a0, a1, a2, b0, b1, b2, d0, d1, d2, tw0, tw1, tw2,
                                        mx, my, opac, near32)
                buf[F_RA + p] = al
                buf[F_RZ + p] = zz
            # pass 2: blend every open lane (selects, no branches)
            finished = 0
            for q in range(q0, q1):
                p = np.uint64(q)
                alpha = buf[F_RA + p]
                z = buf[F_RZ + p]
                tr = buf[p]
                open_p = buf[F_OPEN + p]
                live = (alpha > zero) & (open_p > zero)
                t_next = tr * (one - alpha)
                stop = live & (t_next < t_min)
                blend = live & (t_next >= t_min)
                w = alpha * tr if blend else zero
                last_p = buf[F_LAST + p]
                mat_p = buf[F_MAT + p]
                med_p = buf[F_MED + p]
                ref_p = buf[F_REF + p]
                ref = z if blend & (last_p == zero) else ref_p
                dz = z - ref
                med = blend & (tr > half)
                buf[F_RW + p] = w
                # the first 8 channels at compile-time plane offsets (zero values past K)
                buf[F_ACC + p] += w * v0
                buf[F_ACC1 + p] += w * v1
                buf[F_ACC2 + p] += w * v2
                buf[F_ACC3 + p] += w * v3
                buf[F_ACC4 + p] += w * v4
                buf[F_ACC5 + p] += w * v5
                buf[F_ACC6 + p] += w * v6
                buf[F_ACC7 + p] += w * v7
                buf[p] = t_next if blend else tr
                buf[F_OPEN + p] = zero if stop else open_p
                buf[F_Z + p] += w * z
                buf[F_Z2 + p] += w * dz * dz
                buf[F_MED + p] = z if med else med_p
                buf[F_REF + p] = ref
                buf[F_LAST + p] = rel1 if blend else last_p
                buf[F_MAT + p] = rel if med else mat_p
                finished += np.int64(stop)
            n_done += finished
            # channels beyond the first 8 (planes after the 8 fixed ones): every lane of the rows
            # per channel (a lane that did not blend, inside or outside the image, has w = 0 and adds
            # nothing; the lanes outside the image are never read)
            for ch in range(8, k_ch):
                _scaled_add(buf, F_ACC + np.uint64(ch * TILE_PIXELS), F_RW, vals[g, ch], q0, q1)
            if n_done == n_pix:
                break
        pairs[t] = visited
        for py in range(py0, py1):
            for px in range(px0, px1):
                p = (py - py0) * TILE + (px - px0)
                t_final = buf[p]
                for ch in range(split):
                    a = buf[F_ACC + ch * tp + p]
                    head[py, px, ch] = a + t_final * background[ch] if fold else a
                for ch in range(split, k_ch):
                    tail[py, px, ch - split] = buf[F_ACC + ch * tp + p]
                final_t[py, px] = t_final
                acc_z[py, px] = buf[2 * tp + p]
                acc_z2[py, px] = buf[3 * tp + p]
                median_z[py, px] = buf[4 * tp + p]
                depth_ref[py, px] = buf[5 * tp + p]
                lp = np.int64(buf[6 * tp + p])
                last[py, px] = start + lp if lp > 0 else 0
                mp = np.int64(buf[7 * tp + p])
                median_at[py, px] = start + mp if mp >= 0 else -1
    return head, tail, acc_z, acc_z2, final_t, median_z, depth_ref, last, median_at, pairs
