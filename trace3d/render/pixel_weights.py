"""Per-pixel blending weights of a frozen scene: a feature render as a sparse matrix product.

With the geometry frozen, the feature rendered at pixel x is linear in the per-Gaussian features:

    F(x) = sum_k w_k(x) f_k            (zero background)

where w_k(x) = alpha_k(x) T_k(x) is splat k's blending weight at x. :func:`pixel_weights` computes
these weights once for a view (or a subset of its pixels) as a CSR matrix A [P, N] (pixels x
Gaussians) with a tracing pass over the rasterizer's tiles: GIT with one label per pixel, so the
same kernel (:func:`trace3d.render.kernels.trace_triplets`) and the same early termination as the
rasterizer. A feature render is then ``A @ f`` and its gradient ``A^T @ g`` (:meth:`PixelWeights.render`).
The twin is :func:`trace3d.render.render` with features requiring grad (tests compare both, values
and gradients).

Memory: A has one entry per (pixel, contributing splat); on a default room (160 x 120 px, about 80k
Gaussians) that is a few tens of splats per pixel, so keep the weights of a pixel subset per view
(the lifting step does) rather than of every pixel of every view.
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import Optional

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from ..errors import Trace3DError
from ..scene import Camera
from .projection import Splats, check_splats


@dataclasses.dataclass
class PixelWeights:
    """Blending weights of P pixels of one view over N Gaussians, CSR.

    Attributes:
        pixels: [P] int64 flat pixel indices (y * W + x) of the rows.
        indptr: [P + 1] int64 row pointers.
        indices: [E] int32 Gaussian index of each entry.
        weights: [E] float32 blending weight w_k(x) of each entry.
        num_gaussians: N.
        width, height: the view's size.
        blend_order: each row's entries in blending order (front to back) rather than by Gaussian
            (:func:`pixel_weights_blend_order`; what :mod:`~trace3d.render.weight_maps` needs).
    """

    pixels: np.ndarray
    indptr: np.ndarray
    indices: np.ndarray
    weights: np.ndarray
    num_gaussians: int
    width: int
    height: int
    blend_order: bool = False

    def __post_init__(self) -> None:
        self._fwd: Optional[Tensor] = None
        self._bwd: Optional[Tensor] = None

    @property
    def nnz(self) -> int:
        return int(self.indices.size)

    @property
    def nbytes(self) -> int:
        """Bytes held by the CSR arrays (:meth:`render` adds the transpose, about as much again)."""
        return int(self.pixels.nbytes + self.indptr.nbytes + self.indices.nbytes + self.weights.nbytes)

    def matrix(self) -> Tensor:
        """A as a torch sparse CSR tensor [P, N] (float32)."""
        if self._fwd is None:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)  # "sparse CSR support is in beta"
                self._fwd = torch.sparse_csr_tensor(torch.from_numpy(self.indptr.astype(np.int32)),
                                                    torch.from_numpy(self.indices), torch.from_numpy(self.weights),
                                                    (self.pixels.size, self.num_gaussians), check_invariants=False)
        return self._fwd

    def transpose_matrix(self) -> Tensor:
        """A^T as a torch sparse CSR tensor [N, P] (float32)."""
        if self._bwd is None:
            order = np.argsort(self.indices, kind="stable")
            rows = np.repeat(np.arange(self.pixels.size, dtype=np.int32), np.diff(self.indptr))
            indptr = np.zeros(self.num_gaussians + 1, np.int32)
            np.cumsum(np.bincount(self.indices, minlength=self.num_gaussians), out=indptr[1:])
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)
                self._bwd = torch.sparse_csr_tensor(torch.from_numpy(indptr), torch.from_numpy(rows[order]),
                                                    torch.from_numpy(self.weights[order]),
                                                    (self.num_gaussians, self.pixels.size), check_invariants=False)
        return self._bwd

    def rows(self, which: np.ndarray) -> "PixelWeights":
        """The weights of a subset of the rows (``which``: [Q] int64 row positions)."""
        which = np.asarray(which, np.int64)
        starts, stops = self.indptr[which], self.indptr[which + 1]
        counts = stops - starts
        indptr = np.zeros(which.size + 1, np.int64)
        np.cumsum(counts, out=indptr[1:])
        take = np.repeat(starts - indptr[:-1], counts) + np.arange(indptr[-1])
        return PixelWeights(self.pixels[which], indptr, self.indices[take], self.weights[take],
                            self.num_gaussians, self.width, self.height)

    def render(self, features: Tensor) -> Tensor:
        """Rendered features of the P pixels: [P, D] = A @ features ([N, D]), differentiable in features."""
        if features.dim() != 2 or features.shape[0] != self.num_gaussians:
            raise Trace3DError(f"pixel weights: features must be [N={self.num_gaussians}, D], "
                               f"got {tuple(features.shape)}.")
        return _SparseRender.apply(features, self)

    def render_rows(self, features: Tensor, which: np.ndarray) -> Tensor:
        """Rendered features of the rows ``which`` only ([Q] row positions): [Q, D], differentiable in
        ``features``; equal to ``render(features)[which]`` (the twin) at the cost of the Q rows (numba
        gather, and a serial scatter-add for the gradient, so the result does not depend on threads)."""
        if features.dim() != 2 or features.shape[0] != self.num_gaussians:
            raise Trace3DError(f"pixel weights: features must be [N={self.num_gaussians}, D], "
                               f"got {tuple(features.shape)}.")
        which = np.ascontiguousarray(which, np.int64)
        if which.size and (which.min() < 0 or which.max() >= self.pixels.size):
            raise Trace3DError(f"pixel weights: rows must lie in [0, {self.pixels.size}).")
        return _RowsRender.apply(features, self, which)

    def render_reference(self, features: Tensor) -> Tensor:
        """Slow twin of :meth:`render`: a dense loop over the rows ([P, D], autograd through indexing)."""
        out = []
        for r in range(self.pixels.size):
            a, b = int(self.indptr[r]), int(self.indptr[r + 1])
            idx = torch.from_numpy(self.indices[a:b].astype(np.int64))
            w = torch.from_numpy(self.weights[a:b]).to(features.dtype)
            out.append((w[:, None] * features[idx]).sum(0))
        return torch.stack(out) if out else features.new_zeros(0, features.shape[1])


class _SparseRender(torch.autograd.Function):
    @staticmethod
    def forward(ctx, features: Tensor, weights: PixelWeights) -> Tensor:
        ctx.weights = weights
        dtype = features.dtype
        return (weights.matrix() @ features.detach().float()).to(dtype)

    @staticmethod
    def backward(ctx, v_out: Tensor):
        weights: PixelWeights = ctx.weights
        v_features = (weights.transpose_matrix() @ v_out.float()).to(v_out.dtype)
        return v_features, None


@njit(parallel=True, cache=True)
def _gather_rows(indptr, indices, weights, which, features):
    out = np.zeros((which.size, features.shape[1]), np.float32)
    for q in prange(which.size):
        r = which[q]
        for e in range(indptr[r], indptr[r + 1]):
            w = weights[e]
            g = indices[e]
            for c in range(features.shape[1]):
                out[q, c] += w * features[g, c]
    return out


@njit(cache=True)
def _scatter_rows(indptr, indices, weights, which, v_out, n):
    grad = np.zeros((n, v_out.shape[1]), np.float32)
    for q in range(which.size):
        r = which[q]
        for e in range(indptr[r], indptr[r + 1]):
            w = weights[e]
            g = indices[e]
            for c in range(v_out.shape[1]):
                grad[g, c] += w * v_out[q, c]
    return grad


@njit(parallel=True, cache=True)
def scatter_rows_add(indptr, indices, weights, which, v_out, grad, parts):
    """grad[g] += w v_out[q] for every entry (row ``which[q]``, Gaussian g, weight w): the backward of a
    row gather, into a caller's buffer. ``parts`` threads (e.g. ``numba.get_num_threads()``) split the
    Gaussians into ranges and each walks all the entries in order, so every Gaussian's sum has the same
    order, that of :func:`_scatter_rows`, whatever the split."""
    n = grad.shape[0]
    for part in prange(parts):
        lo = n * part // parts
        hi = n * (part + 1) // parts
        for q in range(which.size):
            r = which[q]
            for e in range(indptr[r], indptr[r + 1]):
                g = indices[e]
                if g >= lo and g < hi:
                    w = weights[e]
                    for c in range(v_out.shape[1]):
                        grad[g, c] += w * v_out[q, c]


class _RowsRender(torch.autograd.Function):
    @staticmethod
    def forward(ctx, features: Tensor, weights: PixelWeights, which: np.ndarray) -> Tensor:
        ctx.weights, ctx.which, ctx.dtype = weights, which, features.dtype
        f = np.ascontiguousarray(features.detach().float().numpy())
        out = _gather_rows(weights.indptr, weights.indices, weights.weights, which, f)
        return torch.from_numpy(out).to(features.dtype)

    @staticmethod
    def backward(ctx, v_out: Tensor):
        w: PixelWeights = ctx.weights
        g = _scatter_rows(w.indptr, w.indices, w.weights, ctx.which,
                          np.ascontiguousarray(v_out.detach().float().numpy()), w.num_gaussians)
        return torch.from_numpy(g).to(ctx.dtype), None, None


def pixel_weights(splats: Splats, camera: Camera, pixels: Optional[np.ndarray] = None,
                  near: float = 0.01) -> PixelWeights:
    """Blending weights of ``pixels`` of ``camera`` (every pixel when None) over the N splats.

    Args:
        splats: N splats (geometry is read, never differentiated).
        camera: the view.
        pixels: [P] flat pixel indices y * W + x (distinct), or None for all H * W pixels in order.
        near: near plane, as in :func:`trace3d.render.render`.
    Returns:
        :class:`PixelWeights` whose row r holds w_k(pixels[r]) for every splat k with non-zero weight.
    """
    from .core import _check_labels, traced_triplets
    from .kernels.coalesce import coalesce_triplets

    n = check_splats(splats)
    hw = camera.height * camera.width
    if pixels is None:
        pixels = np.arange(hw, dtype=np.int64)
    pixels = np.asarray(pixels, np.int64).ravel()
    if pixels.size and (pixels.min() < 0 or pixels.max() >= hw):
        raise Trace3DError(f"pixel weights: pixel indices of camera {camera.name!r} must lie in [0, {hw}).")
    if np.unique(pixels).size != pixels.size:
        raise Trace3DError(f"pixel weights: pixel indices of camera {camera.name!r} must be distinct.")
    labels = np.full(hw, -1, np.int64)
    labels[pixels] = np.arange(pixels.size)
    if pixels.size == 0:
        return PixelWeights(pixels, np.zeros(1, np.int64), np.zeros(0, np.int32), np.zeros(0, np.float32), n,
                            camera.width, camera.height)
    lab = _check_labels(torch.from_numpy(labels.reshape(camera.height, camera.width)), camera, int(pixels.size))
    seen, gauss, row, vals = traced_triplets(splats, camera, lab, near)
    # by pixel, then Gaussian (a pixel's entries are distinct: it lies in one tile)
    _, gauss, vals, indptr = coalesce_triplets(row, seen[gauss], vals, int(pixels.size))
    return PixelWeights(pixels, indptr, gauss.astype(np.int32), vals, n, camera.width, camera.height)


def pixel_weights_blend_order(splats: Splats, camera: Camera, near: float = 0.01) -> PixelWeights:
    """:func:`pixel_weights` of every pixel of ``camera`` with each row's entries in blending order
    (front to back) instead of by Gaussian.

    The same rows and, row by row, the same (Gaussian, weight) entries (tested against
    :func:`pixel_weights`, the twin), so a per-Gaussian sum over the rows in row order (``np.bincount``
    over the entries, :func:`trace3d.lifting.query.object_weights`) gives the same bits: a Gaussian
    has at most one entry per row. One pass over the tiles writes each tile's entries as they are
    blended into room for a bound on them (:func:`~trace3d.render.kernels.trace.pixel_weights_kernel`),
    without the trace's dense [splats, labels] table per tile or the sort of each row; a second, cheap
    one puts them in rows by pixel (the evaluation's training views: 6 of its 18 CPU seconds went to
    those on a default room, docs/performance.md; a first pass that counted each pixel's entries
    before a second that wrote them cost as much again as this one)."""
    from .kernels.binning import Binning
    from .kernels.tiles import _geom_array, pack_geometry
    from .kernels.trace import pixel_weights_bounds, pixel_weights_kernel, pixel_weights_rows
    from .projection import project, visible_mask

    n = check_splats(splats)
    hw = camera.height * camera.width
    with torch.no_grad():
        seen = torch.nonzero(visible_mask(splats, camera, near)).squeeze(1)
        proj = project(Splats(*(t.detach().index_select(0, seen) for t in splats)), camera, near)
    binning = Binning(proj, camera.width, camera.height)
    egeom = binning.entry_geometry(_geom_array(pack_geometry(proj)))
    lists = np.ascontiguousarray(binning.lists, np.int32)
    bounds = pixel_weights_bounds(binning.entry_boxes, binning.offsets, binning.width, binning.height, binning.tiles_x)
    first = np.zeros(bounds.size, np.int64)
    np.cumsum(bounds[:-1], out=first[1:])
    room = int(bounds.sum())
    tile_pixel = np.empty(room, np.int32)
    tile_splat = np.empty(room, np.int32)
    tile_w = np.empty(room, np.float32)
    used = np.zeros(bounds.size, np.int64)
    count = np.zeros(hw, np.int64)
    pixel_weights_kernel(egeom, binning.entry_boxes, lists, binning.offsets, binning.width, binning.height,
                         binning.tiles_x, float(near), first, count, tile_pixel, tile_splat, tile_w, used)
    indptr = np.zeros(hw + 1, np.int64)
    np.cumsum(count, out=indptr[1:])
    gauss = np.empty(int(indptr[-1]), np.int32)
    vals = np.empty(int(indptr[-1]), np.float32)
    pixel_weights_rows(first, used, tile_pixel, tile_splat, tile_w, seen.cpu().numpy().astype(np.int32),
                       indptr[:-1].copy(), gauss, vals)
    return PixelWeights(np.arange(hw, dtype=np.int64), indptr, gauss, vals, n, camera.width, camera.height,
                        blend_order=True)
