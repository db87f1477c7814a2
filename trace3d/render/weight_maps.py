"""A view's feature and instance maps from its pixel weights in blending order, to the rasterizer's bits.

With the geometry frozen a rendered feature is ``F(x) = sum_k w_k(x) f_k`` over the splats that blend
into x, front to back. The rasterizer's forward kernel adds ``w * f`` to a float32 accumulator per
channel in that order, with ``w = alpha T`` computed by the same inline functions that
:func:`~trace3d.render.pixel_weights.pixel_weights_blend_order` uses (no fused multiply-add:
``FASTMATH`` is ``nsz`` only). So the same float32 products added in the same order from a view's
blend-order weights give the rendered map bit for bit, at the cost of one pass over the view's
entries instead of a projection, a binning and a blending of every splat. The evaluation computes a
view's weights once and reads its feature map, its instance maps (PQ^scene) and its object masks
(click extract) from them.

The twins are the rasterizer paths: :func:`trace3d.lifting.contrastive.render_feature_map` and
:func:`trace3d.lifting.contrastive.instance_map` (tests compare every bit).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..errors import Trace3DError
from .pixel_weights import PixelWeights


def _check_full_view(weights: PixelWeights) -> None:
    if not weights.blend_order or weights.pixels.size != weights.width * weights.height:
        raise Trace3DError("weight maps: need the pixel weights of every pixel of the view with each row in "
                           "blending order (pixel_weights_blend_order).")


def feature_map(weights: PixelWeights, features: np.ndarray) -> np.ndarray:
    """[H, W, D] float32: ``features`` [N, D] rendered with zero background (the rasterizer's
    ``render(...).features``, :func:`~trace3d.lifting.contrastive.render_feature_map`, to the bit)."""
    _check_full_view(weights)
    features = np.ascontiguousarray(features, np.float32)
    if features.ndim != 2 or features.shape[0] != weights.num_gaussians:
        raise Trace3DError(f"weight maps: features must be [N={weights.num_gaussians}, D], got {features.shape}.")
    out = np.zeros((weights.height * weights.width, features.shape[1]), np.float32)
    _feature_rows(weights.indptr, weights.indices, weights.weights, features, out)
    return out.reshape(weights.height, weights.width, features.shape[1])


@njit(parallel=True, cache=True)
def _feature_rows(indptr, indices, weights, features, out):
    """out[r] = the float32 sum over row r's entries, in order, of weight * features[gaussian]."""
    d = features.shape[1]
    for r in prange(indptr.shape[0] - 1):
        for e in range(indptr[r], indptr[r + 1]):
            w = weights[e]
            g = indices[e]
            for c in range(d):
                out[r, c] += w * features[g, c]


def instance_map(weights: PixelWeights, instance: np.ndarray, count: int) -> np.ndarray:
    """[H, W] int64: per pixel the instance (1..``count``) of ``instance`` [N] (0 = none) with the largest
    rendered blending weight, 0 where no instance's weight is positive
    (:func:`~trace3d.lifting.contrastive.instance_map`, which renders the one-hot indicators, to the bit:
    a one-hot channel adds ``w * 1 = w`` or ``w * 0 = 0``)."""
    _check_full_view(weights)
    instance = np.ascontiguousarray(instance, np.int64)
    if instance.shape != (weights.num_gaussians,):
        raise Trace3DError(f"weight maps: instance must be [N={weights.num_gaussians}], got {instance.shape}.")
    if count <= 0:
        return np.zeros((weights.height, weights.width), np.int64)
    if instance.size and (instance.min() < 0 or instance.max() > count):
        raise Trace3DError(f"weight maps: instance ids must lie in [0, {count}].")
    out = np.zeros(weights.height * weights.width, np.int64)
    _instance_rows(weights.indptr, weights.indices, weights.weights, instance, count, out)
    return out.reshape(weights.height, weights.width)


@njit(parallel=True, cache=True)
def _instance_rows(indptr, indices, weights, instance, count, out):
    """out[r] = 1 + the first instance of largest float32 weight sum over row r's entries (in order), or
    0 when that largest sum is not positive."""
    for r in prange(indptr.shape[0] - 1):
        acc = np.zeros(count, np.float32)
        for e in range(indptr[r], indptr[r + 1]):
            k = instance[indices[e]]
            if k > 0:
                acc[k - 1] += weights[e]
        best = 0
        for k in range(1, count):
            if acc[k] > acc[best]:
                best = k
        out[r] = best + 1 if acc[best] > np.float32(0.0) else 0


def set_mask(weights: PixelWeights, keep: np.ndarray) -> np.ndarray:
    """[H, W] bool: where the Gaussians ``keep`` [N] bool hold more of the rendered blending weight than
    the others (ties to ``keep``, and some weight): :func:`trace3d.extract.object_mask`, to the bit."""
    keep = np.asarray(keep, bool)
    return instance_map(weights, np.where(keep, 1, 2).astype(np.int64), 2) == 1
