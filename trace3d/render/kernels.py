"""CPU tile kernels (numba) for 2DGS blending, their hand-written backward, and GIT tracing.

This file is longer than the others (~1,500 lines) on purpose: the forward, backward and trace kernels
must make bit-identical decisions for every pixel-splat pair, so they sit beside the inline helpers
and the field constants they share (:func:`splat_geometry`, :func:`eval_lane`, the ``F_*`` offsets),
with the thin torch glue that packs their inputs at the end.

Kernel boundary (small on purpose, so that a CUDA back end can slot in behind it): per splat the
kernels read

    geom [N, 16] float32: A (3), B (3), D (3) with c = A + x B + y D; T_w (3); means2d (2);
                          opacity (1); ln(255 o) (1, informational: pads a row to 64 bytes)
    vals [N, K]  float32: per-splat constant channels (features, then the normal)

(rows gathered into tile-list order before the kernels run) and produce per pixel the blended
channels [H, W, K], sum w z, sum w (z - z_ref)^2, the final transmittance and the median depth.
The backward returns gradients with respect to ``geom``'s first 15 columns and ``vals``; autograd
carries them back through the torch projection to the 3D parameters.

Scheme (as in the CUDA rasterizers): splats are binned to 16x16 tiles (each tile's list in
front-to-back order of centre depth, ties by index), a tile's pixels are blended front to back,
splat by splat: for each row of the splat's footprint box inside the tile, pass 1 evaluates all
16 lanes of the row branch-free (vectorised, with :func:`exp_neg`), pass 2 blends the lanes inside
the box.  Forward, backward and trace share :func:`eval_lane`, so they make bit-identical skip
decisions.  The backward walks each tile's list
back to front, recovering the transmittance by division and keeping, per pixel, the running
"what comes after" dot product.  Tiles run in parallel (``prange``); gradients go to one buffer per
worker chunk (tiles are dealt round-robin to chunks), summed afterwards: race-free and
deterministic.  When nothing upstream of the geometry needs a gradient (lifting's frozen scene, GIT
through autograd), :func:`backward_values_kernel` does the same walk for the value gradients alone.
"""

from __future__ import annotations

import logging

import numba
import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from ..errors import Trace3DError
from .projection import ALPHA_MAX, ALPHA_MIN, TRANSMITTANCE_MIN, Projected

log = logging.getLogger(__name__)

TILE = 16
TILE_PIXELS = TILE * TILE
# field offsets in the forward kernel's flat tile buffer (compile-time constants: the vectoriser
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
# trace_kernel's flat tile buffer: transmittance, open flag, the current row's alpha and weight
T_OPEN = np.uint64(1 * TILE_PIXELS)
T_RA = np.uint64(2 * TILE_PIXELS)
T_RW = np.uint64(3 * TILE_PIXELS)
T_LOC = np.uint64(4 * TILE_PIXELS)
T_COL = np.uint64(5 * TILE_PIXELS)
# trace_kernel sums the weights of a tile with at most this many labels label by label in vector loops
TRACE_LABEL_PASSES = 4
GEOM_COLS = 16
GEOM_GRAD_COLS = 15
LEVEL_SLACK = 1e-3  # added to the informational ln(255 o) column
# value-preserving fast-math flags only (no contraction, no reassociation, infinities allowed): the
# forward, backward and trace kernels must make bit-identical skip decisions for a pair
FASTMATH = {"nsz"}


# ----------------------------------------------------------------------------------------------
# binning
# ----------------------------------------------------------------------------------------------


RADIX_BITS = 11  # three passes over the 32 key bits


@njit(cache=True)
def stable_argsort_f32(keys):
    """The permutation of ``np.argsort(keys, kind="stable")`` for float32 keys, by a least-significant-
    digit radix sort of their bits (three 11-bit passes, each stable, so ties keep their index order).

    The bits are mapped to unsigned integers in the floats' order: -0.0 is read as +0.0 (numpy
    compares them equal) and every NaN as one value above +inf (numpy sorts NaNs last, in index
    order)."""
    n = keys.shape[0]
    ukeys = np.empty(n, np.uint32)
    bits = keys.view(np.uint32)
    for i in range(n):
        b = bits[i]
        x = keys[i]
        if x != x:  # NaN
            b = np.uint32(0xFFFFFFFF)
        elif x == 0:  # +0.0 and -0.0
            b = np.uint32(0x80000000)
        elif b & np.uint32(0x80000000):  # negative: larger magnitude first
            b = ~b
        else:
            b = b | np.uint32(0x80000000)
        ukeys[i] = b
    size = 1 << RADIX_BITS
    mask = np.uint32(size - 1)
    passes = -(-32 // RADIX_BITS)
    # each pass's digit histogram does not depend on the order: all of them in one sweep, then the
    # start of each digit's run
    starts = np.zeros((passes, size + 1), np.int64)
    for i in range(n):
        for k in range(passes):
            starts[k, ((ukeys[i] >> np.uint32(k * RADIX_BITS)) & mask) + 1] += 1
    for k in range(passes):
        for d in range(size):
            starts[k, d + 1] += starts[k, d]
    order = np.arange(n)
    tmp = np.empty(n, np.int64)
    for k in range(passes):
        shift = np.uint32(k * RADIX_BITS)
        counts = starts[k]
        for i in range(n):
            g = order[i]
            d = (ukeys[g] >> shift) & mask
            tmp[counts[d]] = g
            counts[d] += 1
        order, tmp = tmp, order
    return order


@njit(cache=True)
def bin_tiles(boxes, order, tiles_x, tiles_y):
    """Tile lists.

    Args:
        boxes: [N, 4] int64 (x0, y0, x1, y1) half-open pixel boxes.
        order: [M] int64 splat indices to bin, front to back.
    Returns:
        offsets [tiles + 1] int64 and lists [offsets[-1]] int32: tile t holds
        lists[offsets[t]:offsets[t + 1]], front to back.
    """
    n_tiles = tiles_x * tiles_y
    counts = np.zeros(n_tiles + 1, np.int64)
    for i in range(order.shape[0]):
        g = order[i]
        tx0 = boxes[g, 0] // TILE
        ty0 = boxes[g, 1] // TILE
        tx1 = (boxes[g, 2] - 1) // TILE
        ty1 = (boxes[g, 3] - 1) // TILE
        for ty in range(ty0, ty1 + 1):
            for tx in range(tx0, tx1 + 1):
                counts[ty * tiles_x + tx + 1] += 1
    offsets = np.cumsum(counts)
    fill = offsets[:-1].copy()
    lists = np.empty(offsets[-1], np.int32)
    for i in range(order.shape[0]):
        g = order[i]
        tx0 = boxes[g, 0] // TILE
        ty0 = boxes[g, 1] // TILE
        tx1 = (boxes[g, 2] - 1) // TILE
        ty1 = (boxes[g, 3] - 1) // TILE
        for ty in range(ty0, ty1 + 1):
            for tx in range(tx0, tx1 + 1):
                t = ty * tiles_x + tx
                lists[fill[t]] = g
                fill[t] += 1
    return offsets, lists


# ----------------------------------------------------------------------------------------------
# per-lane evaluation (shared by every kernel so that they make identical decisions)
# ----------------------------------------------------------------------------------------------


@njit(inline="always")
def exp_taylor8(y):
    """e^y by its degree-8 Taylor series in Horner form, float32 (relative error < 2e-8 for |y| <= ln 2;
    inlined, so it takes the caller's fastmath flags)."""
    p = np.float32(1.0 / 40320.0)
    p = p * y + np.float32(1.0 / 5040.0)
    p = p * y + np.float32(1.0 / 720.0)
    p = p * y + np.float32(1.0 / 120.0)
    p = p * y + np.float32(1.0 / 24.0)
    p = p * y + np.float32(1.0 / 6.0)
    p = p * y + np.float32(0.5)
    p = p * y + np.float32(1.0)
    return p * y + np.float32(1.0)


@njit(inline="always", fastmath=FASTMATH)
def exp_neg(s):
    """exp(-s) for s >= 0 in float32 from basic operations only (so that loops vectorise without
    SVML): s = (n + f) ln 2, 2^-f by a degree-8 Taylor series of exp on (-ln 2, 0], 2^-n by
    selects.  Relative error about 1e-6 (from rounding s log2 e); exp(-20) and below read as
    exp(-20), far under the 1/255 alpha threshold."""
    s = min(s, np.float32(20.0))
    t = s * np.float32(1.4426950408889634)
    n = np.int32(t)
    y = (t - np.float32(n)) * np.float32(-0.6931471805599453)
    p = exp_taylor8(y)
    p = p * (np.float32(0.5) if (n & 1) else np.float32(1.0))
    p = p * (np.float32(0.25) if (n & 2) else np.float32(1.0))
    p = p * (np.float32(1.0 / 16.0) if (n & 4) else np.float32(1.0))
    p = p * (np.float32(1.0 / 256.0) if (n & 8) else np.float32(1.0))
    p = p * (np.float32(1.0 / 65536.0) if (n & 16) else np.float32(1.0))
    return p


@njit(inline="always")
def _tile_bounds(t, tiles_x, width, height):
    """Tile ``t``'s pixel bounds: its first column and row, and its end column and row clipped to the image."""
    px0 = (t % tiles_x) * TILE
    py0 = (t // tiles_x) * TILE
    return px0, py0, min(px0 + TILE, width), min(py0 + TILE, height)


@njit(inline="always")
def _box_in_tile(ebox, j, px0, py0, px1, py1):
    """Tile-list entry ``j``'s footprint box inside the tile [px0, px1) x [py0, py1): its columns
    relative to the tile [lx0, lx1) and its image rows [y0, y1) (empty ranges where it misses)."""
    return max(ebox[j, 0], px0) - px0, min(ebox[j, 2], px1) - px0, max(ebox[j, 1], py0), min(ebox[j, 3], py1)


@njit(inline="always")
def splat_geometry(egeom, j):
    """The 15 geometry fields of tile-list entry ``j``: A (3), B (3), D (3), T_w (3), means2d (2), opacity."""
    return (egeom[j, 0], egeom[j, 1], egeom[j, 2], egeom[j, 3], egeom[j, 4], egeom[j, 5], egeom[j, 6], egeom[j, 7],
            egeom[j, 8], egeom[j, 9], egeom[j, 10], egeom[j, 11], egeom[j, 12], egeom[j, 13], egeom[j, 14])


@njit(inline="always")
def first_values(vals, g):
    """Splat ``g``'s first 8 channel values, zero past K (the kernels' fixed channel planes)."""
    k = vals.shape[1]
    z = np.float32(0.0)
    return (vals[g, 0] if k > 0 else z, vals[g, 1] if k > 1 else z, vals[g, 2] if k > 2 else z,
            vals[g, 3] if k > 3 else z, vals[g, 4] if k > 4 else z, vals[g, 5] if k > 5 else z,
            vals[g, 6] if k > 6 else z, vals[g, 7] if k > 7 else z)


@njit(inline="always", fastmath=FASTMATH)
def _scaled_add(buf, dst, src, scale, q0, q1):
    """buf[dst + q] += buf[src + q] * scale for the lanes q in [q0, q1) of two planes (one vector loop;
    the kernels' channels past the first 8)."""
    for q in range(q0, q1):
        p = np.uint64(q)
        buf[dst + p] += buf[src + p] * scale


@njit(inline="always", fastmath=FASTMATH)
def eval_lane(x, e0, e1, e2, b0, b1, b2, mx, dy2, opac, tw0, tw1, tw2, near32):
    """One pixel-splat pair: (alpha or 0 when skipped, depth z, u, v, 1 / c2, disk term used, exp(-sigma)).

    c = (e + x b) with e = A + y D; u, v = c0 / c2, c1 / c2; sigma = min(1/2 (u^2 + v^2),
    |pixel - centre|^2); z is the plane intersection's depth where the disk term wins and the
    centre's otherwise (2DGS); alpha = min(0.99, o exp(-sigma)), skipped below 1/255, behind
    ``near`` or for a ray parallel to the plane."""
    c0 = e0 + b0 * x
    c1 = e1 + b1 * x
    c2 = e2 + b2 * x
    nonparallel = c2 != np.float32(0.0)
    inv_c2 = np.float32(1.0) / (c2 if nonparallel else np.float32(1.0))
    u = c0 * inv_c2
    v = c1 * inv_c2
    s_disk = np.float32(0.5) * (u * u + v * v)
    dx = x - mx
    s_filt = dx * dx + dy2
    use_disk = s_disk <= s_filt
    sigma = s_disk if use_disk else s_filt
    z = (u * tw0 + v * tw1 + tw2) if use_disk else tw2
    gauss = exp_neg(sigma)
    alpha = min(opac * gauss, np.float32(ALPHA_MAX))
    keep = nonparallel & (alpha >= np.float32(ALPHA_MIN)) & (z > near32)
    return (alpha if keep else np.float32(0.0)), z, u, v, inv_c2, use_disk, gauss


# ----------------------------------------------------------------------------------------------
# forward
# ----------------------------------------------------------------------------------------------


@njit(parallel=True, cache=True, fastmath=FASTMATH)
def forward_kernel(egeom, ebox, lists, vals, offsets, width, height, tiles_x, near, split, background, fold):
    """Front-to-back blending of every tile.

    Per (splat, tile) both passes run over all 16 lanes of every tile row of the footprint box, one
    loop each without branches, so that they vectorise and the rows overlap in the pipeline: pass 1
    evaluates alpha and depth (alpha 0 outside the box), pass 2 blends the lanes that are still open
    (pixels are independent for a fixed splat; before 2026-11-26 each row had its own two loops, 1.34x
    slower in a fit at either size, the same values).  All
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


# ----------------------------------------------------------------------------------------------
# backward
# ----------------------------------------------------------------------------------------------


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
def _lane_position(q, px0, py0, my):
    """Lane ``q`` of a tile (row q // 16, column q % 16): its buffer index, column, pixel centre x, y and
    y - my."""
    i = q & (TILE - 1)
    y = np.float32(py0 + (q >> 4)) + np.float32(0.5)
    return np.uint64(q), i, np.float32(px0 + i) + np.float32(0.5), y, y - my


@njit(inline="always", fastmath=FASTMATH)
def _lane_alpha(q, px0, py0, lx0, lx1, a0, a1, a2, b0, b1, b2, d0, d1, d2, tw0, tw1, tw2, mx, my, opac, near32):
    """Lane ``q`` of a splat's footprint rows in a tile: its buffer index, alpha (0 outside the box's
    columns [lx0, lx1)) and depth (the forward and trace kernels' first pass)."""
    p, i, x, y, dy = _lane_position(q, px0, py0, my)
    al, zz, _, _, _, _, _ = eval_lane(x, a0 + d0 * y, a1 + d1 * y, a2 + d2 * y, b0, b1, b2, mx, dy * dy, opac, tw0,
                                     tw1, tw2, near32)
    return p, (al if (i >= lx0) & (i < lx1) else np.float32(0.0)), zz


@njit(inline="always", fastmath=FASTMATH)
def _lane_unblend(buf, trans_plane, last_plane, p, i, lx0, lx1, jrel, alpha):
    """The backward's step back past a splat at one lane: whether the pair was blended (inside the box's
    columns [lx0, lx1), alpha not 0, list position ``jrel`` before the pixel's last blended one) and the
    pixel's transmittance before the splat, recovered from the one after it by the same division in
    every backward: (blended, t_before, 1 / (1 - alpha))."""
    live = (i >= lx0) & (i < lx1) & (alpha != np.float32(0.0)) & (jrel < buf[last_plane + p])
    inv_one_minus = np.float32(1.0) / (np.float32(1.0) - alpha)
    return live, buf[trans_plane + p] * inv_one_minus, inv_one_minus


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


@njit(inline="always")
def _live_rows(buf, last_plane, rows_live, r0, r1, lx0, lx1, jrel):
    """The backward's rows of a splat's footprint in a tile where it was blended into some pixel (tile
    list position ``jrel`` before the pixel's last blended one, read from the plane at ``last_plane``):
    marks each row of [r0, r1) in ``rows_live`` and returns the first and last such row (-1, -1: none)."""
    r_first = -1
    r_last = -1
    for r in range(r0, r1):
        row = np.uint64(r * TILE)
        live_row = False
        for i in range(lx0, lx1):
            if jrel < buf[last_plane + row + np.uint64(i)]:
                live_row = True
                break
        rows_live[r] = live_row
        if live_row:
            r_last = r
            if r_first < 0:
                r_first = r
    return r_first, r_last


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
    sums lane by lane in ascending order: the order of the scalar loop this replaced (2026-11-26), so
    the sums are the same bit for bit (a lane the splat did not blend adds zero terms, which leave a
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


# ----------------------------------------------------------------------------------------------
# tracing (GIT)
# ----------------------------------------------------------------------------------------------


@njit(parallel=True, cache=True, fastmath=FASTMATH)
def trace_label_counts(offsets, width, height, tiles_x, labels):
    """[tiles] number of distinct non-negative labels in each 16x16 tile (0 for tiles without splats)."""
    n_tiles = offsets.shape[0] - 1
    n_local = np.zeros(n_tiles, np.int64)
    for t in prange(n_tiles):
        if offsets[t + 1] == offsets[t]:
            continue
        px0, py0, px1, py1 = _tile_bounds(t, tiles_x, width, height)
        seen = np.zeros(TILE_PIXELS, np.int64)
        count = 0
        for py in range(py0, py1):
            for px in range(px0, px1):
                lab = labels[py, px]
                if lab < 0:
                    continue
                new = True
                for i in range(count):
                    if seen[i] == lab:
                        new = False
                        break
                if new:
                    seen[count] = lab
                    count += 1
        n_local[t] = count
    return n_local


@njit(parallel=True, cache=True, fastmath=FASTMATH)
def trace_kernel(egeom, ebox, lists, offsets, width, height, tiles_x, near, labels, tiles, n_local, count_pixels):
    """Per-tile sums of blending weights by label, as sparse triplets (a forward pass that
    accumulates w_k(pixel) into (k, label(pixel)) instead of blending features).

    Args:
        as :func:`forward_kernel`; labels: [H, W] int64 (negative = ignored); tiles: [B] int64, the
        tiles to process (the caller batches them to bound memory); n_local: [tiles] distinct
        labels per tile (:func:`trace_label_counts`); count_pixels: add 1 per pixel a splat
        contributes to instead of its blending weight (the official Trace3D code's counting).
    Returns:
        rows [E'] int64 (splat), cols [E'] int64 (label), weights [E'] float32, non-zero only; the
        same (row, col) may repeat across tiles (sum them).
    """
    n_batch = tiles.shape[0]
    t_min = np.float32(TRANSMITTANCE_MIN)
    near32 = np.float32(near)
    zero = np.float32(0.0)
    one = np.float32(1.0)
    cap = np.zeros(n_batch + 1, np.int64)
    for b in range(n_batch):
        t = tiles[b]
        cap[b + 1] = cap[b] + (offsets[t + 1] - offsets[t]) * n_local[t]
    rows = np.empty(cap[n_batch], np.int64)
    cols = np.empty(cap[n_batch], np.int64)
    weights = np.empty(cap[n_batch], np.float32)
    used = np.zeros(n_batch, np.int64)
    for b in prange(n_batch):
        t = tiles[b]
        start = offsets[t]
        end = offsets[t + 1]
        n_lab = n_local[t]
        if start == end or n_lab == 0:
            continue
        px0, py0, px1, py1 = _tile_bounds(t, tiles_x, width, height)
        n_pix = (px1 - px0) * (py1 - py0)
        local_of = np.full(TILE_PIXELS, -1, np.int64)
        label_of = np.zeros(n_lab, np.int64)
        count = 0
        for py in range(py0, py1):
            for px in range(px0, px1):
                lab = labels[py, px]
                if lab < 0:
                    continue
                found = -1
                for i in range(count):
                    if label_of[i] == lab:
                        found = i
                        break
                if found < 0:
                    label_of[count] = lab
                    found = count
                    count += 1
                local_of[(py - py0) * TILE + (px - px0)] = found
        table = np.zeros((end - start, n_lab), np.float32)
        # flat tile buffer: transmittance, open flag, the current row's alpha and weight planes, the
        # lanes' local labels (-1 none) as float32
        buf = np.zeros(5 * TILE_PIXELS + TILE, np.float32)
        buf[:2 * TILE_PIXELS] = 1.0
        for q in range(TILE_PIXELS):
            buf[T_LOC + np.uint64(q)] = np.float32(local_of[q])
        n_done = 0
        n_used = start
        for j in range(start, end):
            n_used = j + 1
            lx0, lx1, y0, y1 = _box_in_tile(ebox, j, px0, py0, px1, py1)
            a0, a1, a2, b0, b1, b2, d0, d1, d2, tw0, tw1, tw2, mx, my, opac = splat_geometry(egeom, j)
            q0 = (y0 - py0) * TILE
            q1 = (y1 - py0) * TILE
            # every lane of the footprint's rows in one loop per pass, as in forward_kernel: alpha (0
            # outside the box), then the blend of the open lanes without branches
            for q in range(q0, q1):
                p, al, _ = _lane_alpha(q, px0, py0, lx0, lx1, a0, a1, a2, b0, b1, b2, d0, d1, d2, tw0, tw1, tw2,
                                       mx, my, opac, near32)
                buf[T_RA + p] = al
            finished = 0
            for q in range(q0, q1):
                p = np.uint64(q)
                alpha = buf[T_RA + p]
                tr = buf[p]
                open_p = buf[T_OPEN + p]
                live = (alpha > zero) & (open_p > zero)
                t_next = tr * (one - alpha)
                stop = live & (t_next < t_min)
                blend = live & (t_next >= t_min)
                buf[T_RW + p] = (one if count_pixels else alpha * tr) if blend else zero
                buf[p] = t_next if blend else tr
                buf[T_OPEN + p] = zero if stop else open_p
                finished += np.int64(stop)
            n_done += finished
            # the blended lanes' weights into their labels' sums (w = 0 where not blended)
            if n_lab <= TRACE_LABEL_PASSES:
                # one pass per label: per-column sums over the rows (a vector loop), then the 16
                # columns in order (most tiles hold one to three labels)
                for loc in range(n_lab):
                    lf = np.float32(loc)
                    for i in range(TILE):
                        buf[T_COL + np.uint64(i)] = zero
                    for r in range(y0 - py0, y1 - py0):
                        rb = np.uint64(r * TILE)
                        for i in range(TILE):
                            p = rb + np.uint64(i)
                            buf[T_COL + np.uint64(i)] += buf[T_RW + p] if buf[T_LOC + p] == lf else zero
                    for i in range(8):  # the columns' sum as a tree (a chain of 16 adds was the cost)
                        buf[T_COL + np.uint64(i)] += buf[T_COL + np.uint64(i + 8)]
                    for i in range(4):
                        buf[T_COL + np.uint64(i)] += buf[T_COL + np.uint64(i + 4)]
                    s01 = buf[T_COL] + buf[T_COL + np.uint64(2)]
                    s23 = buf[T_COL + np.uint64(1)] + buf[T_COL + np.uint64(3)]
                    table[j - start, loc] += s01 + s23
            else:  # many labels (one per pixel: pixel_weights): each blended lane into its label
                for q in range(q0, q1):
                    w = buf[T_RW + np.uint64(q)]
                    if w != zero:
                        loc = local_of[q]
                        if loc >= 0:
                            table[j - start, loc] += w
            if n_done == n_pix:
                break
        base = cap[b]
        e = 0
        for j in range(start, n_used):
            g = lists[j]
            for i in range(n_lab):
                wv = table[j - start, i]
                if wv != 0:
                    rows[base + e] = g
                    cols[base + e] = label_of[i]
                    weights[base + e] = wv
                    e += 1
        used[b] = e
    total = 0
    for b in range(n_batch):
        total += used[b]
    out_rows = np.empty(total, np.int64)
    out_cols = np.empty(total, np.int64)
    out_w = np.empty(total, np.float32)
    k = 0
    for b in range(n_batch):
        for e in range(used[b]):
            out_rows[k] = rows[cap[b] + e]
            out_cols[k] = cols[cap[b] + e]
            out_w[k] = weights[cap[b] + e]
            k += 1
    return out_rows, out_cols, out_w


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


# ----------------------------------------------------------------------------------------------
# torch glue
# ----------------------------------------------------------------------------------------------


@njit(parallel=True, cache=True)
def copy_rows(dsts, srcs, rows, scatter):
    """For every pair k of 2D arrays: dsts[k][j] = srcs[k][rows[j]] (gather), or with ``scatter``
    dsts[k][rows[j]] = srcs[k][j] (values cast to the destination's dtype); one parallel pass over the
    rows per pair.  (One pass over the rows for all pairs at once was 1.7x slower on arrays that are not
    in the cache, as in a fit: it reads and writes as many streams at once as there are pairs.)"""
    for k in range(len(dsts)):
        dst = dsts[k]
        src = srcs[k]
        width = dst.shape[1]
        for j in prange(rows.shape[0]):
            i = np.int64(rows[j])
            jj = np.int64(j)
            d = i if scatter else jj
            s_ = jj if scatter else i
            for c in range(width):
                dst[d, c] = src[s_, c]


def gather_rows_as(src: np.ndarray, rows: np.ndarray, dtype) -> np.ndarray:
    """``np.ascontiguousarray(src[rows].astype(dtype))`` for a 2D array, as one parallel pass (numpy's
    fancy indexing is single-threaded; the tile entries of a 504x378 view are a few hundred thousand)."""
    out = np.empty((rows.shape[0], src.shape[1]), dtype)
    copy_rows((out,), (np.ascontiguousarray(src),), np.ascontiguousarray(rows, dtype=np.int64), False)
    return out


class Binning:
    """Tile lists of one projection (numpy, CPU)."""

    def __init__(self, proj: Projected, width: int, height: int):
        self.width = int(width)
        self.height = int(height)
        self.tiles_x = (self.width + TILE - 1) // TILE
        self.tiles_y = (self.height + TILE - 1) // TILE
        self.boxes = np.ascontiguousarray(proj.boxes, dtype=np.int64)
        visible = proj.visible.cpu().numpy()
        idx = np.nonzero(visible)[0]
        depth = proj.depths.detach().cpu().numpy()[idx]
        # front to back, ties in index order: the radix sort gives numpy's stable order ~8x faster
        rank = stable_argsort_f32(depth) if depth.dtype == np.float32 else np.argsort(depth, kind="stable")
        self.order = idx[rank].astype(np.int64)
        self.offsets, self.lists = bin_tiles(self.boxes, self.order, self.tiles_x, self.tiles_y)
        self.entry_boxes = gather_rows_as(self.boxes, self.lists, np.int32)  # [E, 4]
        longest = int(np.diff(self.offsets).max()) if self.offsets.size > 1 else 0
        if longest >= 1 << 24:
            raise Trace3DError(f"render: a 16x16 tile holds {longest} splats; the CPU kernels support "
                               f"fewer than {1 << 24} per tile.")
        log.debug("binned %d visible splats into %d tile entries over %dx%d tiles", idx.size,
                  self.lists.size, self.tiles_x, self.tiles_y)
        self.pairs = None  # [tiles] pixel-splat pairs evaluated by the last forward

    def entry_geometry(self, geom: np.ndarray) -> np.ndarray:
        """[E, 16] ``geom`` rows in tile-list order (contiguous reads in the kernels)."""
        return gather_rows_as(geom, self.lists, geom.dtype)


def pack_geometry(proj: Projected) -> Tensor:
    """[N, 15] differentiable kernel inputs: coeffs (9), T_w (3), means2d (2), opacity (1)."""
    return torch.cat([proj.coeffs, proj.ray_transforms[:, 2], proj.means2d, proj.opacities[:, None]], dim=1)


def _geom_array(geom15: Tensor) -> np.ndarray:
    g = geom15.detach().to("cpu", torch.float32).numpy()
    out = np.empty((g.shape[0], GEOM_COLS), np.float32)
    out[:, :GEOM_GRAD_COLS] = g
    with np.errstate(divide="ignore"):
        out[:, 15] = np.log(np.maximum(g[:, 14].astype(np.float64), 1e-30) * 255.0) + LEVEL_SLACK
    return out


def _f32(t: Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().to("cpu", torch.float32).numpy())


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


class _Rasterize(torch.autograd.Function):
    @staticmethod
    def forward(ctx, geom15: Tensor, vals: Tensor, binning: Binning, near: float, split: int,
                background: Tensor | None, value_grad_cols: int | None = None):
        geom = _geom_array(geom15)
        vals_np = _f32(vals)
        egeom = binning.entry_geometry(geom)
        # the blended values as two outputs, columns [:split] and [split:] (features and normals), so
        # that the backward gets their gradients without two zero-filled slice gradients and their sum;
        # background: blended into the first part in the kernel (None: the caller blends it)
        ctx.split = split
        ctx.background = (np.zeros(split, np.float32) if background is None
                          else np.ascontiguousarray(background.detach().numpy()))
        ctx.fold = background is not None
        ctx.value_grad_cols = value_grad_cols  # with frozen geometry: gradients for vals[:, :value_grad_cols]
        head, tail, acc_z, acc_z2, final_t, median_z, depth_ref, last, median_at, pairs = forward_kernel(
            egeom, binning.entry_boxes, binning.lists, vals_np, binning.offsets, binning.width,
            binning.height, binning.tiles_x, float(near), split, ctx.background, ctx.fold)
        binning.pairs = pairs
        ctx.binning = binning
        ctx.near = near
        ctx.in_dtype = (geom15.dtype, vals.dtype, geom15.device)
        ctx.saved = (egeom, vals_np, final_t, depth_ref, last, median_at)
        dev, dt = vals.device, vals.dtype
        outs = [torch.from_numpy(a).to(device=dev, dtype=dt) for a in (head, tail, acc_z, acc_z2, final_t, median_z)]
        ref = torch.from_numpy(depth_ref).to(device=dev, dtype=dt)
        ctx.mark_non_differentiable(ref)
        return tuple(outs) + (ref,)

    @staticmethod
    def backward(ctx, v_head, v_tail, v_z, v_z2, v_final_t, v_median, v_ref):
        b = ctx.binning
        egeom, vals_np, final_t, depth_ref, last, median_at = ctx.saved
        h, w, k = b.height, b.width, vals_np.shape[1]

        def arr(t, shape):
            if t is None:
                return np.zeros(shape, np.float32)
            return np.ascontiguousarray(t.detach().to("cpu", torch.float32).numpy())

        g_head = arr(v_head, (h, w, ctx.split))
        n_chunks = max(1, numba.get_num_threads())
        gdt, vdt, dev = ctx.in_dtype
        if not ctx.needs_input_grad[0]:
            # frozen geometry: the value gradients alone, for the columns that need them (the depth,
            # transmittance and median outputs do not depend on the values)
            n_cols = k if ctx.value_grad_cols is None else ctx.value_grad_cols
            v_tail_np = arr(v_tail, (h, w, k - ctx.split)) if n_cols > ctx.split else np.zeros((h, w, 0), np.float32)
            grads = backward_values_kernel(egeom, b.entry_boxes, b.lists, vals_np.shape[0], b.offsets, b.width,
                                           b.height, b.tiles_x, float(ctx.near), n_chunks, final_t, last, g_head,
                                           v_tail_np, n_cols)
            g_vals = torch.from_numpy(sum_value_chunks(grads, k)).to(device=dev, dtype=vdt)
            return None, g_vals, None, None, None, None, None
        v_t = np.array(arr(v_final_t, (h, w)))  # a copy: the background's share is added in place
        if ctx.fold:
            fold_background_grad(g_head, v_t, ctx.background)
        grads = backward_kernel(egeom, b.entry_boxes, b.lists, vals_np, b.offsets, b.width, b.height, b.tiles_x,
                                float(ctx.near), n_chunks, final_t, depth_ref, last, median_at,
                                g_head, arr(v_tail, (h, w, k - ctx.split)), arr(v_z, (h, w)), arr(v_z2, (h, w)),
                                v_t, arr(v_median, (h, w)))
        g_geom_np, g_vals_np = sum_chunks(grads)
        g_geom = torch.from_numpy(g_geom_np).to(device=dev, dtype=gdt)
        g_vals = torch.from_numpy(g_vals_np).to(device=dev, dtype=vdt)
        return g_geom, g_vals, None, None, None, None, None


def rasterize(proj: Projected, features: Tensor, width: int, height: int, background: Tensor,
              near: float = 0.01, binning: Binning | None = None) -> dict[str, Tensor]:
    """Tile-kernel render of projected splats (same outputs as ``render_reference``).

    Args:
        proj: projection; features: [N, C]; background: [C].
    Returns:
        dict with features [H, W, C], alpha, depth, depth2 (sum w (z - depth_ref)^2), depth_ref,
        median_depth [H, W], normal [H, W, 3].
    """
    if binning is None:
        binning = Binning(proj, width, height)
    c = features.shape[1]
    vals = torch.cat([features, proj.normals.to(features.dtype)], dim=1)
    # a fixed background is blended inside: the same float32 operations as the torch line below, in
    # its order (tested) for three channels; for other channel counts only a zero background (then
    # every term is exact: the order cannot matter). A background to differentiate takes the torch line.
    fold = (vals.dtype == torch.float32 and background.dtype == torch.float32 and background.device.type == "cpu"
            and not background.requires_grad and (c == 3 or not bool(background.any())))
    feats, normal, acc_z, acc_z2, final_t, median_z, depth_ref = _Rasterize.apply(
        pack_geometry(proj), vals, binning, near, c, background.contiguous() if fold else None,
        None if proj.normals.requires_grad else c)
    return {
        "features": feats if fold else feats + final_t[..., None] * background,
        "alpha": 1.0 - final_t,
        "depth": acc_z,
        "depth2": acc_z2,
        "depth_ref": depth_ref,
        "normal": normal,
        "median_depth": median_z,
        "final_t": final_t,
        "pairs": binning.pairs,
    }


# Upper bound on the (splat, label) slots one trace_kernel call preallocates (20 bytes each): tiles
# are processed in batches below it, so memory stays bounded however many labels a view has (a
# single tile over the bound is processed alone).
TRACE_BATCH_SLOTS = 1 << 22


def trace_triplets(proj: Projected, width: int, height: int, labels: Tensor, near: float = 0.01,
                   batch_slots: int = TRACE_BATCH_SLOTS, count_pixels: bool = False
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """GIT weights of one view as the kernel gives them: rows [E] int64 (splat), cols [E] int64
    (label), weights [E] float32, non-zero only, in tile order; a (row, col) may repeat across tiles.

    Tiles are traced in batches whose worst case (tile entries x distinct labels) stays under
    ``batch_slots``, so memory is bounded by one batch plus the non-zero output.
    """
    binning = Binning(proj, width, height)
    geom = _geom_array(pack_geometry(proj))
    lab = np.ascontiguousarray(labels.detach().cpu().numpy().astype(np.int64))
    n_local = trace_label_counts(binning.offsets, binning.width, binning.height, binning.tiles_x, lab)
    need = np.diff(binning.offsets) * n_local
    egeom = binning.entry_geometry(geom)
    parts = []
    tiles = np.nonzero(need)[0]
    start = 0
    while start < tiles.size:
        cum = np.cumsum(need[tiles[start:]])
        stop = start + max(1, int(np.searchsorted(cum, batch_slots, side="right")))
        batch = np.ascontiguousarray(tiles[start:stop], dtype=np.int64)
        parts.append(trace_kernel(egeom, binning.entry_boxes, binning.lists, binning.offsets, binning.width,
                                  binning.height, binning.tiles_x, float(near), lab, batch, n_local,
                                  bool(count_pixels)))
        start = stop
    if len(parts) == 1:
        return parts[0]
    if parts:
        return (np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]),
                np.concatenate([p[2] for p in parts]))
    return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32)
