"""One object out by a click: ``trace3d extract --view V --point X,Y`` on a contrastively lifted scene.

No reference mask is needed. From the clicked pixel of training view V (``selection: features``, the
default; SAGA-style, then 3D connectivity):

1. **seeds**: the Gaussians that blend into the clicked pixel and its 8 neighbours (one trace of V);
   the *query* is the lifted feature of the surface clicked on (a rendered feature at an object's
   border blends two objects'): ``query: medoid``, the weighted medoid of the heavy seeds' features
   (:func:`click_query`; ``top``: the heaviest seed's, the rule before);
2. **similar**: every Gaussian seen in training whose feature lies within the threshold t of the query;
3. **connected**: of the similar Gaussians only those linked to a similar seed through edges of the
   Gaussians' kNN graph (``neighbours`` = 12, by centre) whose both ends are similar: another object
   with the same feature elsewhere in the scene (a twin never seen beside it) is not taken;
   Gaussians never seen in training follow their nearest seen neighbour.
4. **the threshold**, from the data: the scene's distance between same-object and other-object features
   (:func:`~trace3d.segment.feature_threshold` x ``threshold_scale``: where the feature distances of
   neighbours in 3D and of random pairs on two objects cross, the value ``trace3d segment`` joins
   segments with) is the centre of the click's own choice (``threshold_rule: stable``): steps 2-3 at
   every t at once (:func:`click_distances`: the least t that selects each Gaussian) and t where the
   selection grows least (:func:`stable_threshold`): an object's Gaussians join below the valley of their
   distances to the query, its support only above it. ``threshold_rule: data`` uses that distance for
   every click (the rule before), and ``threshold`` a number of yours.

``selection: segment`` returns the ``trace3d segment`` object the click falls in (the segment holding
the most of the seeds' weight); ``selection: region`` is the step before issue 48: a 2D region grown
from the click in the rendered feature map (the most stable region over thresholds, as MSER), used as
the reference mask of the paper's query (:func:`~trace3d.lifting.query.find_query_points`, the object's
Gaussians traced from its masks at the training views) and, with ``connected``, cut to the traced
Gaussians chained in 3D to those under the click.

Writes into ``out_dir``: ``object.ply`` (the object's Gaussians, the 3DGS/2DGS PLY layout of
:meth:`~trace3d.gaussians.GaussianModel.write_ply`, which Gaussian-splat viewers open), ``object.png``
(the clicked view with the click and the object's mask there: the pixels where its Gaussians hold more
of the rendered weight than the rest, :func:`object_mask`; then the object rendered alone from
``picture_views`` training views, those that show most of it), ``turntable.png`` (the object alone from
``turntable_views`` directions around it) and ``extract.json`` (the click, the selection, the
threshold, the Gaussian count and the settings). Its click IoU on the rooms: docs/evaluation.md; how it was chosen: docs/objects.md.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import torch

from .errors import ConfigError, Trace3DError
from .io import write_json
from .params import from_mapping, to_dict

log = logging.getLogger(__name__)


@dataclasses.dataclass
class ExtractParams:
    """Parameters of ``trace3d extract`` (``--params``; ``--view`` and ``--point`` override ``view`` and ``point``).

    Attributes:
        view: the training view clicked on (its frame name).
        point: the clicked pixel (x, y): column and row of the view's image, 0-based (fractions are floored).
        selection: ``features`` (default): the Gaussians whose lifted feature lies within ``threshold`` of
            the clicked pixel's rendered feature, linked in 3D to the Gaussians under the click (module
            docstring); ``segment``: the ``trace3d segment`` object the click falls in; ``region``: the
            2D region grown from the click queried as a reference mask (the step before issue 48).
        threshold: ``features``: the feature distance, the same for every click; ``None``: chosen from the
            data (``threshold_rule``).
        threshold_rule: ``stable`` (default): per click, the most stable threshold of the click's connected
            selection (:func:`stable_threshold`) around ``threshold_scale`` times the lift's same-object /
            other-object distance (:func:`~trace3d.segment.feature_threshold`); ``data``: that distance itself,
            the same for every click (the rule before).
        threshold_scale: see ``threshold_rule``.
        query: the feature the click selects by, from the Gaussians under the click and their blending
            weights there (:func:`click_query`): ``medoid`` (default), of the seeds with at least
            ``query_min_weight`` of the heaviest one's weight the one whose feature has the least weighted
            sum of distances to all the seeds' (the surface clicked on, robust to a stray heavy seed);
            ``top``, the feature of the seed with the most weight (the rule before).
        query_min_weight: see ``query`` (in [0, 1]).
        stable_min_scale, stable_max_scale, stable_steps: ``stable``: the thresholds tried, ``stable_steps`` + 1
            geometric steps from ``stable_min_scale`` to ``stable_max_scale`` times the data's distance.
        stable_span: ``stable``: a threshold's growth is measured from this many steps below it to this many
            above it (the log of the ratio of the selection's training weights there).
        stable_prior: ``stable``: added to the growth per unit of |log(threshold / data distance)|: among
            equally stable thresholds the one nearer the data's distance wins.
        stable_max_share: ``stable``: a threshold whose selection, ``stable_span`` steps above it, holds more
            than this share of the scene's training weight is not an object's.
        stable_min_gaussians: ``stable``: a threshold selecting fewer Gaussians is not an object's.
        neighbours: k of the kNN graph over the Gaussians' centres (``features``, ``segment``).
        pairs, seed: the random pairs (and their seed) of that threshold.
        threshold_steps: ``region``: thresholds tried when growing the region from the click.
        stability_delta: ``region``: grid steps on either side over which a region's growth is measured.
        stability_tolerance: ``region``: regions whose relative growth is within this of the most stable
            one's are near-ties, decided by the widest run of thresholds (0: exact ties only).
        min_region_pixels: ``region``: smallest region that counts as an object.
        max_region_fraction: ``region``: a region whose grown neighbour covers this fraction of the view
            is not an object.
        connected: ``region``: keep only the traced Gaussians connected in 3D to those under the click.
        link_scale: ``region``: two Gaussians are linked when their centres are closer than this many
            times the median nearest-neighbour distance of the traced set.
        picture_views: training views the object is rendered from in ``object.png``.
        turntable_views, turntable_size: the ``turntable.png`` strip (views, pixels per side).
    """

    view: str = ""
    point: tuple[float, ...] = ()
    selection: Literal["features", "segment", "region"] = "features"
    threshold: float | None = None
    threshold_rule: Literal["stable", "data"] = "stable"
    query: Literal["medoid", "top"] = "medoid"
    query_min_weight: float = 0.25
    threshold_scale: float = 1.0
    stable_min_scale: float = 0.2
    stable_max_scale: float = 3.0
    stable_steps: int = 48
    stable_span: int = 4
    stable_prior: float = 0.5
    stable_max_share: float = 0.5
    stable_min_gaussians: int = 10
    neighbours: int = 12
    pairs: int = 100000
    seed: int = 0
    threshold_steps: int = 64
    stability_delta: int = 2
    stability_tolerance: float = 0.0
    min_region_pixels: int = 4
    max_region_fraction: float = 0.9
    connected: bool = True
    link_scale: float = 3.0
    picture_views: int = 6
    turntable_views: int = 8
    turntable_size: int = 128

    def __post_init__(self) -> None:
        if self.threshold is not None and not self.threshold > 0:
            raise ValueError(f"threshold must be > 0 (or null), got {self.threshold}")
        if not self.threshold_scale > 0 or self.neighbours < 1 or self.pairs < 2:
            raise ValueError(f"threshold_scale must be > 0, neighbours >= 1 and pairs >= 2, got "
                             f"{self.threshold_scale}, {self.neighbours}, {self.pairs}")
        if not 0 < self.stable_min_scale < self.stable_max_scale or not 1 <= self.stable_span < self.stable_steps // 2:
            raise ValueError(f"stable_min_scale must be in (0, stable_max_scale) and stable_span in [1, stable_steps / 2), "
                             f"got {self.stable_min_scale}, {self.stable_max_scale}, {self.stable_span}, {self.stable_steps}")
        if not 0.0 <= self.query_min_weight <= 1.0:
            raise ValueError(f"query_min_weight must be in [0, 1], got {self.query_min_weight}")
        if self.stable_prior < 0 or not 0 < self.stable_max_share <= 1 or self.stable_min_gaussians < 1:
            raise ValueError(f"stable_prior must be >= 0, stable_max_share in (0, 1] and stable_min_gaussians >= 1, got "
                             f"{self.stable_prior}, {self.stable_max_share}, {self.stable_min_gaussians}")
        if self.threshold_steps < 4 or not 1 <= self.stability_delta < self.threshold_steps // 2:
            raise ValueError(f"threshold_steps must be >= 4 and stability_delta in [1, threshold_steps / 2), got "
                             f"{self.threshold_steps}, {self.stability_delta}")
        if self.stability_tolerance < 0:
            raise ValueError(f"stability_tolerance must be >= 0, got {self.stability_tolerance}")
        if self.min_region_pixels < 1 or not 0.0 < self.max_region_fraction <= 1.0:
            raise ValueError("min_region_pixels must be >= 1 and max_region_fraction in (0, 1]")
        if not self.link_scale > 0:
            raise ValueError(f"link_scale must be > 0, got {self.link_scale}")
        if self.picture_views < 0 or self.turntable_views < 0 or self.turntable_size < 8:
            raise ValueError("picture_views and turntable_views must be >= 0 and turntable_size >= 8")


def parse_point(text: str) -> tuple[float, float]:
    """``"X,Y"`` -> (x, y)."""
    parts = text.replace(" ", "").split(",")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 2:
        raise ConfigError(f"extract: --point must be two numbers X,Y (column, row), got {text!r}.")
    return values  # type: ignore[return-value]


@dataclasses.dataclass
class ClickRegion:
    """The region grown from a click: mask [H, W] bool, the threshold t on ||F - q||, its stability
    score, and the region's size at every threshold of the grid (thresholds [S], areas [S])."""

    mask: np.ndarray
    threshold: float
    stability: float
    thresholds: np.ndarray
    areas: np.ndarray


def grow_from_click(feature_map: np.ndarray, x: int, y: int, params: ExtractParams | None = None) -> ClickRegion:
    """The most stable region of the clicked pixel's feature (module docstring, step 2).

    Args:
        feature_map: [H, W, D] float32 rendered features; x, y: the clicked pixel (column, row).
    """
    from .lifting.query import query_distances

    params = params or ExtractParams()
    height, width = feature_map.shape[:2]
    if not (0 <= x < width and 0 <= y < height):
        raise ConfigError(f"extract: the point ({x}, {y}) lies outside the {width}x{height} view.")
    q = np.ascontiguousarray(feature_map[y, x][None], dtype=np.float32)
    dist = query_distances(np.ascontiguousarray(feature_map, dtype=np.float32), q)[0]
    top = float(dist.max())
    thresholds = (np.arange(1, params.threshold_steps + 1) * (top / params.threshold_steps)).astype(np.float32)
    regions, areas = [], []
    for t in thresholds:
        _, comps = cv2.connectedComponents((dist <= t).astype(np.uint8), connectivity=4)
        region = comps == comps[y, x]
        regions.append(region)
        areas.append(int(region.sum()))
    areas = np.asarray(areas, np.int64)
    delta, total = params.stability_delta, height * width
    scores = np.full(len(thresholds), np.inf)
    for k in range(delta, len(thresholds) - delta):
        if areas[k] >= params.min_region_pixels and areas[k + delta] < params.max_region_fraction * total:
            scores[k] = (areas[k + delta] - areas[k - delta]) / areas[k]
    best, best_score = None, float(scores.min())
    if np.isfinite(best_score):
        # the most stable regions; among near-ties, the widest run of thresholds (a flat object with a
        # blended border is stable both without and with its border ring: the wider plateau is the object)
        near = scores <= best_score + params.stability_tolerance
        runs, k = [], 0
        while k < len(near):
            if near[k]:
                end = k
                while end + 1 < len(near) and near[end + 1]:
                    end += 1
                runs.append((end - k + 1, -k, k, end))
                k = end + 1
            else:
                k += 1
        _, _, first, last = max(runs)
        best = first + int(np.argmin(scores[first: last + 1]))
        best_score = float(scores[best])
    if best is None:
        raise Trace3DError(f"extract: no object region grows from the point ({x}, {y}): every region is smaller than "
                           f"{params.min_region_pixels} pixels or covers {params.max_region_fraction:.0%} of the "
                           "view; click inside an object.")
    return ClickRegion(regions[best], float(thresholds[best]), float(best_score), thresholds, areas)


# ----------------------------------------------------------------------------------------------
# the click's selection in 3D
# ----------------------------------------------------------------------------------------------


class ClickScene:
    """What every click on one lifted scene shares: the seen Gaussians' kNN graph, the feature
    threshold (given, or ``threshold_scale`` x :func:`~trace3d.segment.feature_threshold`) and, for
    ``selection: segment``, the scene's segments (made on first use); the graph's neighbour lists and every
    unseen Gaussian's nearest seen one (:class:`~trace3d.segment.SeenGraph`, made once, not per click).

    Args:
        means: [N, 3] Gaussian centres; features: [N, D] lifted features; weights: [N] summed training
            blending weights (0 = never seen in training).
        shared: a :class:`~trace3d.segment.SeenGraph` of these means, features and weights with
            ``params.neighbours``, if made already (the evaluation's segment score uses the same one).
    """

    def __init__(self, means: np.ndarray, features: np.ndarray, weights: np.ndarray, params: ExtractParams,
                 shared=None):
        from .segment import SeenGraph

        self.shared = shared if shared is not None else SeenGraph(means, features, weights, params.neighbours)
        self.means = self.shared.means
        self.features = self.shared.features
        self.weights = self.shared.weights
        self.params = params
        self.seen = self.shared.seen
        self.graph = self.shared.graph
        if params.threshold is not None:
            self.data_threshold = None
            self.threshold = float(params.threshold)
        else:
            self.data_threshold = self.shared.threshold(params.pairs, params.seed)
            self.threshold = params.threshold_scale * self.data_threshold
        self.last_threshold = self.threshold  # the threshold of the latest click (``stable``: its own)
        self._segments = None

    def segments(self):
        """The scene's :class:`~trace3d.segment.SceneSegments` with the default segment parameters and
        this scene's ``neighbours`` (made once)."""
        from .segment import SegmentParams, segment_gaussians

        if self._segments is None:
            sp = SegmentParams(neighbours=self.params.neighbours, pairs=self.params.pairs, seed=self.params.seed)
            self._segments = segment_gaussians(self.means, self.features, self.weights, sp, self.shared)
        return self._segments

    def _unseen_follow(self, keep_seen: np.ndarray) -> np.ndarray:
        """[N] bool from the seen Gaussians' choice [S]: an unseen Gaussian follows its nearest seen one."""
        keep = np.zeros(len(self.means), bool)
        keep[self.seen] = keep_seen
        unseen, nearest = self.shared.nearest_seen()
        if unseen.size:
            keep[unseen] = keep_seen[nearest]
        return keep

    def select(self, query: np.ndarray, seeds: np.ndarray, seed_weights: np.ndarray | None = None) -> np.ndarray:
        """[N] bool: the clicked object.

        Args:
            query: [D] the rendered feature at the clicked pixel (used when ``seed_weights`` is None).
            seeds: [K] indices of the Gaussians that blend into the clicked pixel; seed_weights: [K] their
                blending weights there: the query is then the feature of the Gaussian with the most weight
                (``segment``: the segment with the most weight wins).
        """
        seeds = np.asarray(seeds, np.int64)
        if self.params.selection == "region":
            raise ValueError("ClickScene selects by features or segment; selection: region grows a 2D region "
                             "(run_extract, evaluate_clicks)")
        if self.params.selection == "segment":
            seg = self.segments()
            w = np.ones(seeds.size) if seed_weights is None else np.asarray(seed_weights, np.float64)
            labels = seg.instance[seeds]
            hit = labels > 0
            if not hit.any():
                return np.zeros(len(self.means), bool)
            votes = np.bincount(labels[hit], weights=w[hit], minlength=seg.count + 1)
            return seg.instance == int(np.argmax(votes))
        query = np.asarray(query, np.float64)
        if seed_weights is not None and seeds.size:
            # the feature of the surface clicked on, from the Gaussians there (a rendered feature at an
            # object's border blends two objects' features)
            query = click_query(self.features[seeds], np.asarray(seed_weights, np.float64), self.params.query,
                                self.params.query_min_weight)
        inside = np.isin(seeds, self.seen)
        local = np.searchsorted(self.seen, seeds[inside])
        if self.params.threshold is not None or self.params.threshold_rule == "data":
            self.last_threshold = self.threshold
            return self._unseen_follow(select_connected(self.shared.seen_features, query, self.graph.edges, local,
                                                        self.threshold))
        # the largest threshold tried: a point farther from the click is never selected
        limit = self.threshold * self.params.stable_max_scale
        reach = self.click_distances(query, local, limit)
        self.last_threshold = stable_threshold(reach, self.shared.seen_weights, self.threshold, self.params)
        return self._unseen_follow(reach <= self.last_threshold)

    def click_distances(self, query: np.ndarray, seeds: np.ndarray, limit: float = np.inf) -> np.ndarray:
        """:func:`click_distances` of the seen Gaussians (``seeds``: positions in ``seen``) over the scene's
        graph, by :func:`~trace3d.segment.bottleneck_distances` on its neighbour lists (made once): the same
        bits (tests/objects/test_segclick.py)."""
        from .lifting.kernels.query import row_distances
        from .segment import bottleneck_distances

        d = row_distances(self.shared.seen_features, np.asarray(query, np.float64))
        indptr, neighbours = self.shared.neighbour_lists()
        return bottleneck_distances(d, indptr, neighbours, seeds, limit)


def click_query(features: np.ndarray, weights: np.ndarray, rule: str = "medoid", min_weight: float = 0.25) -> np.ndarray:
    """[D] float64: the query feature of a click from the features [K, D] of the Gaussians under it and
    their blending weights [K] there. ``top``: the feature with the most weight (ties: the first);
    ``medoid``: of the features whose weight is at least ``min_weight`` x the largest, the one whose
    weighted sum of distances to all K features is least (ties: the first), i.e. the feature most of
    the click's weight agrees with: a heavy stray Gaussian (a floater, the support seen through a gap)
    does not become the query when the other heavy ones, on the object, agree with each other."""
    features = np.asarray(features, np.float64)
    weights = np.asarray(weights, np.float64)
    if rule == "top" or len(features) < 3:
        return features[int(np.argmax(weights))]
    diff = features[:, None, :] - features[None, :, :]
    cost = np.sqrt((diff * diff).sum(-1)) @ weights
    cost[weights < min_weight * weights.max()] = np.inf
    return features[int(np.argmin(cost))]


def click_distances(features: np.ndarray, query: np.ndarray, edges: np.ndarray, seeds: np.ndarray,
                    limit: float = np.inf) -> np.ndarray:
    """[S] float64: for every point the least threshold t at which :func:`select_connected` (``features``,
    ``query``, ``edges``, ``seeds``, t) selects it (inf: at none), i.e. over the paths from a seed to the
    point along ``edges`` the least largest feature distance to ``query`` of the path's points: the
    selection at t is ``click_distances(...) <= t`` for every t at once.

    Computed on a minimum spanning tree (which holds a least-bottleneck path between any two points) of
    the graph with edge weights max(d_a, d_b) and a root joined to every seed by d_seed, then down the tree
    from the root. Points beyond ``limit`` (the edges to them are left out) get inf. Twin:
    :func:`click_distances_reference`.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree

    count = len(features)
    d = np.sqrt(((np.asarray(features, np.float64) - np.asarray(query, np.float64)[None, :]) ** 2).sum(1))
    reach = np.full(count, np.inf)
    seeds = np.unique(np.asarray(seeds, np.int64))
    seeds = seeds[d[seeds] <= limit]
    if not seeds.size:
        return reach
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    weight = np.maximum(d[edges[:, 0]], d[edges[:, 1]])
    edges, weight = edges[weight <= limit], weight[weight <= limit]
    rows = np.concatenate([edges[:, 0], np.full(seeds.size, count)])
    cols = np.concatenate([edges[:, 1], seeds])
    # + 1: the tree search drops zero weights (a weight of 0 is no edge); the same shift on every edge keeps the tree
    cost = np.concatenate([weight, d[seeds]]) + 1.0
    tree = minimum_spanning_tree(coo_matrix((cost, (rows, cols)), shape=(count + 1, count + 1)).tocsr())
    order, parent = breadth_first_order(tree, count, directed=False, return_predecessors=True)
    # the largest d on each point's path to the root, by pointer jumping: value[v] holds the largest d from
    # v up to (not including) up[v]; each round doubles the stretch, until every point's up is the root
    reached = np.zeros(count + 1, bool)
    reached[order] = True
    up = np.where(reached, parent, count)
    up[count] = count
    value = np.append(np.where(reached[:count], d, np.inf), -np.inf)
    while (up != count).any():
        value = np.maximum(value, value[up])
        up = up[up]
    reach[:] = value[:count]
    return reach


def click_distances_reference(features: np.ndarray, query: np.ndarray, edges: np.ndarray, seeds: np.ndarray,
                              limit: float = np.inf) -> np.ndarray:
    """:func:`click_distances` by a least-bottleneck Dijkstra from the seeds (the twin)."""
    import heapq

    count = len(features)
    d = [float(np.sqrt(((np.asarray(features[i], np.float64) - np.asarray(query, np.float64)) ** 2).sum()))
         for i in range(count)]
    nbrs: list[list[int]] = [[] for _ in range(count)]
    for a, b in np.asarray(edges).reshape(-1, 2).tolist():
        nbrs[a].append(b)
        nbrs[b].append(a)
    reach = [float("inf")] * count
    heap = []
    for s in set(int(v) for v in np.asarray(seeds).tolist()):
        if d[s] > limit:
            continue
        reach[s] = d[s]
        heap.append((d[s], s))
    heapq.heapify(heap)
    while heap:
        key, v = heapq.heappop(heap)
        if key > reach[v]:
            continue
        for u in nbrs[v]:
            nk = max(key, d[u])
            if nk < reach[u] and nk <= limit:
                reach[u] = nk
                heapq.heappush(heap, (nk, u))
    return np.asarray(reach, np.float64)


def stable_threshold(reach: np.ndarray, weights: np.ndarray, base: float, params: ExtractParams) -> float:
    """The click's threshold (``threshold_rule: stable``): among the thresholds t_k = base x the geometric
    steps from ``stable_min_scale`` to ``stable_max_scale``, the one where the click's selection
    (``reach`` <= t, :func:`click_distances`) grows least, in the log of its training weight from
    ``stable_span`` steps below to as many above, plus ``stable_prior`` x |log(t_k / base)|: an object's
    Gaussians join at thresholds below the valley of their distances to the click and its support's
    only above it, where the selection jumps. Thresholds whose selection holds fewer than
    ``stable_min_gaussians`` Gaussians, or (``stable_span`` steps above) more than ``stable_max_share``
    of the scene's weight, are not taken; without any, ``base``. Ties: the smallest.

    Args:
        reach: [S] :func:`click_distances`; weights: [S] training weights; base: the data's threshold.
    """
    p = params
    grid = base * np.exp(np.linspace(np.log(p.stable_min_scale), np.log(p.stable_max_scale), p.stable_steps + 1))
    # only the points a threshold of the grid can select (most are beyond its largest, inf): in a stable
    # sort of every point they come first, in this order, so the counts and sums below are the same bits
    order = np.flatnonzero(reach <= grid[-1])
    order = order[np.argsort(reach[order], kind="stable")]
    sorted_reach = reach[order]
    cum = np.concatenate([[0.0], np.cumsum(np.asarray(weights, np.float64)[order])])
    count = np.searchsorted(sorted_reach, grid, side="right")
    area = cum[count]
    total = float(np.sum(weights))
    span = p.stable_span
    best, best_score = None, np.inf
    for k in range(span, len(grid) - span):
        if count[k] < p.stable_min_gaussians or area[k - span] <= 0 or area[k + span] > p.stable_max_share * total:
            continue
        score = np.log(area[k + span] / area[k - span]) + p.stable_prior * abs(np.log(grid[k] / base))
        if score < best_score:
            best, best_score = k, score
    return float(base if best is None else grid[best])


def select_connected(features: np.ndarray, query: np.ndarray, edges: np.ndarray, seeds: np.ndarray,
                     threshold: float) -> np.ndarray:
    """[S] bool: the points whose feature lies within ``threshold`` of ``query`` and that are linked to a
    seed through edges between such points.

    Args:
        features: [S, D]; query: [D]; edges: [E, 2] point pairs (the kNN graph); seeds: [K] point indices
            (the Gaussians under the click; seeds outside the threshold start nothing).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    count = len(features)
    similar = np.sqrt(((features - query[None, :]) ** 2).sum(1)) <= threshold
    seeds = np.asarray(seeds, np.int64)
    seeds = seeds[similar[seeds]] if seeds.size else seeds
    if not seeds.size:
        return np.zeros(count, bool)
    both = similar[edges[:, 0]] & similar[edges[:, 1]] if len(edges) else np.zeros(0, bool)
    graph = coo_matrix((np.ones(int(both.sum())), (edges[both, 0], edges[both, 1])), shape=(count, count))
    _, labels = connected_components(graph, directed=False)
    return similar & np.isin(labels, np.unique(labels[seeds]))


def select_connected_reference(features: np.ndarray, query: np.ndarray, edges: np.ndarray, seeds: np.ndarray,
                               threshold: float) -> np.ndarray:
    """:func:`select_connected` by a breadth-first walk from the seeds (the twin)."""
    count = len(features)
    similar = [float(np.sqrt(((features[i] - query) ** 2).sum())) <= threshold for i in range(count)]
    nbrs: list[list[int]] = [[] for _ in range(count)]
    for a, b in np.asarray(edges).tolist():
        if similar[a] and similar[b]:
            nbrs[a].append(b)
            nbrs[b].append(a)
    out = np.zeros(count, bool)
    stack = [int(s) for s in seeds if similar[int(s)]]
    for s in stack:
        out[s] = True
    while stack:
        v = stack.pop()
        for u in nbrs[v]:
            if not out[u]:
                out[u] = True
                stack.append(u)
    return out


def click_weights(model, camera, x: int, y: int, radius: int = 1, near: float = 0.01):
    """The :class:`~trace3d.render.pixel_weights.PixelWeights` of the pixels within ``radius`` of (x, y)
    only (what :func:`click_seeds` reads; a full view's weights cost a trace of every pixel)."""
    from .render.pixel_weights import pixel_weights

    pixels = [yy * camera.width + xx for yy in range(y - radius, y + radius + 1)
              for xx in range(x - radius, x + radius + 1) if 0 <= xx < camera.width and 0 <= yy < camera.height]
    with torch.no_grad():
        return pixel_weights(model.splats(), camera, np.asarray(pixels, np.int64), near)


def click_seeds(weights, x: int, y: int, radius: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """The Gaussians that blend into the pixels within ``radius`` of (x, y) of a view's full
    :class:`~trace3d.render.pixel_weights.PixelWeights`, and their summed blending weight there:
    indices [K] (ascending), weights [K]."""
    wanted = [yy * weights.width + xx for yy in range(y - radius, y + radius + 1)
              for xx in range(x - radius, x + radius + 1) if 0 <= xx < weights.width and 0 <= yy < weights.height]
    rows = np.flatnonzero(np.isin(weights.pixels, wanted))
    if not rows.size:
        return np.zeros(0, np.int64), np.zeros(0)
    idx = np.concatenate([weights.indices[weights.indptr[r]: weights.indptr[r + 1]] for r in rows]).astype(np.int64)
    val = np.concatenate([weights.weights[weights.indptr[r]: weights.indptr[r + 1]] for r in rows]).astype(np.float64)
    ids, inverse = np.unique(idx, return_inverse=True)
    return ids, np.bincount(inverse, weights=val, minlength=ids.size)


def connected_to_seeds(means: np.ndarray, seeds: np.ndarray, link_scale: float) -> np.ndarray:
    """[K] bool: the points of ``means`` [K, 3] chained to any of ``seeds`` [K] bool by links shorter than
    ``link_scale`` times the median nearest-neighbour distance."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    count = len(means)
    if count < 2 or not seeds.any():
        return seeds.copy()
    tree = cKDTree(means)
    nearest = tree.query(means, k=2)[0][:, 1]
    link = link_scale * float(np.median(nearest))
    pairs = tree.query_pairs(link, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(count, count))
    _, labels = connected_components(graph, directed=False)
    return np.isin(labels, np.unique(labels[seeds]))


def _gaussians_at(weights, x: int, y: int, radius: int = 1) -> np.ndarray:
    """Indices of the Gaussians that blend into the pixels within ``radius`` of (x, y) of a view's full
    :class:`~trace3d.render.pixel_weights.PixelWeights`."""
    wanted = {yy * weights.width + xx for yy in range(y - radius, y + radius + 1)
              for xx in range(x - radius, x + radius + 1) if 0 <= xx < weights.width and 0 <= yy < weights.height}
    rows = np.flatnonzero(np.isin(weights.pixels, list(wanted)))
    parts = [weights.indices[weights.indptr[r]: weights.indptr[r + 1]] for r in rows]
    return np.unique(np.concatenate(parts)).astype(np.int64) if parts else np.zeros(0, np.int64)


def _mark_click(image: np.ndarray, x: int, y: int) -> np.ndarray:
    out = image.copy()
    size = max(2, min(image.shape[:2]) // 30)
    color = np.array([255, 0, 255], np.uint8)
    out[max(0, y - size): y + size + 1, x] = color
    out[y, max(0, x - size): x + size + 1] = color
    return out


def _tile(images: list[np.ndarray], height: int) -> np.ndarray:
    """Images side by side at one height (each resized, aspect kept), 2-pixel gaps."""
    tiles = []
    for image in images:
        scale = height / image.shape[0]
        width = max(1, round(image.shape[1] * scale))
        tiles.append(cv2.resize(image, (width, height), interpolation=cv2.INTER_NEAREST))
        tiles.append(np.full((height, 2, 3), 255, np.uint8))
    return np.concatenate(tiles[:-1], axis=1)


def object_mask(model, camera, keep: np.ndarray, near: float = 0.01) -> np.ndarray:
    """[H, W] bool: the pixels of ``camera`` where the Gaussians ``keep`` [N] bool hold more of the
    rendered blending weight than the others (occluders included)."""
    from .lifting.contrastive import instance_map

    return instance_map(model, camera, np.where(keep, 1, 2).astype(np.int64), 2, near) == 1


def _select_region(lifted, model, camera, feature_map: np.ndarray, x: int, y: int, p: ExtractParams):
    """``selection: region``: the 2D region grown from the click queried as a reference mask, then (with
    ``connected``) the traced Gaussians linked in 3D to those under the click. Returns keep [N] bool, the
    query's mask at the clicked view and the facts for extract.json."""
    from .lifting import ObjectQuery

    region = grow_from_click(feature_map, x, y, p)
    query = ObjectQuery(p.view, region.mask)
    points = lifted.query_points(query)
    keep = np.asarray(lifted.object_gaussians(query), bool).copy()
    traced = int(keep.sum())
    if p.connected and keep.any():
        under = _gaussians_at(lifted.view_weights(camera), x, y)
        seeds = np.zeros(len(model), bool)
        seeds[under] = True
        seeds &= keep
        if seeds.any():
            kept = np.flatnonzero(keep)
            linked = connected_to_seeds(model.means.detach().double().numpy()[kept], seeds[kept], p.link_scale)
            keep[kept[~linked]] = False
        else:
            log.warning("extract: none of the traced Gaussians blends into the clicked pixel; all %d are kept", traced)
    facts = {"threshold": region.threshold, "stability": region.stability, "region_pixels": int(region.mask.sum()),
             "query_points": points.pixels.tolist(), "query_thresholds": points.thresholds.tolist(),
             "reference_iou": float(points.ious[-1]) if len(points.ious) else None, "gaussians_traced": traced}
    return keep, points.mask(feature_map), facts


def run_extract(scene, poses_dir: Path | None, gaussians_dir: Path, lift_dir: Path, out_dir: Path,
                params: dict) -> dict:
    """Extract the clicked object of a contrastive lift into ``out_dir``; returns extract.json's content."""
    from .evaluation.extraction import render_alone
    from .evaluation.pictures import overlay, world_up, write_turntable
    from .lifting import load_lifted
    from .lifting.query import FeatureLifted
    from .scene import write_rgb
    from .tracing.git import load_fitted

    p = from_mapping(ExtractParams, params, "extract params")
    if not p.view:
        raise ConfigError("extract: name the clicked training view (--view or params.view).")
    if len(p.point) != 2:
        raise ConfigError(f"extract: the point must be (x, y) (--point X,Y or params.point), got {list(p.point)}.")
    start = time.perf_counter()
    model, cameras = load_fitted(scene, poses_dir, gaussians_dir)
    train = [c for c in cameras if c.split == "train"]
    lifted = load_lifted(lift_dir, model, scene, train)
    if not isinstance(lifted, FeatureLifted):
        method = json.loads((Path(lift_dir) / "lift.json").read_text()).get("method")
        raise Trace3DError(f"{lift_dir}: extract by a click needs a contrastive lift (features.npy); this lift's "
                           f"method is {method!r}.")
    by_name = {c.name: c for c in train}
    if p.view not in by_name:
        shown = ", ".join(sorted(by_name)[:6]) + (" ..." if len(by_name) > 6 else "")
        raise ConfigError(f"extract: view {p.view!r} is not a training view of {scene.root} ({shown}).")
    camera = by_name[p.view]
    x, y = int(np.floor(p.point[0])), int(np.floor(p.point[1]))
    if not (0 <= x < camera.width and 0 <= y < camera.height):
        raise ConfigError(f"extract: the point ({x}, {y}) lies outside the {camera.width}x{camera.height} view.")
    feature_map = lifted.feature_map(camera)
    facts: dict = {}
    if p.selection == "region":
        keep, mask, facts = _select_region(lifted, model, camera, feature_map, x, y, p)
    else:
        click = ClickScene(model.means.detach().double().numpy(), lifted.features, lifted.visibility(), p)
        seeds, seed_weights = click_seeds(click_weights(model, camera, x, y, near=lifted.params.near), x, y)
        keep = click.select(feature_map[y, x], seeds, seed_weights)
        facts = {"threshold": click.last_threshold, "threshold_rule": p.threshold_rule if p.threshold is None else "given",
                 "data_threshold": click.data_threshold, "seeds": int(seeds.size)}
        if p.selection == "segment":
            seg = click.segments()
            label = int(np.bincount(seg.instance[keep]).argmax()) if keep.any() else 0
            facts["segment"] = {"id": label, "stuff": bool(seg.stuff[label - 1]) if label else None,
                                "threshold": seg.threshold}
        mask = object_mask(model, camera, keep)
    if not keep.any():
        raise Trace3DError(f"extract: the click ({x}, {y}) on {p.view} selects no Gaussian ({p.selection} selection); "
                           "click inside an object.")
    obj = model.subset(torch.from_numpy(keep))
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    obj.write_ply(out_dir / "object.ply")
    # the picture: the clicked view with the click and the object's mask there, then the object alone
    image = scene.image(p.view)
    panels = [_mark_click(image, x, y),
              _mark_click((overlay(image.astype(np.float32) / 255.0, mask) * 255 + 0.5).astype(np.uint8), x, y)]
    # the training views that show the most of the object alone, the clicked view first
    shown = []
    for k, cam in enumerate(train):
        rgb, alpha = render_alone(obj, cam)
        shown.append((cam.name != p.view, -int((alpha > 0.5).sum()), k, rgb))
    renders = {}
    for _, pixels, k, rgb in sorted(shown, key=lambda item: item[:3])[: p.picture_views]:
        renders[train[k].name] = -pixels
        panels.append((np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8))
    write_rgb(out_dir / "object.png", _tile(panels, max(96, camera.height)))
    if p.turntable_views:
        write_turntable(out_dir / "turntable.png", obj, world_up(train), p.turntable_views, p.turntable_size)
    info = {
        "view": p.view, "point": [x, y], "selection": p.selection, **facts, "mask_pixels": int(mask.sum()),
        "gaussians": int(keep.sum()), "gaussians_total": int(len(model)),
        "picture_views": list(renders), "params": to_dict(p), "lift": str(Path(lift_dir)),
        "seconds": time.perf_counter() - start,
    }
    write_json(out_dir / "extract.json", info)
    log.info("extract: (%d, %d) on %s, %s selection -> %d of %d Gaussians, a %d-pixel mask there -> %s", x, y, p.view,
             p.selection, info["gaussians"], len(model), info["mask_pixels"], out_dir / "object.ply")
    return info
