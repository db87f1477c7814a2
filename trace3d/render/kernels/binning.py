"""Binning splats to 16x16 tiles: the depth order (a radix argsort equal to numpy's stable one), the
per-tile lists, the parallel row gather/scatter, and :class:`Binning`, the tile lists of one
projection that every kernel call reads.  (Part of the former ``render/kernels.py``, moved unchanged.)"""

from __future__ import annotations

import logging

import numpy as np
from numba import njit, prange

from ...errors import Trace3DError
from ..projection import Projected
from .tiles import TILE

log = logging.getLogger(__name__)

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
