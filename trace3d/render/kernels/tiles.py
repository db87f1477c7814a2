"""The tile scheme every CPU kernel shares: tile size, the kernel inputs' layout (``geom`` columns,
:func:`pack_geometry`), the fast-math flags, and the per-lane evaluation (:func:`eval_lane` and its
helpers) that forward, backward and trace call so that they make bit-identical decisions for every
pixel-splat pair.  (Part of the former ``render/kernels.py``, moved unchanged.)"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit
from torch import Tensor

from ..projection import ALPHA_MAX, ALPHA_MIN, Projected

TILE = 16
TILE_PIXELS = TILE * TILE

GEOM_COLS = 16
GEOM_GRAD_COLS = 15
LEVEL_SLACK = 1e-3  # added to the informational ln(255 o) column
# value-preserving fast-math flags only (no contraction, no reassociation, infinities allowed): the
# forward, backward and trace kernels must make bit-identical skip decisions for a pair
FASTMATH = {"nsz"}


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
