"""The ``geometry`` mask source: nested masks from the fitted scene's depth and normals plus colour.

Reads no ground truth. After the 2DGS fit, every view (train and test) is rendered from the fitted
Gaussians in the cameras they were fitted with (the poses folder's): expected depth ``D`` [H, W] (the
alpha-normalised blend; the median depth speckles on textured surfaces) and
normal ``n`` [H, W, 3] (camera space, facing the camera), beside the view's photo. Then, per view:

1. **Pixel pairs.** Each 4-neighbour pair (p, q) gets: the *relative depth jump* across it, measured
   on the inverse depth (linear along any plane, so 0 on a plane whatever its slant and on a crease,
   about ``gap / depth`` across an occlusion; :func:`inverse_depth_jump`, over a span of
   ``2 depth_reach + 2`` pixels so that the blurred occlusions of a fit count); the pair is a
   **depth edge** when the jump exceeds ``depth_edge`` or either pixel is empty (alpha < ``min_alpha``). The
   **crease** angle between the two normals, and its sign: **concave** when
   ``(n_q - n_p) . (X_q - X_p) < 0`` (a floor meeting a chair leg, a wall meeting the floor),
   convex otherwise (the edge of a box). The colour difference (CIELAB).
2. **Superpixels.** Felzenszwalb's graph segmentation of the photo at a fine scale
   (``superpixel_scale``), cut further along depth edges and where neighbouring normals differ by more
   than ``crease_cut`` (connected components of the 4-neighbour graph without those pairs); the thin
   strips that a blurred edge's band of cut pairs leaves are dissolved into the nearest regions
   (:func:`trace3d.masks.graph.dissolve_thin`, radius 1).
3. **Agglomeration.** The region adjacency graph of the superpixels is merged greedily, cheapest
   pair first, with the cost of joining regions A and B::

       cost = colour_weight * |Lab(A) - Lab(B)| / 10           (mean colours)
            + depth_weight * share of the shared border that is a depth edge
            + concave_weight * mean concave crease angle on the border / (pi / 4)
            + convex_weight * mean convex crease angle on the border / (pi / 4)

   multiplied by ``sqrt(min(|A|, |B|) / small_area)`` when the smaller region is under
   ``small_area`` (small fragments join their best neighbour early, as in Felzenszwalb's rule).
   Depth edges separate objects from what stands behind them; concave creases from what they stand
   on; colour splits surfaces. Level ``k`` of the hierarchy is the partition when the next merge
   would cost more than ``thresholds[k]`` (>= 3 increasing values, finest first), so the coarse
   regions are unions of the fine ones by construction.
4. **Masks.** Every region of every level, as :func:`trace3d.masks.graph.nested_masks` emits them
   (area within [``min_area``, ``max_area``] of the image, a region equal to its single finer region
   emitted once, empty pixels never in a mask). Any two masks of a view are disjoint or nested.
   Scores are 1.

Sizes are fractions of the image and ``superpixel_scale`` / ``sigma`` scale with the image as the
``graph`` source's (``reference_pixels``). Frames without a pose in the poses folder (SfM did not
register them) get no masks. Deterministic: no random choice.
"""

from __future__ import annotations

import dataclasses
import heapq
import logging
from pathlib import Path
from typing import Iterator

import numpy as np
from tqdm import tqdm

from ..errors import Trace3DError
from ..scene import Camera, Scene
from .graph import REFERENCE_PIXELS, dissolve_thin, nested_masks

log = logging.getLogger(__name__)


@dataclasses.dataclass
class GeometryParams:
    """Parameters of the ``geometry`` mask source (module docstring).

    Attributes:
        thresholds: merge-cost levels of the hierarchy, finest first (>= 3, strictly increasing).
        superpixel_scale: Felzenszwalb ``scale`` of the colour over-segmentation at ``reference_pixels``.
        sigma: Felzenszwalb pre-smoothing width (pixels at ``reference_pixels``).
        depth_edge: relative depth jump (:func:`inverse_depth_jump`) above which a pixel pair is a depth edge.
        depth_reach: half-width (pixels) of the span a depth jump is measured across (blurred occlusions).
        crease_cut: angle (degrees) between a pixel pair's own normals above which the pair cuts a superpixel.
        colour_weight: weight of the mean-colour difference in the merge cost.
        colour_sigma: the region colours of the merge cost are taken from the image blurred by a Gaussian of
            this width (pixels at ``reference_pixels``; 0: unblurred), so that a fine texture (stripes, tiles)
            averages out instead of keeping its stripes apart.
        depth_weight: weight of the border's share of depth edges in the merge cost.
        concave_weight: weight of the border's mean concave crease angle in the merge cost.
        convex_weight: weight of the border's mean convex crease angle in the merge cost.
        plane_tolerance: a pixel lies on a plane when its distance to it is under this fraction of its depth.
        plane_min_share: a dominant plane holds at least this fraction of the view's pixels.
        max_planes: at most this many dominant planes per view (0: no plane cue).
        plane_iterations: RANSAC draws per plane.
        plane_weight: merge cost added when two regions do not lie on the same dominant plane and one does.
        plane_discount: the colour term is multiplied by this when both regions lie on the same plane.
        plane_member: a region lies on a plane when at least this share of its pixels does.
        seed: seed of the RANSAC draws (with the frame's index).
        small_area: fraction of the image under which a region's merge cost is discounted.
        min_area: regions covering less than this fraction of the image give no mask.
        max_area: regions covering more than this fraction of the image give no mask.
        min_alpha: pixels whose rendered opacity is below this are empty (no surface).
        normal_smooth: half-width (pixels) of the box filter applied to the rendered normals (0: none).
        crease_reach: a pair's crease angle compares the normals this many pixels beyond either pixel
            (a crease blurred over a few pixels still shows its full angle).
        near: near plane of the renders (camera z).
        reference_pixels: the image size (pixels) at which ``superpixel_scale`` and ``sigma`` apply.
        finest_level: masks are emitted from this level of the hierarchy up (0: every level; 1: the finest
            level's regions are left out, so that the patches are the next level's regions).
    """

    thresholds: list[float] = dataclasses.field(default_factory=lambda: [2.0, 4.0, 8.0])
    superpixel_scale: float = 60.0
    sigma: float = 0.5
    depth_edge: float = 0.5
    depth_reach: int = 1
    crease_cut: float = 30.0
    colour_weight: float = 2.0
    colour_sigma: float = 1.5
    depth_weight: float = 8.0
    concave_weight: float = 3.0
    convex_weight: float = 0.5
    plane_tolerance: float = 0.03
    plane_min_share: float = 0.05
    max_planes: int = 0
    plane_iterations: int = 200
    plane_weight: float = 2.0
    plane_discount: float = 0.3
    plane_member: float = 0.6
    seed: int = 0
    small_area: float = 0.005
    min_area: float = 0.003
    max_area: float = 0.9
    min_alpha: float = 0.5
    normal_smooth: int = 0
    crease_reach: int = 2
    near: float = 0.01
    reference_pixels: int = REFERENCE_PIXELS
    finest_level: int = 0

    def __post_init__(self) -> None:
        self.thresholds = [float(t) for t in self.thresholds]
        if not 0 <= self.finest_level < len(self.thresholds):
            raise ValueError(f"finest_level must be in [0, {len(self.thresholds) - 1}] (a level of the "
                             f"{len(self.thresholds)} thresholds), got {self.finest_level}")
        if len(self.thresholds) < 3:
            raise ValueError(f"thresholds needs at least 3 values (finest first), got {self.thresholds}")
        if any(t <= 0 for t in self.thresholds) or any(b <= a for a, b in zip(self.thresholds, self.thresholds[1:])):
            raise ValueError(f"thresholds must be positive and strictly increasing, got {self.thresholds}")
        for name in ("superpixel_scale", "depth_edge", "crease_cut", "near"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("sigma", "colour_weight", "depth_weight", "concave_weight", "convex_weight", "normal_smooth", "crease_reach", "depth_reach",
                     "colour_sigma"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        for name in ("plane_tolerance", "plane_weight", "plane_discount", "max_planes", "plane_iterations"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        for name in ("small_area", "min_area", "min_alpha", "plane_min_share", "plane_member"):
            if not 0.0 <= getattr(self, name) < 1.0:
                raise ValueError(f"{name} must be in [0, 1), got {getattr(self, name)}")
        if not self.min_area < self.max_area <= 1.0:
            raise ValueError(f"max_area must be in (min_area, 1], got {self.max_area}")
        if self.reference_pixels < 1:
            raise ValueError(f"reference_pixels must be >= 1, got {self.reference_pixels}")


# ----------------------------------------------------------------------------------------------
# Rendering the fitted geometry
# ----------------------------------------------------------------------------------------------


def render_geometry(model, camera: Camera, near: float = 0.01) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Expected depth [H, W], unit camera-space normals [H, W, 3] and alpha [H, W] of ``model`` in ``camera``
    (float64; depth 0 and normal 0 where nothing was hit)."""
    import torch

    from ..render import render

    with torch.no_grad():
        zeros = torch.zeros(len(model), 1, dtype=model.means.dtype)
        out = render(model.splats(), camera, zeros, near=near)
    alpha = out.alpha.double().numpy()
    # the expected depth sum_k w_k z_k / alpha: on a fitted scene far smoother than the median depth, whose
    # per-pixel pick of one splat speckles textured surfaces
    depth = np.where(alpha > 1e-6, out.depth.double().numpy() / np.maximum(alpha, 1e-6), 0.0)
    normal = out.normal.double().numpy()
    length = np.linalg.norm(normal, axis=2, keepdims=True)
    normal = np.where(length > 1e-8, normal / np.maximum(length, 1e-12), 0.0)
    return depth, normal, alpha


def back_project(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-space points [H, W, 3] of the pixel centres at ``depth`` [H, W] (z = depth)."""
    H, W = depth.shape
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    x = (u - K[0, 2] - K[0, 1] * (v - K[1, 2]) / K[1, 1]) / K[0, 0]
    y = (v - K[1, 2]) / K[1, 1]
    return np.stack([x * depth, y * depth, depth], axis=2)


# ----------------------------------------------------------------------------------------------
# Pixel pairs
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass
class PixelPairs:
    """The 4-neighbour pairs of an H x W image (horizontal ones first), flat pixel indices and cues.

    a, b: [E] int64 flat indices; depth_edge: [E] bool; crease: [E] float64 angle (radians) between the
    normals ``crease_reach`` pixels beyond either pixel; crease_near: [E] the angle between the pair's own
    normals; concave: [E] bool; colour: [E] float64 CIELAB distance.
    """

    a: np.ndarray
    b: np.ndarray
    depth_edge: np.ndarray
    crease: np.ndarray
    crease_near: np.ndarray
    concave: np.ndarray
    colour: np.ndarray


def inverse_depth_jump(inv: np.ndarray, axis: int, reach: int) -> np.ndarray:
    """Relative depth jump across every neighbour pair along ``axis`` (1: pairs (x, x + 1); 0: (y, y + 1)).

    With inverse depth ``rho`` (linear along any plane in the image) and the span ``lo = x - reach``,
    ``hi = x + 1 + reach`` (indices clipped to the image): ``|rho(hi) - rho(lo) - (hi - lo) s| / max(rho(x),
    rho(x + 1))`` where ``s`` is the mean of the one-pixel slopes just outside the span. Zero on a plane
    whatever its slant, and on a crease; about ``gap / depth`` across an occlusion blurred over up to
    ``2 reach + 1`` pixels.

    Args:
        inv: [H, W] inverse depth (0 where empty).
    Returns:
        [H, W - 1] (axis 1) or [H - 1, W] (axis 0) float64.
    """
    size = inv.shape[axis]
    x = np.arange(size - 1)
    lo, hi = np.clip(x - reach, 0, size - 1), np.clip(x + 1 + reach, 0, size - 1)
    lo_out, hi_out = np.clip(x - reach - 1, 0, size - 1), np.clip(x + 2 + reach, 0, size - 1)

    def take(i):
        return np.take(inv, i, axis=axis)

    slope = 0.5 * ((take(lo) - take(lo_out)) + (take(hi_out) - take(hi)))
    span = (np.minimum(x + 1 + reach, size - 1) - np.maximum(x - reach, 0)).astype(np.float64)
    shape = [1, 1]
    shape[axis] = size - 1
    across = take(hi) - take(lo) - span.reshape(shape) * slope
    ref = np.maximum(np.maximum(take(x), take(x + 1)), 1e-12)
    return np.abs(across) / ref


def pixel_pairs(lab: np.ndarray, depth: np.ndarray, normal: np.ndarray, alpha: np.ndarray, K: np.ndarray,
                params: GeometryParams) -> PixelPairs:
    """The cues of every 4-neighbour pixel pair (module docstring, step 1).

    Args:
        lab: [H, W, 3] CIELAB image; depth: [H, W]; normal: [H, W, 3] unit (0 where empty);
        alpha: [H, W]; K: [3, 3] intrinsics.
    """
    H, W = depth.shape
    if params.normal_smooth > 0:
        from scipy import ndimage

        size = 2 * params.normal_smooth + 1
        smooth = np.stack([ndimage.uniform_filter(normal[..., i], size=size, mode="nearest") for i in range(3)], 2)
        length = np.linalg.norm(smooth, axis=2, keepdims=True)
        normal = np.where(length > 1e-8, smooth / np.maximum(length, 1e-12), 0.0)
    points = back_project(depth, K)
    empty = (alpha < params.min_alpha) | (depth <= 0)
    inv = np.where(empty, 0.0, 1.0 / np.maximum(depth, 1e-12))
    index = np.arange(H * W).reshape(H, W)
    reach = params.crease_reach
    pieces = {k: [] for k in ("a", "b", "depth_edge", "crease", "crease_near", "concave", "colour")}
    for axis in (1, 0):  # horizontal pairs (x, x + 1), then vertical ones
        size = (W, H)[1 - axis]
        lo, hi = np.arange(size - 1), np.arange(1, size)
        far_lo, far_hi = np.maximum(lo - reach, 0), np.minimum(hi + reach, size - 1)

        def take(a, i):
            return np.take(a, i, axis=axis)

        n_p, n_q = take(normal, lo), take(normal, hi)
        jump = inverse_depth_jump(inv, axis, params.depth_reach) > params.depth_edge
        jump |= take(empty, lo) | take(empty, hi)
        # creases from the normals `reach` pixels off on either side (a crease blurred over a few pixels)
        m_p, m_q = take(normal, far_lo), take(normal, far_hi)
        cos = np.clip(np.einsum("...i,...i", m_p, m_q), -1.0, 1.0)
        concave = np.einsum("...i,...i", m_q - m_p, take(points, far_hi) - take(points, far_lo)) < 0
        pieces["a"].append(take(index, lo).ravel())
        pieces["b"].append(take(index, hi).ravel())
        pieces["depth_edge"].append(jump.ravel())
        pieces["crease"].append(np.arccos(cos).ravel())
        pieces["crease_near"].append(np.arccos(np.clip(np.einsum("...i,...i", n_p, n_q), -1.0, 1.0)).ravel())
        pieces["concave"].append(concave.ravel())
        pieces["colour"].append(np.linalg.norm(take(lab, hi) - take(lab, lo), axis=-1).ravel())
    return PixelPairs(**{k: np.concatenate(v) for k, v in pieces.items()})


def _pixel_pairs_reference(lab: np.ndarray, depth: np.ndarray, normal: np.ndarray, alpha: np.ndarray, K: np.ndarray,
                           params: GeometryParams) -> PixelPairs:
    """Loop twin of :func:`pixel_pairs` (one pair at a time; ``normal_smooth`` 0 only; used by the tests)."""
    if params.normal_smooth:
        raise ValueError("the reference twin takes normal_smooth 0")
    H, W = depth.shape
    reach = params.crease_reach
    out = {k: [] for k in ("a", "b", "depth_edge", "crease", "crease_near", "concave", "colour")}

    def point(y, x):
        u, v = x + 0.5, y + 0.5
        return np.linalg.solve(K, np.array([u, v, 1.0])) * depth[y, x]

    def empty(y, x):
        return alpha[y, x] < params.min_alpha or depth[y, x] <= 0

    inv = np.zeros((H, W))
    for y in range(H):
        for x in range(W):
            inv[y, x] = 0.0 if empty(y, x) else 1.0 / max(depth[y, x], 1e-12)

    def jump_at(line, at):
        reach_d = params.depth_reach
        size = len(line)

        def rho(i):
            return line[min(max(i, 0), size - 1)]

        lo, hi = at - reach_d, at + 1 + reach_d
        slope = 0.5 * ((rho(lo) - rho(lo - 1)) + (rho(hi + 1) - rho(hi)))
        span = min(hi, size - 1) - max(lo, 0)
        return abs(rho(hi) - rho(lo) - span * slope) / max(rho(at), rho(at + 1), 1e-12)

    for dy, dx in ((0, 1), (1, 0)):
        for y in range(H - dy):
            for x in range(W - dx):
                q = (y + dy, x + dx)
                far_p = (max(y - reach * dy, 0), max(x - reach * dx, 0))
                far_q = (min(q[0] + reach * dy, H - 1), min(q[1] + reach * dx, W - 1))
                line = inv[y] if dy == 0 else inv[:, x]
                at = x if dy == 0 else y
                jump = jump_at(line, at)
                out["a"].append(y * W + x)
                out["b"].append(q[0] * W + q[1])
                out["depth_edge"].append(jump > params.depth_edge or empty(y, x) or empty(*q))
                m_p, m_q = normal[far_p], normal[far_q]
                out["crease"].append(float(np.arccos(np.clip(m_p @ m_q, -1.0, 1.0))))
                out["crease_near"].append(float(np.arccos(np.clip(normal[y, x] @ normal[q], -1.0, 1.0))))
                out["concave"].append(bool((m_q - m_p) @ (point(*far_q) - point(*far_p)) < 0))
                out["colour"].append(float(np.linalg.norm(lab[q] - lab[y, x])))
    return PixelPairs(**{k: np.asarray(v) for k, v in out.items()})


# ----------------------------------------------------------------------------------------------
# Superpixels and agglomeration
# ----------------------------------------------------------------------------------------------


def superpixels(image: np.ndarray, pairs: PixelPairs, empty: np.ndarray, params: GeometryParams) -> np.ndarray:
    """[H, W] int32 labels 0..n-1: Felzenszwalb's colour regions cut along depth edges and sharp creases;
    empty pixels form regions of their own (module docstring, step 2)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from skimage.segmentation import felzenszwalb

    H, W = empty.shape
    factor = H * W / params.reference_pixels
    colour = felzenszwalb(image, scale=params.superpixel_scale * factor, sigma=params.sigma * float(np.sqrt(factor)),
                          min_size=max(1, int(round(0.0005 * H * W))), channel_axis=-1).ravel()
    flat_empty = empty.ravel()
    keep = (colour[pairs.a] == colour[pairs.b]) & (flat_empty[pairs.a] == flat_empty[pairs.b])
    keep &= ~pairs.depth_edge | (flat_empty[pairs.a] & flat_empty[pairs.b])
    keep &= pairs.crease_near <= np.deg2rad(params.crease_cut)
    graph = coo_matrix((np.ones(int(keep.sum()), np.int8), (pairs.a[keep], pairs.b[keep])), shape=(H * W, H * W))
    _, labels = connected_components(graph, directed=False)
    # a depth edge or crease blurred over a few pixels cuts a band of pairs: the strips between them dissolve
    # into the nearest regions (empty pixels stay apart)
    labels = _consecutive_first(labels).reshape(H, W)
    dissolved = dissolve_thin(labels, 1)
    dissolved[empty] = labels[empty]
    return _consecutive_first(dissolved.ravel()).reshape(H, W)


def _consecutive_first(labels: np.ndarray) -> np.ndarray:
    """Relabel [P] labels 0..n-1 in order of first appearance (raster order): deterministic."""
    _, first, inverse = np.unique(labels, return_index=True, return_inverse=True)
    order = np.argsort(np.argsort(first, kind="stable"), kind="stable")
    return order[inverse].astype(np.int32)


@dataclasses.dataclass
class _Border:
    """Sums over the pixel pairs on the border of two regions."""

    pairs: float
    depth: float
    concave: float
    convex: float


def region_graph(labels: np.ndarray, lab: np.ndarray, pairs: PixelPairs, empty: np.ndarray):
    """The region adjacency graph of ``labels`` [H, W] (n regions).

    Returns:
        area [n], colour sums [n, 3] (CIELAB), empty [n] bool (regions of empty pixels), and the
        borders {(i, j): _Border} for i < j.
    """
    flat = labels.ravel()
    n = int(flat.max()) + 1
    area = np.bincount(flat, minlength=n).astype(np.float64)
    colour = np.stack([np.bincount(flat, weights=lab[..., c].ravel(), minlength=n) for c in range(3)], 1)
    region_empty = np.bincount(flat, weights=empty.ravel().astype(np.float64), minlength=n) > 0.5 * area
    la, lb = flat[pairs.a], flat[pairs.b]
    cross = la != lb
    lo, hi = np.minimum(la, lb)[cross], np.maximum(la, lb)[cross]
    key = lo.astype(np.int64) * n + hi
    uniq, inverse = np.unique(key, return_inverse=True)
    crease = pairs.crease[cross]
    concave = pairs.concave[cross]
    sums = [np.bincount(inverse, weights=w, minlength=len(uniq)) for w in (
        np.ones(len(key)), pairs.depth_edge[cross].astype(np.float64), np.where(concave, crease, 0.0),
        np.where(concave, 0.0, crease))]
    borders = {(int(k // n), int(k % n)): _Border(*(float(s[i]) for s in sums)) for i, k in enumerate(uniq)}
    return area, colour, region_empty, borders


def merge_cost(area_a: float, area_b: float, colour_a: np.ndarray, colour_b: np.ndarray, border: _Border,
               params: GeometryParams, small_pixels: float, plane_a: int = -1, plane_b: int = -1) -> float:
    """The cost of joining two regions (module docstring, step 3); colours are CIELAB means, planes the
    regions' dominant planes (-1: none)."""
    quarter = np.pi / 4
    same_plane = plane_a == plane_b and plane_a >= 0
    cost = (params.colour_weight * float(np.linalg.norm(colour_a - colour_b)) / 10.0
            * (params.plane_discount if same_plane else 1.0)
            + (params.plane_weight if plane_a != plane_b else 0.0)
            + params.depth_weight * border.depth / border.pairs
            + params.concave_weight * border.concave / border.pairs / quarter
            + params.convex_weight * border.convex / border.pairs / quarter)
    smaller = min(area_a, area_b)
    if small_pixels > 0 and smaller < small_pixels:
        cost *= float(np.sqrt(smaller / small_pixels))
    return cost


def plane_histogram(labels: np.ndarray, planes: np.ndarray | None, n: int) -> np.ndarray:
    """[n, P] pixel counts of each region of ``labels`` on each dominant plane (P = 0 without planes)."""
    if planes is None or planes.max() < 0:
        return np.zeros((n, 0))
    P = int(planes.max()) + 1
    on = planes.ravel() >= 0
    key = labels.ravel()[on].astype(np.int64) * P + planes.ravel()[on]
    return np.bincount(key, minlength=n * P).reshape(n, P).astype(np.float64)


def dominant_planes(points: np.ndarray, valid: np.ndarray, params: GeometryParams,
                    rng: np.random.Generator) -> np.ndarray:
    """The view's dominant planes (walls, floor, table tops) by sequential RANSAC.

    A pixel lies on a plane when its distance to it is under ``plane_tolerance`` times its depth. Up to
    ``max_planes`` planes, each drawn ``plane_iterations`` times from 3 random pixels not yet assigned,
    kept while it holds at least ``plane_min_share`` of the view's pixels, then refitted (least squares)
    to its inliers; a pixel goes to the first plane it lies on.

    Args:
        points: [H, W, 3] camera-space points; valid: [H, W] bool (pixels with a surface).
    Returns:
        [H, W] int32: the plane of each pixel, -1 where none.
    """
    H, W = valid.shape
    out = np.full((H, W), -1, np.int32)
    flat = points.reshape(-1, 3)
    free = valid.ravel().copy()
    depth = np.maximum(flat[:, 2], 1e-12)
    need = params.plane_min_share * valid.sum()
    for k in range(params.max_planes):
        candidates = np.nonzero(free)[0]
        if len(candidates) < max(3, need):
            break
        best, best_count = None, 0
        for _ in range(params.plane_iterations):
            p0, p1, p2 = flat[rng.choice(candidates, 3, replace=False)]
            normal = np.cross(p1 - p0, p2 - p0)
            length = np.linalg.norm(normal)
            if length < 1e-12:
                continue
            normal /= length
            inliers = np.abs((flat[candidates] - p0) @ normal) < params.plane_tolerance * depth[candidates]
            count = int(inliers.sum())
            if count > best_count:
                best, best_count = inliers, count
        if best is None or best_count < need:
            break
        members = candidates[best]
        centre = flat[members].mean(axis=0)
        normal = np.linalg.svd(flat[members] - centre, full_matrices=False)[2][-1]
        on = np.abs((flat[candidates] - centre) @ normal) < params.plane_tolerance * depth[candidates]
        if on.sum() < need:
            break
        out.ravel()[candidates[on]] = k
        free[candidates[on]] = False
    return out


def region_plane(counts: np.ndarray, area: float, member: float) -> int:
    """The plane a region lies on (-1: none) from its pixel counts per plane [P] and its area."""
    if len(counts) == 0:
        return -1
    k = int(np.argmax(counts))
    return k if counts[k] >= member * area else -1


def agglomerate(labels: np.ndarray, lab: np.ndarray, pairs: PixelPairs, empty: np.ndarray,
                params: GeometryParams, planes: np.ndarray | None = None) -> np.ndarray:
    """Greedy merging of the regions ``labels`` [H, W], cheapest first; the partition before the first merge
    costing more than each threshold (module docstring, step 3).

    Args:
        planes: [H, W] int, the dominant plane of each pixel (-1: none; :func:`dominant_planes`), optional.
    Returns:
        [K, H, W] int32 nested label maps, finest first (K = len(thresholds)).
    """
    H, W = labels.shape
    area, colour_sum, region_empty, borders = region_graph(labels, lab, pairs, empty)
    n = len(area)
    plane_counts = plane_histogram(labels, planes, n)
    small_pixels = params.small_area * H * W
    parent = np.arange(n)
    version = np.zeros(n, np.int64)
    neighbours: dict[int, dict[int, _Border]] = {i: {} for i in range(n)}
    for (i, j), border in borders.items():
        if region_empty[i] or region_empty[j]:
            continue  # empty regions never merge
        neighbours[i][j] = border
        neighbours[j][i] = border

    def cost(i: int, j: int) -> float:
        return merge_cost(area[i], area[j], colour_sum[i] / area[i], colour_sum[j] / area[j], neighbours[i][j],
                          params, small_pixels, region_plane(plane_counts[i], area[i], params.plane_member),
                          region_plane(plane_counts[j], area[j], params.plane_member))

    heap = [(cost(i, j), i, j, 0, 0) for (i, j) in borders if j in neighbours[i]]
    heapq.heapify(heap)
    levels = []

    def snapshot() -> np.ndarray:
        root = parent.copy()
        while True:
            nxt = root[root]
            if np.array_equal(nxt, root):
                break
            root = nxt
        return root[labels].astype(np.int32)

    for threshold in params.thresholds:
        while heap and heap[0][0] <= threshold:
            c, i, j, vi, vj = heapq.heappop(heap)
            if parent[i] != i or parent[j] != j or version[i] != vi or version[j] != vj:
                continue  # stale: one side has merged or changed since
            # j joins i (the lower index stays the root: deterministic)
            a, b = (i, j) if i < j else (j, i)
            parent[b] = a
            area[a] += area[b]
            colour_sum[a] += colour_sum[b]
            plane_counts[a] += plane_counts[b]
            version[a] += 1
            del neighbours[a][b]
            for c_, border in neighbours.pop(b).items():
                if c_ == a:
                    continue
                del neighbours[c_][b]
                old = neighbours[a].get(c_)
                merged = border if old is None else _Border(old.pairs + border.pairs, old.depth + border.depth,
                                                            old.concave + border.concave, old.convex + border.convex)
                neighbours[a][c_] = merged
                neighbours[c_][a] = merged
            for c_ in sorted(neighbours[a]):
                lo, hi = (a, c_) if a < c_ else (c_, a)
                heapq.heappush(heap, (cost(lo, hi), lo, hi, int(version[lo]), int(version[hi])))
        levels.append(snapshot())
    return np.stack(levels)


def _agglomerate_reference(labels: np.ndarray, lab: np.ndarray, pairs: PixelPairs, empty: np.ndarray,
                           params: GeometryParams, planes: np.ndarray | None = None) -> np.ndarray:
    """Brute-force twin of :func:`agglomerate`: every step recomputes every adjacent pair's cost from the
    pixels and merges the cheapest (ties: the lower pair of labels), into the lower label (used by the tests)."""
    H, W = labels.shape
    current = labels.ravel().copy()
    small_pixels = params.small_area * H * W
    lab_flat = lab.reshape(-1, 3)
    empty_flat = empty.ravel()
    planes_flat = planes.ravel() if planes is not None else np.full(H * W, -1)
    P = int(planes_flat.max()) + 1

    def plane_of(inside):
        counts = np.array([(planes_flat[inside] == k).sum() for k in range(P)], np.float64)
        return region_plane(counts, float(inside.sum()), params.plane_member)

    levels = []
    for threshold in params.thresholds:
        while True:
            best = None
            for i in np.unique(current):
                for j in np.unique(current):
                    if j <= i:
                        continue
                    in_i, in_j = current == i, current == j
                    if 2 * empty_flat[in_i].sum() > in_i.sum() or 2 * empty_flat[in_j].sum() > in_j.sum():
                        continue
                    on = ((current[pairs.a] == i) & (current[pairs.b] == j)) | ((current[pairs.a] == j) & (current[pairs.b] == i))
                    if not on.any():
                        continue
                    border = _Border(float(on.sum()), float(pairs.depth_edge[on].sum()),
                                     float(np.where(pairs.concave[on], pairs.crease[on], 0.0).sum()),
                                     float(np.where(pairs.concave[on], 0.0, pairs.crease[on]).sum()))
                    c = merge_cost(float(in_i.sum()), float(in_j.sum()), lab_flat[in_i].mean(0), lab_flat[in_j].mean(0),
                                   border, params, small_pixels, plane_of(in_i), plane_of(in_j))
                    if best is None or c < best[0]:
                        best = (c, i, j)
            if best is None or best[0] > threshold:
                break
            current[current == best[2]] = best[1]
        levels.append(current.reshape(H, W).astype(np.int32).copy())
    return np.stack(levels)


# ----------------------------------------------------------------------------------------------
# One view, and the source
# ----------------------------------------------------------------------------------------------


def geometry_hierarchy(image: np.ndarray, depth: np.ndarray, normal: np.ndarray, alpha: np.ndarray, K: np.ndarray,
                       params: GeometryParams, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The nested hierarchy of one view.

    Args:
        image: [H, W, 3] uint8 RGB; depth: [H, W] median depth; normal: [H, W, 3] unit camera-space
        normals; alpha: [H, W]; K: [3, 3].
    Returns:
        [K, H, W] int32 nested label maps (finest first) and [H, W] bool empty pixels.
    """
    from skimage.color import rgb2lab

    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.shape[:2] != depth.shape:
        raise Trace3DError(f"geometry masks: the image has shape {image.shape}, the render {depth.shape}.")
    lab = rgb2lab(image)
    pairs = pixel_pairs(lab, depth, normal, alpha, K, params)
    empty = (alpha < params.min_alpha) | (depth <= 0)
    labels = superpixels(image, pairs, empty, params)
    if params.colour_sigma > 0:  # region colours from the blurred image: a fine texture averages out
        from scipy import ndimage

        sigma = params.colour_sigma * float(np.sqrt(depth.size / params.reference_pixels))
        lab = np.stack([ndimage.gaussian_filter(lab[..., c], sigma, mode="nearest") for c in range(3)], axis=2)
    planes = None
    if params.max_planes > 0:
        planes = dominant_planes(back_project(depth, K), ~empty, params, np.random.default_rng([params.seed, seed]))
    return agglomerate(labels, lab, pairs, empty, params, planes), empty


def geometry_view_masks(image: np.ndarray, depth: np.ndarray, normal: np.ndarray, alpha: np.ndarray, K: np.ndarray,
                        params: GeometryParams, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """One view's masks [M, H, W] bool and scores [M] float32 (all 1); see :func:`geometry_hierarchy`."""
    hierarchy, empty = geometry_hierarchy(image, depth, normal, alpha, K, params, seed)
    H, W = depth.shape
    masks, _ = nested_masks(hierarchy[params.finest_level:], max(1, int(np.ceil(params.min_area * H * W))),
                            int(np.floor(params.max_area * H * W)), exclude=empty)
    return masks, np.ones(len(masks), np.float32)


def iter_geometry_masks(scene: Scene, params: GeometryParams, gaussians_dir: Path | None,
                        poses_dir: Path | None) -> Iterator[tuple[str, np.ndarray, np.ndarray]]:
    """Yield (frame name, masks [M, H, W] bool, scores [M] float32) for every frame, from the fitted scene."""
    if gaussians_dir is None:
        raise Trace3DError("the geometry mask source renders the fitted scene: give `trace3d masks` the 2DGS fit "
                           "with --gaussians (and the poses folder it was fitted with, --poses).")
    from ..gaussians import GaussianModel
    from ..scene import read_pose_cameras, require_known_poses

    if poses_dir is None:
        require_known_poses(scene, "trace3d masks --source geometry")
    model = GaussianModel.read_ply(Path(gaussians_dir) / "point_cloud.ply")
    cameras = read_pose_cameras(Path(poses_dir), scene) if poses_dir is not None else list(scene.cameras)
    by_name = {cam.name: cam for cam in cameras}
    log.info("geometry masks: %d Gaussians, depth edges > %.2f of the depth, concave creases, colour; levels %s",
             len(model), params.depth_edge, params.thresholds)
    for index, scene_cam in enumerate(tqdm(scene.cameras, desc="geometry masks", unit="view", mininterval=5.0)):
        cam = by_name.get(scene_cam.name)
        if cam is None:
            log.warning("geometry masks: frame %s has no pose in the fit; it gets no masks", scene_cam.name)
            yield scene_cam.name, np.zeros((0, scene_cam.height, scene_cam.width), bool), np.zeros(0, np.float32)
            continue
        depth, normal, alpha = render_geometry(model, cam, params.near)
        masks, scores = geometry_view_masks(scene.image(cam.name), depth, normal, alpha, cam.K, params, index)
        yield cam.name, masks, scores
