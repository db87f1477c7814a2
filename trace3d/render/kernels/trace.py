"""Gaussian Instance Tracing in the tile scheme: per splat and label, the sum of its blending weights
over the label's pixels (:func:`trace_kernel`), driven tile batch by tile batch with bounded memory
by :func:`trace_triplets`.  (Part of the former ``render/kernels.py``, moved unchanged.)"""

from __future__ import annotations

import numpy as np
from numba import njit, prange
from torch import Tensor

from ..projection import TRANSMITTANCE_MIN, Projected
from .binning import Binning
from .tiles import (FASTMATH, TILE, TILE_PIXELS, _box_in_tile, _geom_array, _lane_alpha, _tile_bounds, pack_geometry,
                    splat_geometry)

# trace_kernel's flat tile buffer: transmittance, open flag, the current row's alpha and weight
T_OPEN = np.uint64(1 * TILE_PIXELS)
T_RA = np.uint64(2 * TILE_PIXELS)
T_RW = np.uint64(3 * TILE_PIXELS)
T_LOC = np.uint64(4 * TILE_PIXELS)
T_COL = np.uint64(5 * TILE_PIXELS)


@njit(inline="always", fastmath=FASTMATH)
def _blend_footprint(buf, geometry, q0, q1, px0, py0, lx0, lx1, near32, t_min, unit_weight):
    """One splat over the lanes of its footprint's rows in a tile (``trace_kernel`` and
    ``pixel_weights_kernel``): every lane's alpha (0 outside the box) into the alpha plane, then the blend
    of the open lanes without branches, as in ``forward_kernel``: the weight plane gets alpha x T (1 with
    ``unit_weight``) where the lane blends, else 0; transmittance and open flag advance. Returns how many
    lanes closed (their transmittance fell below ``t_min``)."""
    a0, a1, a2, b0, b1, b2, d0, d1, d2, tw0, tw1, tw2, mx, my, opac = geometry
    zero = np.float32(0.0)
    one = np.float32(1.0)
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
        buf[T_RW + p] = (one if unit_weight else alpha * tr) if blend else zero
        buf[p] = t_next if blend else tr
        buf[T_OPEN + p] = zero if stop else open_p
        finished += np.int64(stop)
    return finished
# trace_kernel sums the weights of a tile with at most this many labels label by label in vector loops
TRACE_LABEL_PASSES = 4


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
            q0 = (y0 - py0) * TILE
            q1 = (y1 - py0) * TILE
            n_done += _blend_footprint(buf, splat_geometry(egeom, j), q0, q1, px0, py0, lx0, lx1, near32, t_min,
                                       count_pixels)
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



@njit(parallel=True, cache=True)
def pixel_weights_bounds(ebox, offsets, width, height, tiles_x):
    """[tiles] int64: at most how many entries :func:`pixel_weights_kernel` emits in each tile (the
    pixels of every tile-list entry's footprint box inside the tile: a lane outside the box has alpha 0)."""
    n_tiles = offsets.shape[0] - 1
    out = np.zeros(n_tiles, np.int64)
    for t in prange(n_tiles):
        px0, py0, px1, py1 = _tile_bounds(t, tiles_x, width, height)
        total = 0
        for j in range(offsets[t], offsets[t + 1]):
            lx0, lx1, y0, y1 = _box_in_tile(ebox, j, px0, py0, px1, py1)
            if lx1 > lx0 and y1 > y0:
                total += (lx1 - lx0) * (y1 - y0)
        out[t] = total
    return out


@njit(parallel=True, cache=True, fastmath=FASTMATH)
def pixel_weights_kernel(egeom, ebox, lists, offsets, width, height, tiles_x, near, first, count, tile_pixel,
                         tile_splat, tile_w, used):
    """Every pixel's blending weights in one pass over the tiles, the trace of one label per pixel
    without :func:`trace_kernel`'s dense [splats, labels] table per tile: the same lanes, alphas and
    transmittances (the same inline functions and float32 operations), each blended lane's weight
    emitted as it is blended.

    Tile t writes its entries from ``first[t]`` on (room for :func:`pixel_weights_bounds`'s bound):
    ``tile_pixel`` (y * W + x), ``tile_splat`` (the tile-list splat, ``lists[j]``) and ``tile_w``, in the
    order its splats are blended (front to back), ``used[t]`` of them; ``count`` [H * W] (zeros) gets
    each pixel's number of entries. :func:`pixel_weights_rows` then puts them in rows by pixel. The
    weights are :func:`trace_kernel`'s for the label map ``y * W + x`` (its table adds a pixel's one
    weight to 0, which gives the weight)."""
    n_tiles = offsets.shape[0] - 1
    t_min = np.float32(TRANSMITTANCE_MIN)
    near32 = np.float32(near)
    zero = np.float32(0.0)
    for t in prange(n_tiles):
        start = offsets[t]
        end = offsets[t + 1]
        if start == end:
            continue
        px0, py0, px1, py1 = _tile_bounds(t, tiles_x, width, height)
        n_pix = (px1 - px0) * (py1 - py0)
        buf = np.zeros(4 * TILE_PIXELS, np.float32)  # transmittance, open flag, alpha, weight planes
        buf[:2 * TILE_PIXELS] = 1.0
        n_done = 0
        k = first[t]
        for j in range(start, end):
            lx0, lx1, y0, y1 = _box_in_tile(ebox, j, px0, py0, px1, py1)
            q0 = (y0 - py0) * TILE
            q1 = (y1 - py0) * TILE
            n_done += _blend_footprint(buf, splat_geometry(egeom, j), q0, q1, px0, py0, lx0, lx1, near32, t_min,
                                       False)
            for q in range(q0, q1):
                w = buf[T_RW + np.uint64(q)]
                if w != zero:
                    px = px0 + q % TILE
                    py = py0 + q // TILE
                    if px < px1 and py < py1:
                        pix = py * width + px
                        tile_pixel[k] = pix
                        tile_splat[k] = lists[j]
                        tile_w[k] = w
                        k += 1
                        count[pix] += 1
            if n_done == n_pix:
                break
        used[t] = k - first[t]


@njit(parallel=True, cache=True)
def pixel_weights_rows(first, used, tile_pixel, tile_splat, tile_w, seen, cursor, out_gauss, out_w):
    """:func:`pixel_weights_kernel`'s entries into rows by pixel: ``cursor`` [H * W] holds each pixel's
    first row position (the row pointers) and advances; a pixel lies in one tile, whose entries come in
    blending order, so each row keeps that order. ``out_gauss`` gets the model's index ``seen[splat]``."""
    for t in prange(first.shape[0]):
        for e in range(first[t], first[t] + used[t]):
            p = tile_pixel[e]
            k = cursor[p]
            out_gauss[k] = seen[tile_splat[e]]
            out_w[k] = tile_w[e]
            cursor[p] = k + 1



# Upper bound on the (splat, label) slots one trace_kernel call preallocates (20 bytes each): tiles
# are processed in batches below it, so memory stays bounded however many labels a view has (a
# single tile over the bound is processed alone).
TRACE_BATCH_SLOTS = 1 << 22


def trace_triplets(proj: Projected, width: int, height: int, labels: Tensor, near: float = 0.01,
                   batch_slots: int = TRACE_BATCH_SLOTS, count_pixels: bool = False,
                   binning: Binning | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """GIT weights of one view as the kernel gives them: rows [E] int64 (splat), cols [E] int64
    (label), weights [E] float32, non-zero only, in tile order; a (row, col) may repeat across tiles.

    Tiles are traced in batches whose worst case (tile entries x distinct labels) stays under
    ``batch_slots``, so memory is bounded by one batch plus the non-zero output. ``binning``: the
    projection's tile lists when the caller has them (:class:`trace3d.render.core.FrozenView`).
    """
    if binning is None:
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
