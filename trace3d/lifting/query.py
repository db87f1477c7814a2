"""Querying lifted features (paper Sec. 3.5): iterative query-point finding and object extraction.

From one reference view and a mask of the target:

1. render the feature map F [H, W, D] of the reference view;
2. the first query point is the mask pixel deepest inside the mask (largest distance to its border);
   its feature q_1 gets the distance threshold t_1 that maximises the IoU of {x : ||F(x) - q_1|| <= t_1}
   with the mask (searched over ``threshold_steps`` quantiles of the distances inside the mask) among
   the thresholds whose pixels are at least ``min_precision`` (0.9, the released code's precision
   bound) inside the mask, so that one point never swallows a neighbour that a second point would miss;
3. while the IoU improves by more than ``min_gain`` and fewer than ``max_queries`` points are chosen,
   the next query point is the deepest pixel of the largest missed region (mask and not predicted);
   it gets its own threshold maximising the IoU of the union; it is kept only if the IoU improves.

The prediction at any camera is the union over query points of {x : ||F(x) - q_j|| <= t_j}.
The object's Gaussians are traced from the masks predicted at the training views (as the paper
extracts objects): each view's mask is traced (weights summed per Gaussian over object and
background pixels) and a Gaussian is the object's when its object share of the summed weight over
all views exceeds ``gaussian_share`` (0.5: the majority). The geometry is frozen, so the trace is a
product with each training view's pixel weights (:func:`trace_object_weights`); :func:`trace_object`,
GIT through the rasterizer, is its twin. The evaluation plans all its queries and answers them in one
pass over the views, one view's pixel weights and feature map held at a time
(:meth:`FeatureLifted.plan`, :meth:`FeatureLifted.run_plan`). A view's feature map is read from its
pixel weights in blending order (:mod:`trace3d.render.weight_maps`: the rasterizer's bits), so that a
view costs one tracing pass, not a trace and a render.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

import cv2
import numpy as np
import torch

from ..errors import Trace3DError
from ..gaussians import GaussianModel
from ..scene import Camera, Scene
from . import ObjectQuery
from .kernels.query import (_add_masked_rows, _kernel_applies, _query_distances, _query_mask, _query_mask_objects,
                            _query_mask_stack, object_balls)

log = logging.getLogger(__name__)


@dataclass
class QueryParams:
    """Parameters of query-point finding and object tracing."""

    max_queries: int = 8
    min_gain: float = 0.002
    threshold_steps: int = 64
    min_precision: float = 0.9  # a query point's threshold may add pixels outside the mask at most 10 % of the time
    min_missed_pixels: int = 4
    gaussian_share: float = 0.5
    near: float = 0.01

    # each field's range: refused on input and in the config schema (trace3d.params.check_ranges)
    RANGES = {"max_queries": ">= 1", "threshold_steps": ">= 2", "gaussian_share": "[0, 1)"}

    def __post_init__(self) -> None:
        if self.max_queries < 1 or self.threshold_steps < 2:
            raise ValueError(f"max_queries must be >= 1 and threshold_steps >= 2, got {self.max_queries}, "
                             f"{self.threshold_steps}")
        if not 0.0 <= self.gaussian_share < 1.0:
            raise ValueError(f"gaussian_share must be in [0, 1), got {self.gaussian_share}")


@dataclass
class QueryPoints:
    """Query features [Q, D], thresholds [Q], the reference pixels they came from [Q, 2] (x, y) and the
    reference IoU after each accepted point [Q]."""

    features: np.ndarray
    thresholds: np.ndarray
    pixels: np.ndarray
    ious: np.ndarray

    def distances(self, feature_map: np.ndarray) -> np.ndarray:
        """[Q, H, W] distances of every pixel's feature to each query feature."""
        return query_distances(feature_map, self.features)

    def distances_numpy(self, feature_map: np.ndarray) -> np.ndarray:
        """:meth:`distances` in numpy (the twin of the kernel; any dtype)."""
        return _query_distances_numpy(feature_map, self.features)

    def mask(self, feature_map: np.ndarray) -> np.ndarray:
        """[H, W] bool: the union over query points of distance <= threshold."""
        if self.features.shape[0] == 0:
            return np.zeros(feature_map.shape[:2], bool)
        if _kernel_applies(feature_map, self.features) and self.thresholds.dtype == np.float32:
            out = np.empty(feature_map.shape[:2], np.bool_)
            _query_mask(feature_map, self.features, self.thresholds, out)
            return out
        return (self.distances_numpy(feature_map) <= self.thresholds[:, None, None]).any(0)


def query_distances(feature_map: np.ndarray, features: np.ndarray) -> np.ndarray:
    """[Q, H, W] distances of every pixel's feature [H, W, D] to each of ``features`` [Q, D]: one numba
    pass for float32 inputs (numpy's values to the bit, below), else numpy."""
    if _kernel_applies(feature_map, features):
        out = np.empty((features.shape[0],) + feature_map.shape[:2], np.float32)
        _query_distances(feature_map, features, out)
        return out
    return _query_distances_numpy(feature_map, features)


def _query_distances_numpy(feature_map: np.ndarray, features: np.ndarray) -> np.ndarray:
    diff = feature_map[None] - features[:, None, None, :]
    return np.sqrt((diff * diff).sum(-1))


def iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0


def deepest_pixel(region: np.ndarray) -> tuple[int, int]:
    """(x, y) of the pixel of ``region`` farthest from its border (lowest index on ties)."""
    dist = cv2.distanceTransform(np.pad(region, 1).astype(np.uint8), cv2.DIST_L2, 5)[1:-1, 1:-1]
    y, x = np.unravel_index(int(np.argmax(dist)), dist.shape)
    return int(x), int(y)


def _best_threshold(dist: np.ndarray, covered: np.ndarray, mask: np.ndarray, steps: int,
                    min_precision: float) -> tuple[float, float]:
    """Threshold t on ``dist`` [H, W] maximising IoU(covered | dist <= t, mask) among those whose newly
    covered pixels lie in the mask at least ``min_precision`` of the time (the smallest candidate is
    always allowed); returns (t, IoU)."""
    inside = dist[mask]
    # candidates are distances that occur (inverted CDF), so "<= t" is exact after the float32 cast
    cands = np.unique(np.quantile(inside, np.linspace(0.0, 1.0, steps), method="inverted_cdf")).astype(np.float32) \
        if inside.size else np.zeros(1, np.float32)
    # vectorised over candidates: counts of pixels with dist < t, by (mask, covered)
    order = np.sort(dist[~covered & mask])
    order_out = np.sort(dist[~covered & ~mask])
    base_inter = int((covered & mask).sum())
    base_union = int((covered | mask).sum())
    new_in = np.searchsorted(order, cands, side="right")
    new_out = np.searchsorted(order_out, cands, side="right")
    inter = base_inter + new_in
    union = base_union + new_out
    scores = inter / np.maximum(union, 1)
    precise = new_in >= min_precision * np.maximum(new_in + new_out, 1)
    scores = np.where(precise | (np.arange(cands.size) == 0), scores, -1.0)
    best = int(np.argmax(scores))
    return float(cands[best]), float(scores[best])


def find_query_points(feature_map: np.ndarray, mask: np.ndarray, params: QueryParams | None = None) -> QueryPoints:
    """The paper's iterative query-point finding on the reference view.

    Args:
        feature_map: [H, W, D] rendered features of the reference view.
        mask: [H, W] bool reference mask (non-empty).
    """
    params = params or QueryParams()
    mask = np.asarray(mask, bool)
    if mask.shape != feature_map.shape[:2]:
        raise Trace3DError(f"query: mask shape {mask.shape} differs from the view's {feature_map.shape[:2]}.")
    if not mask.any():
        raise Trace3DError("query: the reference mask is empty.")
    feats, thresholds, pixels, ious = [], [], [], []
    covered = np.zeros_like(mask)
    best_iou = 0.0
    region = mask
    while len(feats) < params.max_queries:
        x, y = deepest_pixel(region)
        q = feature_map[y, x]
        dist = query_distances(feature_map, q[None])[0].astype(np.float32, copy=False)
        t, score = _best_threshold(dist, covered, mask, params.threshold_steps, params.min_precision)
        if feats and score <= best_iou + params.min_gain:
            break
        feats.append(q)
        thresholds.append(t)
        pixels.append((x, y))
        ious.append(score)
        covered = covered | (dist <= t)
        best_iou = score
        missed = mask & ~covered
        if missed.sum() < params.min_missed_pixels:
            break
        count, comps = cv2.connectedComponents(missed.astype(np.uint8), connectivity=4)
        sizes = np.bincount(comps.ravel(), minlength=count)
        sizes[0] = 0
        region = comps == int(np.argmax(sizes))
    d = feature_map.shape[-1]
    return QueryPoints(np.asarray(feats, np.float32).reshape(-1, d), np.asarray(thresholds, np.float32),
                       np.asarray(pixels, np.int64).reshape(-1, 2), np.asarray(ious, np.float32))


def trace_object(model: GaussianModel, cameras: Sequence[Camera], masks: Sequence[np.ndarray], share: float = 0.5,
                 near: float = 0.01) -> np.ndarray:
    """[N] bool: Gaussians whose GIT weight over all views falls on the object's pixels by more than ``share``.

    Args:
        cameras: L views; masks: L [H, W] bool object masks.
    """
    from ..render import trace

    splats = model.splats()
    fg = torch.zeros(len(model), dtype=torch.float64)
    total = torch.zeros(len(model), dtype=torch.float64)
    with torch.no_grad():
        for cam, m in zip(cameras, masks):
            w = trace(splats, cam, torch.from_numpy(np.asarray(m, np.int64)), 2, near=near).coalesce()
            rows, cols = w.indices()
            vals = w.values().double()
            total.index_add_(0, rows, vals)
            fg.index_add_(0, rows[cols == 1], vals[cols == 1])
    frac = fg / total.clamp_min(1e-12)
    return ((total > 0) & (frac > share)).numpy()


def trace_object_weights(weights: Sequence, masks: Sequence[np.ndarray], share: float = 0.5,
                         total: np.ndarray | None = None) -> np.ndarray:
    """:func:`trace_object` from precomputed full-view blending weights (the fast path).

    With the geometry frozen, the GIT weight of Gaussian i on a view's mask is the sum of its blending
    weights over the mask's pixels: a product with the view's pixel weights, no rasterization.

    Args:
        weights: L :class:`~trace3d.render.pixel_weights.PixelWeights` over every pixel of each view.
        masks: L [H, W] bool object masks.
        total: [N] the Gaussians' summed weight over the L views (query independent; computed if None).
    Returns:
        [N] bool, as :func:`trace_object`.
    """
    if total is None:
        total = summed_weights(weights)
    fg = object_weights(weights, masks)
    frac = fg / np.maximum(total, 1e-12)
    return (total > 0) & (frac > share)


def object_weights(weights: Sequence, masks: Sequence[np.ndarray]) -> np.ndarray:
    """[N] float64: every Gaussian's blending weight summed over the pixels of ``masks`` (one [H, W]
    bool per view of ``weights``).

    Visits only the CSR rows of the mask's pixels (a mask covers a few percent of a view), one numba
    pass per view; the values are those of :func:`object_weights_numpy` to the bit: per view the
    float64 sums in entry order (``np.bincount``'s), then added to the running total view by view."""
    n = weights[0].num_gaussians if weights else 0
    fg = np.zeros(n, np.float64)
    view = np.zeros(n, np.float64)
    touched = np.zeros(n, np.bool_)
    order = np.empty(n, np.int64)
    for w, m in zip(weights, masks):
        flat = np.ascontiguousarray(np.asarray(m, bool).ravel())
        _add_masked_rows(flat, w.pixels, w.indptr, w.indices, w.weights, fg, view, touched, order)
    return fg


def object_weights_numpy(weights: Sequence, masks: Sequence[np.ndarray]) -> np.ndarray:
    """:func:`object_weights` in numpy over every entry (the twin)."""
    n = weights[0].num_gaussians if weights else 0
    fg = np.zeros(n, np.float64)
    for w, m in zip(weights, masks):
        inside = np.asarray(m, bool).ravel()[w.pixels]
        entries = np.repeat(inside, np.diff(w.indptr))
        fg += np.bincount(w.indices[entries], weights=w.weights[entries], minlength=n)
    return fg


def summed_weights(weights: Iterable, num_gaussians: int | None = None) -> np.ndarray:
    """[N] float64: every Gaussian's blending weight summed over all pixels of the given views, in
    their order. ``weights`` may be a generator (one view's weights held at a time); ``num_gaussians``
    gives N when there may be no view (default: the first view's)."""
    total = None if num_gaussians is None else np.zeros(num_gaussians, np.float64)
    for w in weights:
        if total is None:
            total = np.zeros(w.num_gaussians, np.float64)
        _add_view_total(total, w)
    return np.zeros(0, np.float64) if total is None else total


def _add_view_total(total: np.ndarray, w) -> None:
    """total += one view's per-Gaussian sums (``np.bincount``'s order: the view's entries in order)."""
    total += np.bincount(w.indices, weights=w.weights, minlength=len(total))


def query_key(query: ObjectQuery) -> str:
    return query.reference + ":" + hashlib.sha1(np.packbits(np.asarray(query.mask, bool)).tobytes()).hexdigest()


def _points_key(q: QueryPoints) -> bytes:
    """What a mask of ``q`` is a function of: the query features and thresholds (bytes)."""
    return b"".join((str(q.features.shape).encode(), q.features.tobytes(), q.thresholds.tobytes()))


class _FeatureMaps:
    """Rendered feature maps (or a view's pixel weights) by view name, least recently used dropped beyond
    ``budget_bytes`` (a map is a function of the view only, so a dropped one is rendered again to the
    same bits)."""

    def __init__(self, budget_bytes: int):
        from collections import OrderedDict

        self.budget = int(budget_bytes)
        self.maps: "OrderedDict[str, np.ndarray]" = OrderedDict()
        self.bytes = 0

    def get(self, name: str) -> np.ndarray | None:
        fmap = self.maps.get(name)
        if fmap is not None:
            self.maps.move_to_end(name)
        return fmap

    def put(self, name: str, fmap: np.ndarray) -> None:
        if fmap.nbytes > self.budget:
            return
        self.maps[name] = fmap
        self.bytes += fmap.nbytes
        while self.bytes > self.budget:
            _, old = self.maps.popitem(last=False)
            self.bytes -= old.nbytes


class _Shared:
    """What :meth:`FeatureLifted.with_query` siblings share (none of it depends on the query parameters
    but ``near``): the feature-map cache, the blend-order pixel weights of the views asked for outside
    the pass (reference and test views: :meth:`FeatureLifted.blend_weights`), the summed visibility, the
    traced object Gaussians and the stored masks by query-point content, and the queries planned for the
    next pass over the views."""

    def __init__(self, map_budget_bytes: int, weights_budget_bytes: int):
        self.maps = _FeatureMaps(map_budget_bytes)
        self.weights = _FeatureMaps(weights_budget_bytes)
        self.total: np.ndarray | None = None
        # object Gaussians by (share, query-point content): one query point is often all that the full
        # search keeps, and then both protocols trace alike
        self.by_points: dict[bytes, np.ndarray] = {}
        self.masks: dict[tuple[bytes, str], tuple[np.ndarray, tuple[int, int]]] = {}  # packed bits, (H, W)
        self.pending_traces: dict[bytes, tuple[QueryPoints, float]] = {}
        self.pending_masks: dict[str, dict[bytes, QueryPoints]] = {}  # by camera name
        self.pending_cameras: dict[str, Camera] = {}


class FeatureLifted:
    """A :class:`~trace3d.lifting.LiftedScene` over lifted features (method ``"contrastive"``).

    The evaluation asks for every object's Gaussians, traced from its masks at every training view,
    and its masks at the scored views. Rather than keeping every training view's pixel weights and
    feature map (about 24 GB at 640x480 with 219 views, docs/scale.md), the queries are *planned*
    (:meth:`plan`) and answered by one pass over the views (:meth:`run_plan`) that holds one view's
    pixel weights and feature map at a time and, per traced object, one [N] float64 accumulator; the
    sums are those of the all-views-at-once path (:meth:`object_gaussians_at_once`, the twin): per
    object, views in order, a view's masked rows in order. A query that was not planned is answered
    by a pass of its own.
    """

    def __init__(self, model: GaussianModel, features: np.ndarray, train_cameras: Sequence[Camera],
                 params: QueryParams | None = None, map_budget_mb: float = 256.0, weights_budget_mb: float = 256.0):
        if features.shape[0] != len(model):
            raise Trace3DError(f"contrastive lift: {features.shape[0]} features for {len(model)} Gaussians; was it "
                               f"lifted on these Gaussians?")
        self.model = model
        self.features = np.asarray(features, np.float32)
        self.train_cameras = list(train_cameras)
        self.params = params or QueryParams()
        self.map_budget_mb = map_budget_mb
        self.weights_budget_mb = weights_budget_mb
        self._queries: dict[str, QueryPoints] = {}
        self._gaussians: dict[str, np.ndarray] = {}
        self._shared = _Shared(int(map_budget_mb * 2**20), int(weights_budget_mb * 2**20))

    def with_query(self, **overrides) -> "FeatureLifted":
        """The same lifted scene queried with other :class:`QueryParams` (e.g. ``max_queries=1``, the
        evaluation's single-query-point protocol); it shares the rendered feature maps, the visibility,
        the traced objects and the planned pass with this one (they do not depend on the query
        parameters), so that queries planned on both are answered by one pass over the views."""
        params = dataclasses.replace(self.params, **overrides)
        other = FeatureLifted(self.model, self.features, self.train_cameras, params, self.map_budget_mb,
                              self.weights_budget_mb)
        if params.near == self.params.near:
            other._shared = self._shared
        return other

    def feature_map(self, camera: Camera) -> np.ndarray:
        """[H, W, D] rendered features (cached up to ``map_budget_mb``, least recently used dropped): from
        the view's :meth:`blend_weights` (:func:`trace3d.render.weight_maps.feature_map`, the bits of
        :func:`~trace3d.lifting.contrastive.render_feature_map`, its twin)."""
        fmap = self._shared.maps.get(camera.name)
        if fmap is None:
            fmap = self._map_from(camera, self.blend_weights(camera))
        return fmap

    def _map_from(self, camera: Camera, weights) -> np.ndarray:
        """The feature map of ``camera`` from its blend-order ``weights``, put into the map cache."""
        from ..render.weight_maps import feature_map

        fmap = feature_map(weights, self.features)
        self._shared.maps.put(camera.name, fmap)
        return fmap

    def blend_weights(self, camera: Camera):
        """The full-view pixel weights of ``camera`` with each row in blending order
        (:func:`~trace3d.render.pixel_weights.pixel_weights_blend_order`; what the feature map, the
        evaluation's instance maps and object masks are read from), kept up to ``weights_budget_mb``
        (least recently used dropped; the pass over the training views keeps none of its own)."""
        from ..render.pixel_weights import pixel_weights_blend_order

        w = self._shared.weights.get(camera.name)
        if w is None:
            with torch.no_grad():
                w = pixel_weights_blend_order(self.model.splats(), camera, near=self.params.near)
            self._shared.weights.put(camera.name, w)
        return w

    def view_weights(self, camera: Camera):
        """The full-view :class:`~trace3d.render.pixel_weights.PixelWeights` of one view (not kept)."""
        from ..render.pixel_weights import pixel_weights

        with torch.no_grad():
            return pixel_weights(self.model.splats(), camera, near=self.params.near)

    def _training_views(self):
        """(camera, pixel weights) of each training view in order, computed one at a time (the caller
        drops a view's weights before asking for the next: then one view's are alive). Each row's
        entries come in blending order (:func:`~trace3d.render.pixel_weights.pixel_weights_blend_order`:
        the per-Gaussian sums over rows that the pass makes are :func:`pixel_weights`'s bits)."""
        from ..render.pixel_weights import pixel_weights_blend_order

        splats = self.model.splats()
        for c in self.train_cameras:
            w = self._shared.weights.get(c.name)  # a reference view's, computed for its query points
            if w is None:
                with torch.no_grad():
                    w = pixel_weights_blend_order(splats, c, near=self.params.near)
            yield c, w

    # --- the all-views-at-once path (the twin of the pass; it holds every training view) ----------
    def train_masks(self, q: QueryPoints) -> list[np.ndarray]:
        """[H, W] bool masks of ``q`` at every training view: :meth:`QueryPoints.mask` of each view's
        feature map rendered by the rasterizer (the twin of the maps read from pixel weights), in one
        kernel call over the training views' maps stacked (every training view's map at once: for tests
        and twins); per view when the sizes differ or the kernel does not apply."""
        from .contrastive import render_feature_map

        def rendered(c: Camera) -> np.ndarray:
            return render_feature_map(self.model, c, self.features, self.params.near)

        cams = self.train_cameras
        if not cams or q.features.shape[0] == 0 or q.thresholds.dtype != np.float32 \
                or len({(c.height, c.width) for c in cams}) != 1:
            return [q.mask(rendered(c)) for c in cams]
        first = rendered(cams[0])
        if not _kernel_applies(first, q.features):
            return [q.mask(rendered(c)) for c in cams]
        stack = np.empty((len(cams),) + first.shape, np.float32)
        for i, c in enumerate(cams):
            stack[i] = first if i == 0 else rendered(c)
        out = np.empty(stack.shape[:3], np.bool_)
        _query_mask_stack(stack, q.features, q.thresholds, out)
        return list(out)

    def train_weights(self) -> list:
        """The full-view pixel weights of every training view at once (:func:`pixel_weights`, rows by
        Gaussian; not kept: for tests and twins)."""
        from ..render.pixel_weights import pixel_weights

        splats = self.model.splats()
        with torch.no_grad():
            return [pixel_weights(splats, c, near=self.params.near) for c in self.train_cameras]

    def object_gaussians_at_once(self, query: ObjectQuery) -> np.ndarray:
        """:meth:`object_gaussians` from every training view's pixel weights and masks held at once (the
        code before the pass; the twin)."""
        return trace_object_weights(self.train_weights(), self.train_masks(self.query_points(query)),
                                    self.params.gaussian_share)

    # --- the pass -------------------------------------------------------------------------------------
    def visibility(self) -> np.ndarray:
        """[N] float64: every Gaussian's blending weight summed over all training pixels (computed once).

        From the pass when one has run; otherwise view by view, each view's pixel weights dropped after
        its sum (the same sums in the same order as :func:`summed_weights`, so the same bits)."""
        if self._shared.total is None:
            self._shared.total = summed_weights((w for _, w in self._training_views()), len(self.model))
        return self._shared.total

    def _trace_key(self, q: QueryPoints) -> bytes:
        return np.float64(self.params.gaussian_share).tobytes() + _points_key(q)

    def plan(self, query: ObjectQuery, cameras: Sequence[Camera] = ()) -> None:
        """Ask for the object Gaussians of ``query`` and its masks at ``cameras`` from the next
        :meth:`run_plan` (its query points are found now, on the reference view)."""
        q = self.query_points(query)
        sh = self._shared
        tkey = self._trace_key(q)
        if tkey not in sh.by_points:
            sh.pending_traces[tkey] = (q, self.params.gaussian_share)
        pkey = _points_key(q)
        for c in cameras:
            if (pkey, c.name) not in sh.masks:
                sh.pending_masks.setdefault(c.name, {})[pkey] = q
                sh.pending_cameras[c.name] = c

    def run_plan(self) -> None:
        """One pass over the training views (in order), then over the other planned cameras: per view,
        its feature map and (training views) its pixel weights, every planned object's mask there,
        added to the object's accumulator, and the masks asked for there stored (bit-packed); then the
        traced Gaussians. Holds one view's pixel weights and feature map at a time (and the maps that
        fit the cache's budget)."""
        sh = self._shared
        traces = list(sh.pending_traces.items())
        n = len(self.model)
        if traces or sh.total is None:
            sums = [np.zeros(n, np.float64) for _ in traces]
            total = np.zeros(n, np.float64)
            view = np.zeros(n, np.float64)
            touched = np.zeros(n, np.bool_)
            order = np.empty(n, np.int64)
            trace_points = [q for _, (q, _) in traces]
            trace_keys = [_points_key(q) for q in trace_points]
            for cam, w in self._training_views():
                _add_view_total(total, w)
                wanted = sh.pending_masks.pop(cam.name, {})
                sh.pending_cameras.pop(cam.name, None)
                # one mask per distinct query-point content at this view: the traced objects', then the
                # other masks asked for here
                keys = list(dict.fromkeys(trace_keys + list(wanted)))
                by_key = {**dict(zip(trace_keys, trace_points)), **wanted}
                fmap = sh.maps.get(cam.name)
                if fmap is None and keys:
                    fmap = self._map_from(cam, w)
                masks = dict(zip(keys, self._masks_at(cam, [by_key[k] for k in keys], fmap)))
                for fg, key in zip(sums, trace_keys):
                    flat = np.ascontiguousarray(masks[key].ravel())
                    _add_masked_rows(flat, w.pixels, w.indptr, w.indices, w.weights, fg, view, touched, order)
                for key in wanted:
                    sh.masks[(key, cam.name)] = (np.packbits(masks[key]), masks[key].shape)
                del masks, w, fmap
            if sh.total is None:
                sh.total = total
            del total
            for (key, (_, share)), fg in zip(traces, sums):
                frac = fg / np.maximum(sh.total, 1e-12)
                sh.by_points[key] = (sh.total > 0) & (frac > share)
            del sums
        sh.pending_traces.clear()
        # the masks asked for at the other views (and at the training views when no pass was needed)
        for name in list(sh.pending_masks):
            wanted = sh.pending_masks.pop(name)
            cam = sh.pending_cameras.pop(name)
            keys = list(wanted)
            for key, m in zip(keys, self._masks_at(cam, [wanted[k] for k in keys])):
                sh.masks[(key, name)] = (np.packbits(m), m.shape)

    def _masks_at(self, camera: Camera, points: Sequence[QueryPoints],
                  fmap: np.ndarray | None = None) -> list[np.ndarray]:
        """[H, W] bool masks of each of ``points`` at one view (:meth:`QueryPoints.mask`, the twin; one
        kernel call for all of them when it applies); ``fmap``: the view's feature map if at hand."""
        if not points:
            return []
        fmap = self.feature_map(camera) if fmap is None else fmap
        use = [q for q in points if q.features.shape[0] > 0]
        if use and all(q.features.dtype == np.float32 and q.thresholds.dtype == np.float32 for q in points) \
                and all(_kernel_applies(fmap, q.features) for q in use):
            feats = np.ascontiguousarray(np.concatenate([q.features.reshape(-1, fmap.shape[2]) for q in points]))
            thresholds = np.ascontiguousarray(np.concatenate([q.thresholds for q in points]))
            starts = np.zeros(len(points) + 1, np.int64)
            starts[1:] = np.cumsum([q.features.shape[0] for q in points])
            out = np.empty((len(points),) + fmap.shape[:2], np.bool_)
            centres, radii = object_balls(feats, thresholds, starts)
            _query_mask_objects(fmap, feats, thresholds, starts, centres, radii, out)
            return list(out)
        return [q.mask(fmap) for q in points]

    def _reference_camera(self, query: ObjectQuery) -> Camera:
        for c in self.train_cameras:
            if c.name == query.reference:
                return c
        raise Trace3DError(f"query: reference view {query.reference!r} is not a training view.")

    def query_points(self, query: ObjectQuery) -> QueryPoints:
        key = query_key(query)
        if key not in self._queries:
            cam = self._reference_camera(query)
            self._queries[key] = find_query_points(self.feature_map(cam), query.mask, self.params)
        return self._queries[key]

    def object_masks(self, query: ObjectQuery, cameras: Sequence[Camera]) -> list[np.ndarray]:
        """The masks of ``query`` at ``cameras``: those a pass stored (:meth:`plan`), else from each
        view's feature map (the same bits)."""
        q = self.query_points(query)
        pkey = _points_key(q)
        out = []
        for c in cameras:
            stored = self._shared.masks.get((pkey, c.name))
            if stored is None:
                out.append(q.mask(self.feature_map(c)))
            else:
                bits, shape = stored
                out.append(np.unpackbits(bits, count=shape[0] * shape[1]).reshape(shape).astype(bool))
        return out

    def object_gaussians(self, query: ObjectQuery) -> np.ndarray:
        key = query_key(query)
        if key not in self._gaussians:
            q = self.query_points(query)
            # the traced Gaussians are a function of the query features and thresholds (and the share)
            tkey = self._trace_key(q)
            if tkey not in self._shared.by_points:
                self.plan(query)
                self.run_plan()
            self._gaussians[key] = self._shared.by_points[tkey]
        return self._gaussians[key]


def load_feature_lifted(lift_dir: Path, info: dict, model: GaussianModel, scene: Scene,
                        train_cameras: Sequence[Camera]) -> FeatureLifted:
    """Loader of method ``"contrastive"``: ``features.npy`` [N, D] beside ``lift.json``."""
    from ..params import from_mapping

    path = Path(lift_dir) / "features.npy"
    if not path.is_file():
        raise Trace3DError(f"{path}: features.npy is missing from the contrastive lift folder.")
    try:
        features = np.load(path)
    except (ValueError, OSError) as exc:
        raise Trace3DError(f"{path}: not a NumPy array file ({exc}).") from exc
    if features.ndim != 2:
        raise Trace3DError(f"{path}: expected [N, D] features, got shape {features.shape}.")
    params = from_mapping(QueryParams, info.get("params", {}).get("query", {}), f"{lift_dir}/lift.json query")
    return FeatureLifted(model, features, train_cameras, params)
