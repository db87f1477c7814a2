"""The scene's objects without ground truth: ``trace3d segment`` on a contrastively lifted scene.

For a capture with no ground truth (a user's photos or ``transforms.json``, masks from the ``geometry``
or ``graph`` source), the objects are what the lift separates *and* what hangs together in 3D
(``method: graph``, the default; :func:`segment_gaussians`):

1. **Graph**: the k nearest neighbours (``neighbours`` = 12) of every Gaussian seen in training
   (summed training blending weight > 0), by centre (:func:`gaussian_graph`).
2. **Threshold from the data**: contrastive lifting pulls an instance's features together and pushes
   other instances' apart, so neighbours in 3D (mostly on one object) have close features and random
   pairs of Gaussians (mostly on two objects) far ones; the join threshold is ``threshold_scale`` (1)
   times the distance at which the two samples' error shares are equal (:func:`feature_threshold`).
3. **Growing**: the graph's edges in order of feature distance (Kruskal's order) join their two
   segments when the two segments' weighted mean features are within the threshold
   (:func:`_merge_edges`, a union-find): a chain of similar neighbours cannot leak from one object into
   the next, because the segments' means must agree, not only the two Gaussians at the border.
4. **Minimum size**: a segment with less than ``min_share`` of the training weight, fewer than
   ``min_gaussians`` Gaussians, or a longest side under ``min_size`` of the scene's (3D, robust
   principal extents) joins the adjacent segment (over the kNN edges) with the nearest mean feature,
   smallest first, until none is left; one with no neighbour at all is dropped. Gaussians never seen
   in training take their nearest seen neighbour's segment.
5. **Stuff**: a segment whose thickness is at most ``flat_ratio`` of its second side and whose two
   in-plane sides are at least ``stuff_size`` of the scene's longest side is a large planar surface
   (wall, floor): it is reported under ``stuff`` (``stuff/<k>.ply``), not as an object.

``method: features`` is the step before issue 48 (the features alone, clustered as the PQ^scene
evaluation clusters them: :func:`~trace3d.evaluation.panoptic.cluster_features`, then clusters that win
fewer than ``min_pixels`` training pixels are dropped); ``method: hdbscan_graph`` splits those clusters
into their pieces connected in 3D (light pieces go back to their cluster's heaviest one) and then runs
steps 4 and 5. The choice of the defaults (measured on development rooms): docs/objects.md.

**Files**: per object its Gaussians (``objects/<k>.ply``, the 3DGS/2DGS layout of
:meth:`~trace3d.gaussians.GaussianModel.write_ply`) and the object alone from ``turntable_views``
directions (``objects/<k>.png``, :func:`~trace3d.evaluation.pictures.turntable_strip`, as the evaluate
step draws its objects). Objects are numbered 1, 2, ... by the training pixels they win (every training
pixel goes to the segment with the largest rendered weight), largest first.

Writes into ``out_dir``: ``objects/<k>.ply``, ``objects/<k>.png``, ``stuff/<k>.ply``,
``contact_sheet.png`` (every object's turntable strip, one row per object with its number, in order)
and ``segment.json`` (per object and stuff segment: ``gaussians``, ``views`` seen = training views where
it wins at least one pixel, ``pixels`` won over all training views, ``cluster``; the threshold and the
stages' counts, the dropped segments and the settings).
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
from numba import njit

from .errors import Trace3DError
from .io import write_json
from .params import from_mapping, to_dict

log = logging.getLogger(__name__)


@dataclasses.dataclass
class SegmentParams:
    """Parameters of ``trace3d segment`` (``--params``).

    Attributes:
        method: ``graph`` (default): the lifted features over the Gaussians' 3D neighbourhood graph
            (module docstring); ``features``: HDBSCAN of the features alone, as the PQ^scene evaluation's
            ``panoptic`` clusters them (the step before issue 48); ``hdbscan_graph``: those clusters split
            into their pieces connected in 3D, then the size and stuff steps of ``graph``.
        neighbours: k of the kNN graph over the Gaussians' centres.
        feature_threshold: two segments join when their mean features are closer than this; ``None``:
            ``threshold_scale`` times the distance that tells same-object pairs from other-object pairs
            in this lift (:func:`feature_threshold`).
        threshold_scale: see ``feature_threshold``.
        pairs: random pairs of Gaussians drawn for that threshold (with ``seed``).
        min_share: a segment holds at least this share of the summed training blending weight (about
            its share of the training pixels); ``features``: HDBSCAN's minimum cluster size as a share
            of ``samples`` (as ``panoptic_min_share``).
        min_size: a segment's longest side is at least this share of the scene's longest side (3D).
        min_gaussians: a segment (a cluster) with fewer Gaussians is not an object.
        flat_ratio, stuff_size: a segment is stuff (a wall, the floor) when its thickness is at most
            ``flat_ratio`` of its second side and both its in-plane sides are at least ``stuff_size`` of
            the scene's longest side.
        samples: ``features`` and ``hdbscan_graph``: Gaussians clustered (as ``panoptic_samples``).
        seed: the seed of the random pairs and of the clustered Gaussians' draw.
        min_pixels: ``features`` only: a cluster winning fewer training pixels (over all views together)
            is not an object; ``None``: ``min_share`` of all the training views' pixels (at least 1).
        turntable_views, turntable_size: each object's ``objects/<k>.png`` strip (views, pixels per side).
        near: the renders' near plane.
    """

    method: Literal["graph", "hdbscan_graph", "features"] = "graph"
    neighbours: int = 12
    feature_threshold: float | None = None
    threshold_scale: float = 1.0
    pairs: int = 100000
    min_share: float = 0.001
    min_size: float = 0.02
    min_gaussians: int = 20
    flat_ratio: float = 0.2
    stuff_size: float = 0.2
    samples: int = 8000
    seed: int = 0
    min_pixels: int | None = None
    turntable_views: int = 8
    turntable_size: int = 96
    near: float = 0.01

    def __post_init__(self) -> None:
        if self.neighbours < 1:
            raise ValueError(f"neighbours must be >= 1, got {self.neighbours}")
        if self.feature_threshold is not None and not self.feature_threshold > 0:
            raise ValueError(f"feature_threshold must be > 0 (or null), got {self.feature_threshold}")
        if self.samples < 2:
            raise ValueError(f"samples must be >= 2, got {self.samples}")
        if not 0.0 < self.min_share < 1.0:
            raise ValueError(f"min_share must be in (0, 1), got {self.min_share}")
        if not 0.0 <= self.min_size < 1.0:
            raise ValueError(f"min_size must be in [0, 1), got {self.min_size}")
        if not 0.0 < self.flat_ratio < 1.0 or not 0.0 < self.stuff_size <= 1.0:
            raise ValueError(f"flat_ratio must be in (0, 1) and stuff_size in (0, 1], got {self.flat_ratio}, "
                             f"{self.stuff_size}")
        if self.min_gaussians < 1:
            raise ValueError(f"min_gaussians must be >= 1, got {self.min_gaussians}")
        if self.min_pixels is not None and self.min_pixels < 1:
            raise ValueError(f"min_pixels must be >= 1 (or null), got {self.min_pixels}")
        if self.turntable_views < 1 or self.turntable_size < 8:
            raise ValueError("turntable_views must be >= 1 and turntable_size >= 8")


# ----------------------------------------------------------------------------------------------
# the Gaussians' neighbourhood graph and its partition by lifted features
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass
class GaussianGraph:
    """The k-nearest-neighbour graph over the centres of the *seen* Gaussians (``seen`` [S] indices into
    the model): ``edges`` [E, 2] (i < j, positions in ``seen``; a pair once, whichever end found the
    other) and their lengths [E]."""

    seen: np.ndarray
    edges: np.ndarray
    lengths: np.ndarray


def gaussian_graph(means: np.ndarray, seen: np.ndarray, neighbours: int) -> GaussianGraph:
    """The kNN graph of ``means[seen]`` (``means`` [N, 3], ``seen`` [S] indices; ties of the tree
    search are broken by index, so the graph is deterministic)."""
    from scipy.spatial import cKDTree

    points = np.ascontiguousarray(means[seen], np.float64)
    count = len(points)
    k = min(neighbours, count - 1)
    if k < 1:
        return GaussianGraph(seen, np.zeros((0, 2), np.int64), np.zeros(0))
    dist, idx = cKDTree(points).query(points, k=k + 1)
    rows = np.repeat(np.arange(count), k)
    cols = idx[:, 1:].ravel()
    lengths = dist[:, 1:].ravel()
    ok = cols < count  # cKDTree pads with `count` when fewer points exist
    rows, cols, lengths = rows[ok], cols[ok], lengths[ok]
    lo, hi = np.minimum(rows, cols), np.maximum(rows, cols)
    key = lo.astype(np.int64) * count + hi
    order = np.argsort(key, kind="stable")
    key, lo, hi, lengths = key[order], lo[order], hi[order], lengths[order]
    first = np.ones(len(key), bool)
    first[1:] = key[1:] != key[:-1]
    edges = np.stack([lo[first], hi[first]], 1).astype(np.int64)
    return GaussianGraph(seen, edges, lengths[first])


def feature_threshold(features: np.ndarray, weights: np.ndarray, edges: np.ndarray, pairs: int, seed: int,
                      near: np.ndarray | None = None, order: np.ndarray | None = None) -> float:
    """The feature distance that tells "the same object" from "another object" in a lifted scene, from
    the data alone: the equal-error point between two samples of distances,

    * neighbours in 3D (the kNN graph's ``edges`` [E, 2], each weighted by its lighter end's weight):
      mostly pairs on one object, and
    * ``pairs`` random pairs (each end drawn with probability proportional to ``weights`` [S], seeded):
      mostly pairs on two objects, the more so the more objects the scene has,

    i.e. the distance t at which the share of neighbour pairs farther than t plus the share of
    other-object pairs closer than t is least: where the two distance densities cross (the valley
    between them; in an empty gap, the gap's middle). Contrastive lifting pulls an instance's features
    together and pushes other instances' apart. The random pairs that fall on one object are taken out
    first: their share is estimated as twice the share of random pairs closer than the neighbours'
    median distance.
    Measured on development lifts (docs/objects.md) it lies at 4-12.

    ``near`` [E] and ``order`` [E]: the edges' feature distances (:func:`edge_distances`) and their stable
    ascending order, if computed already (:class:`SeenGraph`); the same values either way."""
    features = np.asarray(features, np.float64)
    weights = np.asarray(weights, np.float64)
    if len(features) < 2 or not len(edges):
        return 1.0
    if near is None:
        near = edge_distances(features, edges)
    near_w = np.minimum(weights[edges[:, 0]], weights[edges[:, 1]])
    rng = np.random.default_rng(seed)
    p = weights / weights.sum()
    a = rng.choice(len(features), size=pairs, p=p)
    b = rng.choice(len(features), size=pairs, p=p)
    far = np.sort(np.sqrt(((features[a] - features[b]) ** 2).sum(1)))
    if order is None:
        order = np.argsort(near, kind="stable")
    near, cum = near[order], np.cumsum(near_w[order])
    median = near[min(np.searchsorted(cum, 0.5 * cum[-1]), near.size - 1)]
    # random pairs on one object (many in a scene of few objects: a wall and a plant) are as close as
    # neighbours: their share is twice the random pairs' share under the neighbours' median distance,
    # and the pairs on two objects are what is left
    same = min(0.99, 2.0 * np.searchsorted(far, median, side="right") / far.size)
    grid = np.unique(np.concatenate([near, far]))
    k = np.searchsorted(near, grid, side="right")
    near_cdf = np.where(k > 0, cum[np.maximum(k - 1, 0)], 0.0) / cum[-1]  # share of neighbours <= t
    far_cdf = np.searchsorted(far, grid, side="right") / far.size  # share of random pairs <= t
    other_cdf = np.clip((far_cdf - same * near_cdf) / (1.0 - same), 0.0, 1.0)
    # the errors of the cut at t: neighbours beyond it, other-object pairs within it; their sum is least
    # where the two densities cross (in an empty gap between them: along the whole gap, whose middle is taken)
    error = (1.0 - near_cdf) + other_cdf
    best = np.flatnonzero(error <= error.min() + 1e-3)
    first = best[0]
    last = first
    while last + 1 < grid.size and error[last + 1] <= error.min() + 1e-3:
        last += 1
    upper = grid[last + 1] if last + 1 < grid.size else grid[last]
    return float(0.5 * (grid[first] + upper))


def edge_distances(features: np.ndarray, edges: np.ndarray, block: int = 1 << 14) -> np.ndarray:
    """[E] float64: the feature distance between the two ends of every edge (``features`` [S, D] float64),
    ``block`` edges at a time (the bits of ``sqrt(((f[a] - f[b]) ** 2).sum(1))`` over all edges at once,
    row by row the same operations, without its [E, D] temporaries: on a default room they cost more in
    fresh memory than in arithmetic)."""
    out = np.empty(len(edges))
    for lo in range(0, len(edges), block):
        diff = features[edges[lo:lo + block, 0]]
        diff -= features[edges[lo:lo + block, 1]]
        diff *= diff
        np.sqrt(diff.sum(1), out=out[lo:lo + block])
    return out


def _lexsorted(edges: np.ndarray) -> bool:
    """Whether the edges [E, 2] are in strictly ascending (first end, second end) order (as
    :func:`gaussian_graph` lists them)."""
    if len(edges) < 2:
        return True
    a, b = edges[:-1], edges[1:]
    return bool(((a[:, 0] < b[:, 0]) | ((a[:, 0] == b[:, 0]) & (a[:, 1] < b[:, 1]))).all())


class SeenGraph:
    """What the segment and click steps derive from one lifted scene's seen Gaussians, each computed once
    on first use and then shared: the kNN graph (:func:`gaussian_graph`), the seen Gaussians' features
    and weights, the edges' feature distances and their ascending order, the data's feature threshold
    per (pairs, seed) (:func:`feature_threshold`), every unseen Gaussian's nearest seen one, and the graph
    as neighbour lists (for :func:`bottleneck_distances`). The evaluation's segment and click scores use
    one; a caller without one gets one of its own (the same values: the same functions on the same inputs).

    Args:
        means: [N, 3] centres; features: [N, D] lifted features; weights: [N] summed training blending
            weights (> 0: seen); neighbours: k of the graph; graph: the seen Gaussians' graph if made already.
    """

    def __init__(self, means: np.ndarray, features: np.ndarray, weights: np.ndarray, neighbours: int,
                 graph: GaussianGraph | None = None):
        self.means = np.asarray(means, np.float64)
        self.features = np.asarray(features, np.float64)
        self.weights = np.asarray(weights, np.float64)
        self.seen = np.flatnonzero(self.weights > 0)
        self.neighbours = int(neighbours)
        self.graph = graph if graph is not None else gaussian_graph(self.means, self.seen, self.neighbours)
        self.seen_features = self.features[self.seen]
        self.seen_weights = self.weights[self.seen]
        self._distances = None
        self._order = None
        self._thresholds: dict = {}
        self._nearest = None
        self._lists = None

    def distances(self) -> np.ndarray:
        """[E] the edges' feature distances (:func:`edge_distances`)."""
        if self._distances is None:
            edges = self.graph.edges
            self._distances = edge_distances(self.seen_features, edges) if len(edges) else np.zeros(0)
        return self._distances

    def order(self) -> np.ndarray:
        """[E] the edges by ascending feature distance, ties in edge order (a stable sort)."""
        if self._order is None:
            self._order = np.argsort(self.distances(), kind="stable")
        return self._order

    def grow_order(self) -> np.ndarray:
        """The edges by ascending feature distance, ties by their (first, second) ends: :meth:`order` when
        the edges are listed in that order already (:func:`gaussian_graph`'s), else a lexsort."""
        edges = self.graph.edges
        if _lexsorted(edges):
            return self.order()
        return np.lexsort((edges[:, 1], edges[:, 0], self.distances()))

    def threshold(self, pairs: int, seed: int) -> float:
        """:func:`feature_threshold` of the seen Gaussians over the graph's edges (made once per pairs, seed)."""
        key = (int(pairs), int(seed))
        if key not in self._thresholds:
            edges = self.graph.edges
            ready = len(self.seen) >= 2 and len(edges)
            self._thresholds[key] = feature_threshold(self.seen_features, self.seen_weights, edges, pairs, seed,
                                                      self.distances() if ready else None,
                                                      self.order() if ready else None)
        return self._thresholds[key]

    def nearest_seen(self) -> tuple[np.ndarray, np.ndarray]:
        """The unseen Gaussians [U] (indices into the model) and each one's nearest seen Gaussian [U]
        (a position in ``seen``; a k-d tree of the seen centres, ties by index); empty when none is unseen
        or none is seen."""
        if self._nearest is None:
            from scipy.spatial import cKDTree

            unseen = np.flatnonzero(self.weights <= 0)
            if unseen.size and self.seen.size:
                _, nearest = cKDTree(self.means[self.seen]).query(self.means[unseen], k=1)
                self._nearest = (unseen, np.asarray(nearest, np.int64))
            else:
                self._nearest = (np.zeros(0, np.int64), np.zeros(0, np.int64))
        return self._nearest

    def neighbour_lists(self) -> tuple[np.ndarray, np.ndarray]:
        """The graph as CSR neighbour lists over the seen Gaussians: indptr [S + 1], neighbours [2E] (each
        edge from both ends)."""
        if self._lists is None:
            self._lists = neighbour_lists(self.graph.edges, len(self.seen))
        return self._lists


def neighbour_lists(edges: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR neighbour lists of the undirected ``edges`` [E, 2] over ``count`` points: indptr [count + 1] int64
    and neighbours [2E] int64 (each point's in edge order)."""
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    ends = np.concatenate([edges[:, 0], edges[:, 1]])
    others = np.concatenate([edges[:, 1], edges[:, 0]])
    order = np.argsort(ends, kind="stable")
    indptr = np.zeros(count + 1, np.int64)
    np.cumsum(np.bincount(ends, minlength=count), out=indptr[1:])
    return indptr, np.ascontiguousarray(others[order])


@njit(cache=True)
def _bottleneck_reach(indptr, neighbours, d, order, seeds, limit):
    """:func:`bottleneck_distances`' kernel: a Dijkstra over the least largest ``d`` of a path, whose queue
    is ``d``'s ascending ``order``. A point reached from a point at level ``key`` gets ``key`` when its own
    d is at most ``key`` (it joins the level's flood, a stack) and its own d otherwise (its final value
    too: every path to it holds it); such points, and the seeds, are the levels to come, each flooded from
    when the walk along ``order`` comes to it (it comes after the level that reached it: its d is larger).
    Points with d > limit are never entered."""
    count = d.shape[0]
    reach = np.full(count, np.inf)
    level = np.zeros(count, np.bool_)  # reached at its own d: a level to flood from
    stack = np.empty(count, np.int64)
    for i in range(seeds.shape[0]):
        s = seeds[i]
        if d[s] <= limit and reach[s] == np.inf:
            reach[s] = d[s]
            level[s] = True
    for j in range(order.shape[0]):
        v = order[j]
        if not level[v]:
            continue
        key = d[v]
        top = 1
        stack[0] = v
        while top > 0:
            top -= 1
            x = stack[top]
            for k in range(indptr[x], indptr[x + 1]):
                u = neighbours[k]
                if reach[u] != np.inf or d[u] > limit:
                    continue
                if d[u] <= key:
                    reach[u] = key
                    stack[top] = u
                    top += 1
                else:
                    reach[u] = d[u]
                    level[u] = True
    return reach


def bottleneck_distances(d: np.ndarray, indptr: np.ndarray, neighbours: np.ndarray, seeds: np.ndarray,
                         limit: float = np.inf) -> np.ndarray:
    """[S] float64: per point the least, over the paths from a seed to it along the graph
    (:func:`neighbour_lists`), of the path's largest ``d`` [S] (inf: no path whose points all have
    d <= ``limit``). Every value is one of ``d``'s, so any exact method gives the same bits: this is
    :func:`trace3d.extract.click_distances` (a minimum spanning tree) by a flood kernel walking ``d`` in
    ascending order, its twin ``click_distances_reference`` a plain Dijkstra."""
    seeds = np.unique(np.asarray(seeds, np.int64))
    d = np.ascontiguousarray(d, np.float64)
    # the walk's queue: the points a level can enter (d <= limit; the others are never entered), ascending;
    # ties in any order: the values do not depend on it
    order = np.flatnonzero(d <= limit)
    order = order[np.argsort(d[order])].astype(np.int64, copy=False)
    return _bottleneck_reach(np.ascontiguousarray(indptr, np.int64), np.ascontiguousarray(neighbours, np.int64), d,
                             order, seeds, float(limit))


@njit(cache=True)
def _find(parent, v):
    root = v
    while parent[root] != root:
        root = parent[root]
    while parent[v] != root:
        nxt = parent[v]
        parent[v] = root
        v = nxt
    return root


@njit(cache=True)
def _merge_edges(edges, distances, sums, mass, threshold, parent):
    """Edges in the given order (ascending feature distance): join their ends' components when the
    distance between the two components' mean features is at most ``threshold``; the heavier component's
    root stays (ties: the lower index). ``sums`` [S, D] (weight x feature) and ``mass`` [S] are updated at
    the roots; ``parent`` [S] is the union-find forest."""
    t2 = threshold * threshold
    dim = sums.shape[1]
    for e in range(edges.shape[0]):
        a = _find(parent, edges[e, 0])
        b = _find(parent, edges[e, 1])
        if a == b:
            continue
        d2 = 0.0
        for c in range(dim):
            t = sums[a, c] / mass[a] - sums[b, c] / mass[b]
            d2 += t * t
        if d2 > t2:
            continue
        if mass[b] > mass[a] or (mass[b] == mass[a] and b < a):
            a, b = b, a
        parent[b] = a
        mass[a] += mass[b]
        for c in range(dim):
            sums[a, c] += sums[b, c]


def _roots(parent: np.ndarray) -> np.ndarray:
    """[S] every point's root in the union-find forest ``parent`` [S] (by pointer jumping: each round
    halves the paths; ``parent`` is left as it is). Twin: :func:`_find` per point."""
    roots = np.asarray(parent, np.int64).copy()
    while True:
        up = roots[roots]
        if np.array_equal(up, roots):
            return roots
        roots = up


def _merge_edges_reference(edges, distances, sums, mass, threshold, parent) -> None:
    """:func:`_merge_edges` written plainly in Python (the twin)."""

    def find(v):
        while parent[v] != v:
            v = parent[v]
        return v

    for e in range(len(edges)):
        a, b = find(int(edges[e, 0])), find(int(edges[e, 1]))
        if a == b:
            continue
        d2 = 0.0
        for c in range(sums.shape[1]):
            t = sums[a, c] / mass[a] - sums[b, c] / mass[b]
            d2 += t * t
        if d2 > threshold * threshold:
            continue
        if mass[b] > mass[a] or (mass[b] == mass[a] and b < a):
            a, b = b, a
        parent[b] = a
        mass[a] += mass[b]
        sums[a] += sums[b]


@dataclasses.dataclass
class SceneSegments:
    """Every Gaussian's segment ``instance`` [N] (1..K; 0 = none), per segment whether it is stuff [K]
    bool (a large planar surface: wall, floor), its Gaussian count [K], its summed training-view
    blending weight [K] (about its training pixels) and its 3D extents [K, 3] (longest first); the
    feature threshold and how it was chosen; counts of the stages."""

    instance: np.ndarray
    stuff: np.ndarray
    gaussians: np.ndarray
    weight: np.ndarray
    extents: np.ndarray
    threshold: float
    threshold_source: str
    stats: dict

    @property
    def count(self) -> int:
        return int(self.stuff.size)


def _extents(points: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """[3] the side lengths (longest first) of the weighted point set along its principal axes, robust
    to stray points (a fitted wall has floaters in front of it): the weighted interquartile range of the
    points' coordinates on each axis, over 0.5 (the side of a uniform segment with that range)."""
    w = weights / weights.sum()
    centre = (points * w[:, None]).sum(0)
    d = points - centre
    cov = (d * w[:, None]).T @ d
    _, axes = np.linalg.eigh(cov)
    sides = []
    for axis in axes.T:
        t = d @ axis
        order = np.argsort(t, kind="stable")
        cum = np.cumsum(w[order])
        lo = t[order][min(np.searchsorted(cum, 0.25), len(t) - 1)]
        hi = t[order][min(np.searchsorted(cum, 0.75), len(t) - 1)]
        sides.append((hi - lo) / 0.5)
    return np.sort(np.asarray(sides))[::-1]


def segment_gaussians(means: np.ndarray, features: np.ndarray, weights: np.ndarray, params: "SegmentParams",
                      graph: GaussianGraph | SeenGraph | None = None) -> SceneSegments:
    """Objects of a lifted scene from its features and 3D adjacency (module docstring).

    Args:
        means: [N, 3] Gaussian centres; features: [N, D] lifted features; weights: [N] summed training
            blending weights (0 = never seen: such Gaussians take their nearest seen neighbour's segment).
        graph: the seen Gaussians' :func:`gaussian_graph` if made already, or a :class:`SeenGraph` of these
            means, features and weights (its graph, edge distances, threshold and nearest seen Gaussians
            are then shared with its other users).
    """
    shared = graph if isinstance(graph, SeenGraph) else SeenGraph(means, features, weights, params.neighbours, graph)
    means = shared.means
    weights = shared.weights
    n = len(means)
    seen = shared.seen
    graph = shared.graph
    count = seen.size
    f = shared.seen_features
    w = shared.seen_weights
    edges = graph.edges
    fdist = shared.distances()
    if params.feature_threshold is not None:
        threshold, source = float(params.feature_threshold), "params"
    else:
        base = shared.threshold(params.pairs, params.seed)
        threshold = params.threshold_scale * base
        source = f"{params.threshold_scale:g} x the equal-error distance {base:.4g}"
    if params.method == "graph":
        # 1. grow segments along the kNN edges, in order of feature distance (ties by the edge's ends)
        grow = shared.grow_order()
        parent = np.arange(count, dtype=np.int64)
        sums = f * w[:, None]
        mass = w.copy()
        _merge_edges(np.ascontiguousarray(edges[grow]), np.ascontiguousarray(fdist[grow]), sums, mass, threshold,
                     parent)
        roots = _roots(parent)
    else:
        # 1. HDBSCAN of the features (the PQ^scene clustering), each cluster split into its pieces
        # connected in 3D (kNN edges inside the cluster)
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        from .evaluation.panoptic import cluster_features

        clusters = cluster_features(shared.features, weights, params.samples, params.min_share, params.seed)
        cl = clusters.instance[seen]
        same = cl[edges[:, 0]] == cl[edges[:, 1]]
        linked = coo_matrix((np.ones(int(same.sum())), (edges[same, 0], edges[same, 1])), shape=(count, count))
        roots = connected_components(linked, directed=False)[1] if count else np.zeros(0, np.int64)
        # a piece too light to be an object on its own goes back to its cluster's heaviest piece
        piece_mass = np.bincount(roots, weights=w) if count else np.zeros(0)
        piece_size = np.bincount(roots) if count else np.zeros(0, np.int64)
        piece_cluster = np.zeros(len(piece_mass), np.int64)
        piece_cluster[roots] = cl
        light = (piece_mass < params.min_share * float(w.sum())) | (piece_size < params.min_gaussians)
        heaviest = {}
        for piece in np.argsort(-piece_mass, kind="stable").tolist():
            heaviest.setdefault(int(piece_cluster[piece]), piece)
        target = np.array([heaviest[int(piece_cluster[q])] if light[q] and piece_cluster[q] > 0 else q
                           for q in range(len(piece_mass))], np.int64)
        roots = target[roots]
    _, label = np.unique(roots, return_inverse=True)
    grown = int(label.max() + 1) if count else 0
    # 2. fragments (too few Gaussians, too little weight, too small in 3D) join the adjacent segment
    # (over all kNN edges) whose mean feature is nearest, smallest fragments first, round by round
    scene_side = float(_extents(means[seen], w)[0]) if count > 1 else 0.0
    min_weight = params.min_share * float(w.sum())
    min_side = params.min_size * scene_side
    absorbed = 0
    while True:
        k = int(label.max() + 1) if count else 0
        size = np.bincount(label, minlength=k)
        mass_k = np.bincount(label, weights=w, minlength=k)
        mean_k = np.stack([np.bincount(label, weights=w * f[:, c], minlength=k) for c in range(f.shape[1])], 1) \
            / np.maximum(mass_k, 1e-300)[:, None]
        small = (size < params.min_gaussians) | (mass_k < min_weight)
        big_enough = np.flatnonzero(~small)  # 3D size only for segments that pass the cheap tests
        side = np.zeros(k)
        order = np.argsort(label, kind="stable")
        starts = np.concatenate([[0], np.cumsum(size)])
        for s in big_enough:
            idx = order[starts[s]: starts[s + 1]]
            side[s] = _extents(means[seen[idx]], w[idx])[0] if idx.size > 1 else 0.0
        small |= side < min_side
        a, b = label[edges[:, 0]], label[edges[:, 1]]
        cross = a != b
        a, b = np.concatenate([a[cross], b[cross]]), np.concatenate([b[cross], a[cross]])
        take = small[a]
        a, b = a[take], b[take]
        if a.size == 0:
            break
        d = np.sqrt(((mean_k[a] - mean_k[b]) ** 2).sum(1))
        # per small segment its nearest neighbour (ties: the lower label); small segments first by size
        pick = np.lexsort((b, d, a))
        a, b = a[pick], b[pick]
        first = np.ones(a.size, bool)
        first[1:] = a[1:] != a[:-1]
        a, b = a[first], b[first]
        # each small segment joins its pick; chains resolve through a union-find of the segments
        seg_parent = np.arange(k, dtype=np.int64)
        for s, t in sorted(zip(a.tolist(), b.tolist()), key=lambda st: (size[st[0]], st[0])):
            rs, rt = _find(seg_parent, s), _find(seg_parent, t)
            if rs != rt:
                seg_parent[rs] = rt
                absorbed += 1
        roots_k = np.array([_find(seg_parent, s) for s in range(k)], np.int64)
        _, label = np.unique(roots_k[label], return_inverse=True)
    # segments still small have no neighbour at all: no segment
    k = int(label.max() + 1) if count else 0
    size = np.bincount(label, minlength=k)
    mass_k = np.bincount(label, weights=w, minlength=k)
    order = np.argsort(label, kind="stable")
    starts = np.concatenate([[0], np.cumsum(size)])
    extents = np.zeros((k, 3))
    for s in range(k):
        idx = order[starts[s]: starts[s + 1]]
        if idx.size > 1:
            extents[s] = _extents(means[seen[idx]], w[idx])
    keep = (size >= params.min_gaussians) & (mass_k >= min_weight) & (extents[:, 0] >= min_side)
    # numbered by weight, heaviest first (ties: the lower label)
    ranked = sorted(np.flatnonzero(keep).tolist(), key=lambda s: (-mass_k[s], s))
    number = np.zeros(k + 1, np.int64)
    number[np.asarray(ranked, np.int64)] = np.arange(1, len(ranked) + 1)
    seen_instance = number[label] if count else np.zeros(0, np.int64)
    instance = np.zeros(n, np.int64)
    instance[seen] = seen_instance
    unseen, nearest = shared.nearest_seen()
    if unseen.size and count:
        instance[unseen] = seen_instance[nearest]
    kept = np.asarray(ranked, np.int64)
    ext = extents[kept] if kept.size else np.zeros((0, 3))
    # stuff: planar (thickness under flat_ratio of the second side) and large (both in-plane sides at
    # least stuff_size of the scene's longest side)
    stuff = (ext[:, 2] <= params.flat_ratio * ext[:, 1]) & (ext[:, 1] >= params.stuff_size * scene_side) \
        if kept.size else np.zeros(0, bool)
    stats = {"seen_gaussians": int(count), "edges": int(len(edges)),
             "grown_segments": grown, "absorbed_fragments": absorbed, "dropped_segments": int(k - kept.size),
             "scene_side": scene_side, "min_weight": min_weight, "min_side": min_side}
    return SceneSegments(instance, stuff, size[kept] if kept.size else np.zeros(0, np.int64),
                         mass_k[kept] if kept.size else np.zeros(0), ext, threshold, source, stats)


def contact_sheet(strips: list[np.ndarray], labels: list[str]) -> np.ndarray:
    """[H, W, 3] uint8: the strips [h, w, 3] one under another (2-pixel white gaps), each after a
    square tile with its label; an empty list gives one tile saying so."""
    if not strips:
        tile = np.zeros((48, 160, 3), np.uint8)
        cv2.putText(tile, "no objects", (8, 30), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
        return tile
    width = max(s.shape[1] for s in strips)
    rows = []
    for strip, label in zip(strips, labels):
        h = strip.shape[0]
        tile = np.zeros((h, h, 3), np.uint8)
        scale = max(0.35, h / 96)
        cv2.putText(tile, label, (max(2, h // 8), h // 2 + int(8 * scale)), cv2.FONT_HERSHEY_SIMPLEX, scale,
                    (255, 255, 255), max(1, int(round(scale))), cv2.LINE_AA)
        pad = np.zeros((h, width - strip.shape[1], 3), np.uint8)
        rows.append(np.concatenate([tile, np.full((h, 2, 3), 255, np.uint8), strip, pad], axis=1))
        rows.append(np.full((2, rows[-1].shape[1], 3), 255, np.uint8))
    return np.concatenate(rows[:-1], axis=0)


def run_segment(scene, poses_dir: Path | None, gaussians_dir: Path, lift_dir: Path, out_dir: Path,
                params: dict) -> dict:
    """Cluster a contrastive lift's Gaussians into objects and write them into ``out_dir`` (module
    docstring); returns segment.json's content."""
    from .evaluation.panoptic import cluster_features
    from .lifting.contrastive import instance_map
    from .evaluation.pictures import turntable_strip, world_up
    from .lifting import load_lifted
    from .lifting.query import FeatureLifted
    from .scene import write_rgb
    from .tracing.git import load_fitted

    p = from_mapping(SegmentParams, params, "segment params")
    start = time.perf_counter()
    model, cameras = load_fitted(scene, poses_dir, gaussians_dir)
    train = [c for c in cameras if c.split == "train"]
    if not train:
        raise Trace3DError(f"{scene.root}: segment needs training views; cameras.json has none.")
    lifted = load_lifted(lift_dir, model, scene, train)
    if not isinstance(lifted, FeatureLifted):
        method = json.loads((Path(lift_dir) / "lift.json").read_text()).get("method")
        raise Trace3DError(f"{lift_dir}: segment clusters lifted features and needs a contrastive lift "
                           f"(features.npy); this lift's method is {method!r}.")
    weights = lifted.visibility()
    facts: dict = {}
    if p.method == "features":
        clusters = cluster_features(lifted.features, weights, p.samples, p.min_share, p.seed)
        log.info("segment: %d clusters of %d Gaussians from %d samples (%d noise, min cluster size %d)",
                 clusters.count, len(model), clusters.samples, clusters.noise, clusters.min_cluster_size)
        instance, k, stuff = clusters.instance, clusters.count, np.zeros(clusters.count, bool)
        facts = {"samples": clusters.samples, "noise_samples": clusters.noise,
                 "min_cluster_size": clusters.min_cluster_size}
    else:
        seg = segment_gaussians(model.means.detach().double().numpy(), lifted.features, weights, p)
        log.info("segment: %d segments (%d stuff) of %d Gaussians, feature threshold %.3g (%s)", seg.count,
                 int(seg.stuff.sum()), len(model), seg.threshold, seg.threshold_source)
        instance, k, stuff = seg.instance, seg.count, seg.stuff
        facts = {"threshold": seg.threshold, "threshold_source": seg.threshold_source, **seg.stats}
    # every training pixel to the segment with the largest rendered weight: pixels won and views seen
    pixels = np.zeros(k + 1, np.int64)
    views = np.zeros(k + 1, np.int64)
    for cam in train:
        won = np.bincount(instance_map(model, cam, instance, k, p.near).ravel(), minlength=k + 1)
        pixels += won
        views += won > 0
    gaussians = np.bincount(instance, minlength=k + 1)
    total_pixels = sum(c.width * c.height for c in train)
    if p.method == "features":
        min_pixels = p.min_pixels if p.min_pixels is not None else max(1, int(np.ceil(p.min_share * total_pixels)))
    else:
        min_pixels = 0  # the segments passed the size tests already (weight, Gaussians, 3D size)
    kept, dropped, walls = [], [], []
    for label in range(1, k + 1):
        entry = {"cluster": label, "gaussians": int(gaussians[label]), "views": int(views[label]),
                 "pixels": int(pixels[label])}
        big = entry["gaussians"] >= p.min_gaussians and entry["pixels"] >= max(min_pixels, 1)
        if not big:
            dropped.append(entry)
        else:
            (walls if stuff[label - 1] else kept).append(entry)
    kept.sort(key=lambda e: (-e["pixels"], e["cluster"]))
    walls.sort(key=lambda e: (-e["pixels"], e["cluster"]))
    out_dir = Path(out_dir)
    objects_dir = out_dir / "objects"
    objects_dir.mkdir(parents=True, exist_ok=True)
    up = world_up(train)
    strips, names = [], []
    for number, entry in enumerate(kept, start=1):
        entry["id"] = number
        obj = model.subset(torch.from_numpy(instance == entry["cluster"]))
        obj.write_ply(objects_dir / f"{number}.ply")
        strip = turntable_strip(obj, up, p.turntable_views, p.turntable_size, p.near)
        write_rgb(objects_dir / f"{number}.png", strip)
        strips.append(strip)
        names.append(str(number))
    if walls:
        (out_dir / "stuff").mkdir(exist_ok=True)
    for number, entry in enumerate(walls, start=1):
        entry["id"] = number
        model.subset(torch.from_numpy(instance == entry["cluster"])).write_ply(out_dir / "stuff" / f"{number}.ply")
    write_rgb(out_dir / "contact_sheet.png", contact_sheet(strips, names))
    info = {
        "objects": [{"id": e["id"], "cluster": e["cluster"], "gaussians": e["gaussians"], "views": e["views"],
                     "pixels": e["pixels"]} for e in kept],
        "stuff": [{"id": e["id"], "cluster": e["cluster"], "gaussians": e["gaussians"], "views": e["views"],
                   "pixels": e["pixels"]} for e in walls],
        "dropped": dropped, "clusters": k, **facts, "min_pixels": min_pixels,
        "gaussians_total": int(len(model)), "unclustered_gaussians": int(gaussians[0]),
        "training_views": len(train), "training_pixels": int(total_pixels), "background_pixels": int(pixels[0]),
        "params": to_dict(p), "lift": str(Path(lift_dir)), "seconds": time.perf_counter() - start,
    }
    write_json(out_dir / "segment.json", info)
    log.info("segment: %d objects and %d stuff segments kept, %d dropped, %.1f s -> %s", len(kept), len(walls),
             len(dropped), info["seconds"], objects_dir)
    return info

