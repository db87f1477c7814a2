"""Scene-level instance segmentation from the lifted features alone, scored as PQ^scene.

The query protocols (``extraction``, ``nvs``) hand the lifted scene a ground-truth mask per object,
so an object split into pieces in feature space costs nothing when the query's points land on every
piece. This metric asks nothing of the ground truth until the score:

1. **Clustering** (no ground truth): ``samples`` Gaussians, drawn (seeded, without replacement) with
   probability proportional to their blending weight summed over the training views' pixels, are
   clustered on their lifted features by HDBSCAN (:func:`hdbscan`: mutual-reachability distances
   with ``min_samples`` neighbours, single-linkage tree, condensed with ``min_cluster_size``,
   clusters chosen by excess of mass); every Gaussian takes the cluster with the nearest mean feature. Per-Gaussian features, not rendered pixels: a rendered border pixel blends two objects'
   features, and such blends form clusters of their own. The minimum size is
   ``ceil(samples * min_share)`` = 8 of 8,000: a cluster must cover about ``min_share`` = 0.1 % of
   the training pixels (19 px of a 160x120 view on average; chosen on exact object labels only,
   docs/evaluation.md).
2. **Labelling**: every pixel of the evaluated views gets the instance with the largest rendered
   weight (the Gaussians' one-hot instance indicators rendered like features, argmax per pixel), so
   every covered pixel gets an instance id, occlusion-aware like the renders.
3. **Score** (:func:`panoptic_quality`): the views are concatenated, so each predicted instance and
   each ground-truth object is ONE segment over all views (PQ^scene, Siddiqui et al., *Panoptic
   Lifting*, CVPR 2023; reported by Bhalgat et al., *Contrastive Lift*, NeurIPS 2023): a cluster
   that is one object in one view and another object in the next cannot match both. Matching and
   counting as Kirillov et al.'s PQ (CVPR 2019) and the COCO panoptic evaluation: a pair matches
   when IoU > 0.5 (unique), void (unlabelled) pixels are left out of a predicted segment's area,
   an unmatched predicted segment more than half of whose pixels are void is not a false positive;
   PQ = sum of matched IoUs / (TP + FP/2 + FN/2) = SQ x RQ. ``mIoU``: the ground-truth objects
   matched one-to-one to predicted segments by the Hungarian method on IoU
   (``scipy.optimize.linear_sum_assignment``), the mean over the objects, an unmatched one counting 0.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numba import njit

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------------------------
# PQ^scene
# ----------------------------------------------------------------------------------------------


@dataclass
class PanopticScore:
    """PQ, SQ, RQ (None when there is neither a ground-truth nor a predicted segment), the counts,
    the matched pairs' IoUs and the Hungarian mIoU over the ground-truth segments."""

    pq: float | None
    sq: float | None
    rq: float | None
    tp: int
    fp: int
    fn: int
    ignored: int  # unmatched predicted segments mostly on void pixels (not counted as FP)
    miou: float | None
    matches: list[tuple[int, int, float]]  # (ground-truth id, predicted id, IoU) of the IoU > 0.5 matches
    object_iou: dict[int, float]  # ground-truth id -> IoU of its Hungarian match (0 if none)

    def to_json(self) -> dict:
        return {"PQ": self.pq, "SQ": self.sq, "RQ": self.rq, "mIoU": self.miou, "TP": self.tp, "FP": self.fp,
                "FN": self.fn, "ignored_predictions": self.ignored,
                "matches": [{"object": g, "instance": p, "iou": i} for g, p, i in self.matches],
                "object_iou": {str(k): v for k, v in sorted(self.object_iou.items())}}


def panoptic_quality(pred: np.ndarray, truth: np.ndarray, threshold: float = 0.5) -> PanopticScore:
    """PQ of one segmentation: ``pred`` and ``truth`` are int label arrays of one shape (any shape:
    concatenated views for PQ^scene); ``truth`` 0 = void (ignored), ``pred`` 0 = no instance.

    IoU(p, g) = |p & g| / (|p| - |p & void| + |g| - |p & g|). Pairs with IoU > ``threshold`` (0.5 makes
    the matching unique) are true positives; unmatched ground-truth segments false negatives; unmatched
    predicted segments false positives unless more than half of their pixels are void.
    """
    pred = np.asarray(pred).ravel().astype(np.int64)
    truth = np.asarray(truth).ravel().astype(np.int64)
    if pred.shape != truth.shape:
        raise ValueError(f"panoptic_quality: {pred.size} predicted labels for {truth.size} ground-truth labels.")
    if (pred < 0).any() or (truth < 0).any():
        raise ValueError("panoptic_quality: labels must be non-negative (0 = void / no instance).")
    gt_ids, gt_area = np.unique(truth[truth > 0], return_counts=True)
    pr_ids, pr_area = np.unique(pred[pred > 0], return_counts=True)
    gi = np.searchsorted(gt_ids, truth)
    pi = np.searchsorted(pr_ids, pred)
    # intersections [G, P] and each prediction's void pixels [P]
    both = (truth > 0) & (pred > 0)
    inter = np.bincount(gi[both] * pr_ids.size + pi[both], minlength=gt_ids.size * pr_ids.size
                        ).reshape(gt_ids.size, pr_ids.size)
    void = np.bincount(pi[(truth == 0) & (pred > 0)], minlength=pr_ids.size) if pr_ids.size else np.zeros(0, np.int64)
    union = (pr_area - void)[None, :] + gt_area[:, None] - inter
    iou = np.where(union > 0, inter / np.maximum(union, 1), 0.0)
    g_match, p_match = np.nonzero(iou > threshold)
    matches = [(int(gt_ids[g]), int(pr_ids[p]), float(iou[g, p])) for g, p in zip(g_match, p_match)]
    tp = len(matches)
    fn = gt_ids.size - tp
    unmatched = np.ones(pr_ids.size, bool)
    unmatched[p_match] = False
    mostly_void = void > 0.5 * pr_area
    ignored = int((unmatched & mostly_void).sum())
    fp = int((unmatched & ~mostly_void).sum())
    denominator = tp + 0.5 * fp + 0.5 * fn
    if denominator == 0:
        pq = sq = rq = None
    else:
        total = sum(m[2] for m in matches)
        rq = tp / denominator
        sq = total / tp if tp else 0.0
        pq = total / denominator
    object_iou = {int(g): 0.0 for g in gt_ids}
    if gt_ids.size and pr_ids.size:
        # imported here: scipy.optimize costs every evaluate job 0.35 s of CPU before its first line, and the
        # official protocol computes no PQ (trace3d bench startup)
        from scipy.optimize import linear_sum_assignment

        rows, cols = linear_sum_assignment(iou, maximize=True)
        for r, c in zip(rows, cols):
            object_iou[int(gt_ids[r])] = float(iou[r, c])
    miou = float(np.mean(list(object_iou.values()))) if object_iou else None
    return PanopticScore(pq, sq, rq, tp, fp, fn, ignored, miou, matches, object_iou)


# ----------------------------------------------------------------------------------------------
# HDBSCAN (Campello, Moulavi & Sander 2013; McInnes, Healy & Astels 2017) on scipy
# ----------------------------------------------------------------------------------------------


def _mutual_reachability_mst(x: np.ndarray, core: np.ndarray) -> np.ndarray:
    """[S - 1, 3] (i, j, weight) edges of the minimum spanning tree of the mutual-reachability graph
    max(core_i, core_j, |x_i - x_j|) of the points ``x`` [S, D] (Prim's algorithm, one row of distances
    at a time: O(S^2 D) time, O(S) memory; ties go to the lowest index)."""
    x = np.ascontiguousarray(x, np.float64)
    core = np.ascontiguousarray(core, np.float64)
    edges = np.empty((max(x.shape[0] - 1, 0), 3))
    if x.shape[0] > 1:
        _prim(x, core, edges)
    return edges


@njit(cache=True)
def _prim(x, core, edges):
    """Prim's algorithm for :func:`_mutual_reachability_mst`. The points not yet in the tree are kept at
    the front of a transposed copy of ``x`` (a point that joins is swapped with the last of them), so the
    distances to the newest tree point are a loop over contiguous columns that LLVM vectorises across
    points; each point's squared distance still adds its dimensions in order, so the values are those
    of a point-by-point loop (:func:`_mutual_reachability_mst_reference`, the twin). The next point is the
    one of least reach, ties to the lowest index."""
    s, dim = x.shape
    xt = np.empty((dim, s))
    for c in range(dim):
        for j in range(s):
            xt[c, j] = x[j, c]
    perm = np.arange(s)
    best = np.full(s, np.inf)
    source = np.zeros(s, np.int64)
    core_p = core.copy()
    d2 = np.empty(s)
    xc = np.empty(dim)
    m = s
    q = 0  # the point that joins: position 0 (point 0) first
    for e in range(-1, s - 1):
        current = perm[q]
        if e >= 0:
            edges[e, 0] = source[q]
            edges[e, 1] = current
            edges[e, 2] = best[q]
        m -= 1  # swap the joining point out of the active front
        for c in range(dim):
            xt[c, q], xt[c, m] = xt[c, m], xt[c, q]
        perm[q], perm[m] = perm[m], perm[q]
        best[q], best[m] = best[m], best[q]
        source[q], source[m] = source[m], source[q]
        core_p[q], core_p[m] = core_p[m], core_p[q]
        if m == 0:
            break
        for c in range(dim):
            xc[c] = x[current, c]
        for p in range(m):
            d2[p] = 0.0
        for c in range(dim):
            v = xc[c]
            for p in range(m):
                t = xt[c, p] - v
                d2[p] += t * t
        cc = core[current]
        q = -1
        q_d = np.inf
        q_i = s
        for p in range(m):
            d = max(np.sqrt(d2[p]), core_p[p], cc)
            if d < best[p]:
                best[p] = d
                source[p] = current
            if best[p] < q_d or (best[p] == q_d and perm[p] < q_i):
                q_d = best[p]
                q_i = perm[p]
                q = p
        if q < 0:  # no finite reach (NaN features): the lowest-index point joins at inf
            q_i = s
            for p in range(m):
                if perm[p] < q_i:
                    q_i = perm[p]
                    q = p


def _mutual_reachability_mst_reference(x: np.ndarray, core: np.ndarray) -> np.ndarray:
    """:func:`_mutual_reachability_mst` by a plain Prim over the dense mutual-reachability matrix (numpy;
    the twin of :func:`_prim`: the same distances, dimensions summed in order, ties to the lowest index)."""
    x = np.asarray(x, np.float64)
    core = np.asarray(core, np.float64)
    s = x.shape[0]
    edges = np.empty((max(s - 1, 0), 3))
    if s < 2:
        return edges
    d2 = np.zeros((s, s))
    for c in range(x.shape[1]):  # in order of the dimensions, as the kernel adds them
        t = x[:, None, c] - x[None, :, c]
        d2 += t * t
    reach = np.maximum(np.maximum(np.sqrt(d2), core[:, None]), core[None, :])
    in_tree = np.zeros(s, bool)
    in_tree[0] = True
    best = reach[0].copy()
    source = np.zeros(s, np.int64)
    for e in range(s - 1):
        cand = np.where(in_tree, np.inf, best)
        nxt = int(np.argmin(cand))  # the first of the least: the lowest index
        edges[e] = (source[nxt], nxt, best[nxt])
        in_tree[nxt] = True
        closer = ~in_tree & (reach[nxt] < best)
        best[closer] = reach[nxt][closer]
        source[closer] = nxt
    return edges


def _single_linkage(edges: np.ndarray, s: int) -> np.ndarray:
    """[S - 1, 4] scipy-style linkage (child a, child b, distance, size; new node S + row) of a minimum
    spanning tree's ``edges`` [S - 1, 3], merged in order of weight (stable)."""
    order = np.argsort(edges[:, 2], kind="stable")
    parent = np.arange(2 * s - 1)
    size = np.concatenate([np.ones(s, np.int64), np.zeros(s - 1, np.int64)])

    def find(v: int) -> int:
        root = v
        while parent[root] != root:
            root = parent[root]
        while parent[v] != root:
            parent[v], v = root, parent[v]
        return root

    z = np.empty((s - 1, 4))
    for row, e in enumerate(order):
        a, b = find(int(edges[e, 0])), find(int(edges[e, 1]))
        node = s + row
        parent[a] = parent[b] = node
        size[node] = size[a] + size[b]
        z[row] = (a, b, edges[e, 2], size[node])
    return z


def hdbscan(x: np.ndarray, min_cluster_size: int, min_samples: int | None = None) -> np.ndarray:
    """[S] int cluster labels 0..K-1 of the points ``x`` [S, D] (-1 = noise).

    Core distance = distance to the ``min_samples``-th nearest point (the point itself counted);
    mutual reachability = max(core_i, core_j, |x_i - x_j|); its single-linkage tree is condensed
    (a split counts when both sides have ``min_cluster_size`` points; otherwise the smaller side's
    points fall out of the cluster at that level) and the clusters are chosen by excess of mass
    (stability sum over points of lambda_leave - lambda_birth, lambda = 1 / distance). The root is
    a cluster only if nothing splits it. Labels are numbered in the order of each cluster's first
    point. Deterministic: no random choice.
    """
    x = np.asarray(x, np.float64)
    s = x.shape[0]
    m = int(min_cluster_size)
    k = int(min_samples if min_samples is not None else m)
    if m < 2 or k < 1:
        raise ValueError(f"hdbscan: min_cluster_size must be >= 2 and min_samples >= 1, got {m}, {k}.")
    if s < m:
        return np.full(s, -1, np.int64)
    k = min(k, s)
    from scipy.spatial import cKDTree

    core = cKDTree(x).query(x, k=k)[0]
    core = core[:, -1] if core.ndim == 2 else np.zeros(s)
    z = _single_linkage(_mutual_reachability_mst(x, core), s)
    left, right = z[:, 0].astype(np.int64), z[:, 1].astype(np.int64)
    size = np.concatenate([np.ones(s, np.int64), z[:, 3].astype(np.int64)])
    with np.errstate(divide="ignore"):
        lam_node = np.where(z[:, 2] > 0, 1.0 / z[:, 2], np.inf)

    def leaves(node: int) -> list[int]:
        out, stack = [], [node]
        while stack:
            v = stack.pop()
            if v < s:
                out.append(v)
            else:
                stack.extend((left[v - s], right[v - s]))
        return out

    birth, parent, stability, children = [0.0], [-1], [0.0], [[]]
    point_cluster = np.full(s, -1, np.int64)
    stack = [(2 * s - 2, 0)]
    while stack:
        node, c = stack.pop()
        if node < s:
            point_cluster[node] = c
            continue
        lam = lam_node[node - s]
        a, b = left[node - s], right[node - s]
        big_a, big_b = size[a] >= m, size[b] >= m
        if big_a and big_b:
            stability[c] += size[node] * (lam - birth[c]) if np.isfinite(lam) else 0.0
            for child in (a, b):
                birth.append(lam)
                parent.append(c)
                stability.append(0.0)
                children.append([])
                children[c].append(len(birth) - 1)
                stack.append((child, len(birth) - 1))
            continue
        for child, big in ((a, big_a), (b, big_b)):
            if big:
                stack.append((child, c))
            else:
                pts = leaves(child)
                point_cluster[pts] = c
                if np.isfinite(lam):
                    stability[c] += len(pts) * (lam - birth[c])
    count = len(birth)
    selected = np.zeros(count, bool)
    best = np.array(stability, np.float64)
    for c in range(count - 1, 0, -1):  # children are created after their parents
        if not children[c]:
            selected[c] = True
            continue
        below = sum(best[ch] for ch in children[c])
        if stability[c] > below:
            selected[c] = True
            best[c] = stability[c]
            stack2 = list(children[c])
            while stack2:
                v = stack2.pop()
                selected[v] = False
                stack2.extend(children[v])
        else:
            best[c] = below
    if not children[0]:
        selected[0] = True  # nothing splits the data: one cluster
    owner = np.full(count, -1, np.int64)  # each cluster's selected ancestor (or itself)
    for c in range(count):
        v = c
        while v >= 0 and not selected[v]:
            v = parent[v]
        owner[c] = v
    raw = owner[point_cluster]
    labels = np.full(s, -1, np.int64)
    order = {}
    for i in range(s):
        if raw[i] >= 0:
            labels[i] = order.setdefault(int(raw[i]), len(order))
    return labels


# ----------------------------------------------------------------------------------------------
# instance maps of the evaluated views from a feature-lifted scene
# ----------------------------------------------------------------------------------------------


@dataclass
class FeatureClusters:
    """The clustered Gaussians: every Gaussian's instance [N] (1..K; the nearest cluster mean), the
    clustered samples' indices [C] and labels [C]."""

    instance: np.ndarray
    sample_index: np.ndarray
    sample_label: np.ndarray
    count: int  # K
    samples: int
    noise: int
    min_cluster_size: int


def cluster_features(features: np.ndarray, weights: np.ndarray, samples: int, min_share: float, seed: int
                     ) -> FeatureClusters:
    """HDBSCAN of ``samples`` Gaussians drawn without replacement (seeded) with probability proportional
    to ``weights`` [N] (their blending weight summed over the training views' pixels, so a cluster's
    share of the samples is about its share of the training pixels; unseen Gaussians are never drawn),
    on their features [N, D]; ``min_cluster_size = min_samples = max(2, ceil(samples * min_share))``.
    Every Gaussian then takes the cluster whose mean feature is nearest (the contrastive loss pulls an
    instance's features to one point; a 1-NN search over 80,000 Gaussians in 16-D took seconds)."""
    features = np.asarray(features, np.float64)
    weights = np.asarray(weights, np.float64)
    n = features.shape[0]
    seen = np.flatnonzero(weights > 0)
    rng = np.random.default_rng(seed)
    count = min(samples, seen.size)
    take = np.sort(rng.choice(seen, size=count, replace=False, p=weights[seen] / weights[seen].sum())) \
        if count else np.zeros(0, np.int64)
    m = max(2, math.ceil(count * min_share))
    labels = hdbscan(features[take], m, m) if count else np.zeros(0, np.int64)
    keep = labels >= 0
    k = int(labels.max() + 1) if keep.any() else 0
    instance = np.zeros(n, np.int64)
    if k:
        # nearest cluster mean (squared distances through one product; ties to the lower label)
        centres = np.stack([features[take[labels == j]].mean(0) for j in range(k)])
        d2 = (centres * centres).sum(1)[None, :] - 2.0 * features @ centres.T
        instance = np.argmin(d2, axis=1).astype(np.int64) + 1
    return FeatureClusters(instance, take[keep], labels[keep] + 1, k, int(count), int((~keep).sum()), m)


def scene_truth(instances: np.ndarray, evaluated: dict[int, np.ndarray]) -> np.ndarray:
    """[H, W] int ground-truth instance map: each pixel's finest evaluated object (the evaluated object
    whose membership holds the pixel's leaf id and that no other evaluated object containing it lies
    below), 0 = void (no evaluated object).

    Args:
        instances: [H, W] leaf ids.
        evaluated: object id -> its membership table (:func:`~trace3d.evaluation.groundtruth.membership`).
    """
    out = np.zeros(instances.shape, np.int64)
    # an object nested in another has a smaller membership: paint the largest first, the finest last
    for oid in sorted(evaluated, key=lambda o: (-int(evaluated[o].sum()), o)):
        member = evaluated[oid]
        ids = instances.astype(np.int64)
        inside = ids < len(member)
        hit = np.zeros(ids.shape, bool)
        hit[inside] = member[ids[inside]]
        out[hit] = oid
    return out


def _scene_score(model, instance: np.ndarray, count: int, gt, frames: Sequence[str], cameras: dict, near: float,
                 min_pixels: int, view_weights=None) -> tuple[PanopticScore, dict]:
    """PQ^scene of the per-Gaussian ``instance`` [N] (1..count, 0 = none) over the views ``frames``;
    evaluated objects with fewer than ``min_pixels`` pixels over all the views together are void.
    ``view_weights``: camera -> its blend-order pixel weights at ``near`` (the lifted scene's
    :meth:`~trace3d.lifting.query.FeatureLifted.blend_weights`): the instance maps are read from them
    (:func:`trace3d.render.weight_maps.instance_map`, the same bits), else rendered.
    Returns the score and the counts for metrics.json."""
    from ..lifting.contrastive import instance_map
    from ..render import weight_maps

    preds, truths = [], []
    for f in frames:
        if view_weights is not None:
            preds.append(weight_maps.instance_map(view_weights(cameras[f]), instance, count).ravel())
        else:
            preds.append(instance_map(model, cameras[f], instance, count, near).ravel())
        truths.append(scene_truth(gt.instances(f), gt.members).ravel())
    pred = np.concatenate(preds) if preds else np.zeros(0, np.int64)
    truth = np.concatenate(truths) if truths else np.zeros(0, np.int64)
    ids, area = np.unique(truth[truth > 0], return_counts=True)
    small = ids[area < min_pixels]
    truth[np.isin(truth, small)] = 0
    score = panoptic_quality(pred, truth)
    present = np.unique(pred[pred > 0])
    facts = {"instances_in_views": int(present.size), "objects": int(ids.size - small.size),
             "void_objects": [int(i) for i in small], "views": len(frames), "pixels": int(pred.size),
             "void_pixels": int((truth == 0).sum())}
    return score, facts


def evaluate_panoptic(lifted, gt, frames: Sequence[str], cameras: dict, samples: int, min_share: float,
                      seed: int, min_pixels: int) -> dict:
    """PQ^scene of a feature-lifted scene over the views ``frames`` (module docstring).

    ``lifted`` needs ``model``, ``features`` [N, D], ``visibility()`` [N] and ``params.near`` (the
    contrastive lift's :class:`~trace3d.lifting.query.FeatureLifted`); ``gt`` is the evaluation's
    :class:`~trace3d.evaluation.groundtruth.GroundTruth`; ``cameras`` maps frame names to cameras.
    Evaluated objects with fewer than ``min_pixels`` pixels over all the views together are void.
    """
    start = time.perf_counter()
    weights = lifted.visibility()
    clusters = cluster_features(lifted.features, weights, samples, min_share, seed)
    score, facts = _scene_score(lifted.model, clusters.instance, clusters.count, gt, frames, cameras,
                                lifted.params.near, min_pixels, getattr(lifted, "blend_weights", None))
    out = {**score.to_json(), "clusters": clusters.count, "instances_in_views": facts["instances_in_views"],
           "objects": facts["objects"], "void_objects": facts["void_objects"],
           "views": len(frames), "pixels": facts["pixels"], "void_pixels": facts["void_pixels"],
           "samples": clusters.samples, "noise_samples": clusters.noise,
           "min_cluster_size": clusters.min_cluster_size, "seconds": time.perf_counter() - start}
    log.info("panoptic: %d clusters from %d samples (%d noise), PQ %s SQ %s RQ %s mIoU %s over %d objects, "
             "%d views, %.2f s", clusters.count, clusters.samples, clusters.noise, _fmt(score.pq), _fmt(score.sq),
             _fmt(score.rq), _fmt(score.miou), out["objects"], len(frames), out["seconds"])
    return out


def evaluate_segments(lifted, gt, frames: Sequence[str], cameras: dict, segment_params, min_pixels: int,
                      graph=None) -> dict:
    """PQ^scene of the ``trace3d segment`` objects (:func:`~trace3d.segment.segment_gaussians`: the lifted
    features over the Gaussians' 3D kNN graph; stuff segments count as instances like the others, and
    on the rooms they lie on void walls and floors) over the views ``frames``; as :func:`evaluate_panoptic`
    otherwise. ``graph``: the seen Gaussians' kNN graph with ``segment_params.neighbours`` if made
    already, or the click score's :class:`~trace3d.segment.SeenGraph` (its edge distances, threshold and
    nearest seen Gaussians shared too)."""
    from ..segment import segment_gaussians

    start = time.perf_counter()
    seg = segment_gaussians(lifted.model.means.detach().double().numpy(), lifted.features, lifted.visibility(),
                            segment_params, graph)
    score, facts = _scene_score(lifted.model, seg.instance, seg.count, gt, frames, cameras, lifted.params.near,
                                min_pixels, getattr(lifted, "blend_weights", None))
    out = {**score.to_json(), "segments": seg.count, "stuff": int(seg.stuff.sum()), "threshold": seg.threshold,
           "threshold_source": seg.threshold_source, **facts, **seg.stats,
           "seconds": time.perf_counter() - start}
    log.info("segment PQ^scene: %d segments (%d stuff, threshold %.3g), PQ %s SQ %s RQ %s mIoU %s over %d objects, "
             "%.2f s", seg.count, int(seg.stuff.sum()), seg.threshold, _fmt(score.pq), _fmt(score.sq), _fmt(score.rq),
             _fmt(score.miou), facts["objects"], out["seconds"])
    return out


def _fmt(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.3f}"
