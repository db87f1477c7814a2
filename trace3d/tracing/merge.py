"""Consistent 2D instance maps by majority vote over co-visible views (paper Sec. 3.3; ``merge`` step).

This file stays longer than ~800 lines: the vote, its brute-force twin, the per-view union-find and the
association of ids across views are the ``merge`` step's one algorithm, read top to bottom; the quality
figures the step reports against the ground truth are in :mod:`.merge_quality`.

For two patches P_a, P_b of a view v0, G_a and G_b are the Gaussians whose argmax patch in v0 is
P_a (P_b) — the supplementary's argmax reduction of W — and visible in v0. Over the other views v,
the co-visible triples are Omega = {(G_a, G_b, v) : both have a vote in v}, and

    sim(P_a, P_b) = 1/|Omega| sum_Omega [argmax_v(G_a) == argmax_v(G_b)],

the inner product of the two Gaussians' (one-hot, argmax-reduced) instance distributions in v.
A Gaussian has a vote in v when it is visible there and, under ``uncovered: exclude`` (both
presets; the released code's ``valid_weight_mask``), its argmax there is not label 0 (pixels no
mask covers): agreement on being uncovered is no evidence of one instance. Pairs with sim > theta
(0.5; ``official`` 0.4) merge (union-find). Candidate pairs: those inside a common coarser mask
(supplementary, "Scalability of patch merging"; ``candidates: coarser_mask``, the default) or all
pairs of the view (main text; ``all_pairs``). The ``official`` preset adds the released code's
minimum support (:class:`VoteRule`): more than 100 Gaussians per patch, voting views where more than
20 % of each set votes, at least 2 of them, and Gaussians with at least 3 votes among them.

**Cost.** The sum over Gaussian pairs factors per view into histograms of the two sets' labels:
with h_a[v, l] = |{i in G_a : visible in v, label_v(i) = l}| and n_a[v] = sum_l h_a[v, l],

    sum_Omega [same] = sum_v <h_a[v], h_b[v]>,   |Omega| = sum_v n_a[v] n_b[v],

so one source view costs one pass over its visible Gaussians and all views
(:func:`cooccurrence`, numba), instead of |G_a| |G_b| L (label 0 excluded: the sums run over
l >= 1; a view filter: the sums run over the pair's voting views). Only a minimum number of voting
views per Gaussian breaks the factoring: it depends on the pair's views, so that rule histograms
each pair's Gaussians (:func:`_vote_per_gaussian`). :func:`pair_similarity_bruteforce` is the
pair loop the tests compare against. The source view v0 itself is left out of the vote (in v0
the two sets disagree by construction).

**Ids across views** (beyond the paper, which merges within each view only): merged instances of
different views are linked when they hold each other's Gaussians by mutual majority (more than
``association_share`` of each one's Gaussians co-visible in the other view fall into the other);
links are joined strongest first, never joining two instances of the same view, so that every
instance map keeps its own segmentation and only its ids become global.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Sequence

import numpy as np
from numba import njit, prange

from .consistency import average_linkage, comembership, mask_vote, stack_comembership
from .git import ROW_BLOCK_ENTRIES, GITStats, GITVisible
from .merge_quality import PairQuality, segmentation_quality, view_pair_quality

log = logging.getLogger(__name__)

PRESET_VALUES = {
    "paper": {"threshold": 0.5, "min_visibility": 0.0, "uncovered": "exclude", "min_gaussians": 0,
              "min_view_share": 0.0, "min_views": 1, "min_gaussian_views": 0, "grouping": "union_find"},
    # merge_patches.py / utils/con_mask_utils.py of the released code: an unseen Gaussian is one with
    # zero weight (its 25-pixel threshold belongs to the refine script, remove_ab_gaus.py), label 0 is
    # invalid (valid_weight_mask), a patch needs more than GAUS_NUM_TH = 100 Gaussians, a view votes
    # when more than vf_th = 0.2 of both sets are valid there, at least 2 such views, and a Gaussian
    # votes with more than 2 valid voting views (filter_weights' ct_th + 1 below 160 views); the pairs are
    # grouped by the released loop of SegmentationMask.repair (released_greedy: at most 2 patches a group).
    "official": {"threshold": 0.4, "min_visibility": 0.0, "uncovered": "exclude", "min_gaussians": 100,
                 "min_view_share": 0.2, "min_views": 2, "min_gaussian_views": 3, "grouping": "released_greedy"},
}

# The hierarchical method's threshold on its mask-level similarity, chosen end to end on the development
# rooms (config/dev.yaml; docs/bench/merge_dev_e2e.json) before it was scored with it anywhere else
# (docs/tracing.md, "The hierarchical merge"). The first round's 0.25 (chosen by the merge's ARI) lost
# NVS mIoU on every sample of the default rooms.
HIERARCHICAL_THRESHOLD = 0.4


@dataclass
class MergeParams:
    """Parameters of the ``merge`` step (``None`` takes the preset's value; docs/tracing.md).

    threshold: merge patch pairs whose similarity exceeds it (paper 0.5, official 0.4).
    min_visibility: a Gaussian sees a view when its GIT visibility exceeds this (both presets 0.0:
        any weight, the released merge_patches.py's "unseen = zero weight").
    candidates: which pairs of a view are compared: ``coarser_mask`` (default), the pairs of
        patches inside a common coarser mask (supplementary, "Scalability of patch merging");
        ``all_pairs``, every pair of patches of the view (the paper's main text, Sec. 3.3);
        ``conflict_area``, the released code's rule (:func:`conflict_areas`): the patches of one
        "conflict area", a union of masks that overlap transitively (IoU >= 0.05), where an area
        that one patch fills to 95 % is joined into one instance without a vote.
    grouping: how the pairs above the threshold become instances: ``union_find`` (paper preset),
        every such pair joined, transitively; ``released_greedy`` (official preset), the released
        ``SegmentationMask.repair`` loop (:func:`released_greedy`): each patch, in the released ids'
        order, joins the first later candidate above the threshold, whose Gaussian set then empties,
        so no instance holds more than 2 patches.
    uncovered: label 0 (pixels no mask covers) in the vote: ``exclude`` (both presets; the released
        code's valid_weight_mask): no vote; ``label``: an ordinary label, two uncovered Gaussians agree.
    min_gaussians: a patch takes part only with more than this many Gaussians (official 100:
        GAUS_NUM_TH; paper 0).
    min_view_share: a view votes on a pair only when more than this share of each patch's Gaussians
        vote there (official 0.2: vf_th; paper 0.0, every co-visible view).
    min_views: a pair with fewer voting views is not merged (official 2; paper 1).
    min_gaussian_views: a Gaussian votes only with a vote in at least this many of the pair's
        voting views (official 3; paper 0).
    method: ``vote`` (both presets): the paper's argmax-patch vote, pairs grouped by ``grouping``;
        ``hierarchical`` (beyond the paper, :mod:`.consistency`): the mask-level vote (do the two
        patches' Gaussians lie under a common mask of the other views), every pair of the view
        compared, groups by average linkage; ``candidates``, ``grouping`` and the minimum-support keys
        do not apply.
    mask_weight: (``hierarchical``) what a common mask of another view counts for, against 1 for the
        same patch there: 0 is the paper's vote, 1 the plain mask-level vote.
    association_share: the mutual-majority share that links instances across views.
    ground_truth_level: level of the ground-truth hierarchy the ``merge.json`` quality figures use.
    """

    preset: Literal["paper", "official"] = "paper"
    threshold: float | None = None
    min_visibility: float | None = None
    candidates: Literal["coarser_mask", "all_pairs", "conflict_area"] = "coarser_mask"
    grouping: Literal["union_find", "released_greedy"] | None = None
    uncovered: Literal["exclude", "label"] | None = None
    min_gaussians: int | None = None
    min_view_share: float | None = None
    min_views: int | None = None
    min_gaussian_views: int | None = None
    method: Literal["vote", "hierarchical"] = "vote"
    mask_weight: float = 0.25
    association_share: float = 0.5
    ground_truth_level: Literal["part", "object", "group"] = "object"
    preview_views: int = 4

    def __post_init__(self) -> None:
        if self.method not in ("vote", "hierarchical"):
            raise ValueError(f"method must be vote or hierarchical, got {self.method!r}")
        if not 0.0 <= self.mask_weight <= 1.0:
            raise ValueError(f"mask_weight must be in [0, 1], got {self.mask_weight}")
        if self.method == "hierarchical" and self.threshold is None:
            self.threshold = HIERARCHICAL_THRESHOLD
        for key, value in PRESET_VALUES[self.preset].items():
            if getattr(self, key) is None:
                setattr(self, key, value)
        if not 0.0 <= self.threshold <= 1.0:
            raise ValueError(f"threshold must be in [0, 1], got {self.threshold}")
        if not 0.0 < self.association_share < 1.0:
            raise ValueError(f"association_share must be in (0, 1), got {self.association_share}")
        if not 0.0 <= self.min_view_share < 1.0:
            raise ValueError(f"min_view_share must be in [0, 1), got {self.min_view_share}")
        for key in ("min_gaussians", "min_views", "min_gaussian_views"):
            if getattr(self, key) < 0:
                raise ValueError(f"{key} must be >= 0, got {getattr(self, key)}")

    @property
    def rule(self) -> "VoteRule":
        return VoteRule(uncovered=self.uncovered, min_gaussians=self.min_gaussians,
                        min_view_share=self.min_view_share, min_views=self.min_views,
                        min_gaussian_views=self.min_gaussian_views)


# ----------------------------------------------------------------------------------------------
# Similarity: factored (numba) and brute force (the twin)
# ----------------------------------------------------------------------------------------------


@njit(parallel=True, cache=True)
def cooccurrence(source: np.ndarray, labels: np.ndarray, visible: np.ndarray, num_source: int,
                 num_labels: int) -> np.ndarray:
    """hist[a, v, l] = |{i : source[i] == a, visible[i, v], labels[i, v] == l}|.

    Args:
        source: [n] int64 source label of each Gaussian (negative: skipped).
        labels: [n, L] int32 labels per view (negative: skipped).
        visible: [n, L] bool.
    Returns:
        [num_source, L, num_labels] int32 (views in parallel: each writes its own slice).
    """
    n, views = labels.shape
    hist = np.zeros((num_source, views, num_labels), np.int32)
    for v in prange(views):
        for i in range(n):
            a = source[i]
            if a < 0 or not visible[i, v]:
                continue
            lab = labels[i, v]
            if lab >= 0:
                hist[a, v, lab] += 1
    return hist


@dataclass(frozen=True)
class VoteRule:
    """Which Gaussians and views vote on a pair of patches (see :class:`MergeParams` for the keys).

    uncovered: ``exclude``: a Gaussian whose argmax in view v is label 0 (no mask covers its pixels)
        has no vote in v, neither agreement nor disagreement (the released code's
        ``valid_weight_mask``); ``label``: label 0 is a label like any other, so two Gaussians that
        are both uncovered in v agree (this project's earlier behaviour).
    min_gaussians: a patch takes part only when more than this many Gaussians trace to it.
    min_view_share: view v votes on (P_a, P_b) only when more than this share of G_a and of G_b
        have a vote there.
    min_views: a pair with fewer voting views gets similarity 0 (unsupported).
    min_gaussian_views: a Gaussian votes only when it has a vote in at least this many of the
        pair's voting views (0: every Gaussian).
    """

    uncovered: Literal["exclude", "label"] = "exclude"
    min_gaussians: int = 0
    min_view_share: float = 0.0
    min_views: int = 1
    min_gaussian_views: int = 0

    @property
    def first_label(self) -> int:
        """The smallest label that votes (1 when label 0 is excluded)."""
        return 1 if self.uncovered == "exclude" else 0


# Rule of the plain form (the paper's formula over every co-visible view, label 0 a label).
PLAIN = VoteRule(uncovered="label")

# Largest [pairs, views, labels] block of the factored vote computed at once (float64 entries).
VOTE_BLOCK = 1 << 22


def vote(hist: np.ndarray, pairs: np.ndarray, counts: np.ndarray | None = None,
         rule: VoteRule = PLAIN) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Similarities of patch ``pairs`` [K, 2] from one source view's histograms (factored form).

    Args:
        hist: [A, L, T] int label histograms of each source patch's Gaussians per view
            (:func:`source_histograms`; the source view's slice is zero).
        pairs: [K, 2] source patch ids.
        counts: [A] number of Gaussians of each source patch (|G_a|); needed when ``rule`` asks for
            a minimum number of Gaussians or a minimum view share.
        rule: which Gaussians and views vote. ``rule.min_gaussian_views`` needs each Gaussian's
            labels: :func:`merge_view` handles it with :func:`_vote_per_gaussian`; here it must be 0.
    Returns:
        sim [K] float64 (0 where unsupported or Omega is empty), |Omega| [K] int64 (0 where
        unsupported) and supported [K] bool.
    """
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    k = len(pairs)
    if rule.min_gaussian_views > 0:
        raise ValueError("vote: min_gaussian_views needs each Gaussian's labels (merge_view).")
    if k == 0:
        return np.zeros(0), np.zeros(0, np.int64), np.zeros(0, bool)
    h = hist[:, :, rule.first_label:]
    n = h.sum(axis=2, dtype=np.int64)  # [A, L] Gaussians with a vote in each view
    if counts is None:
        if rule.min_gaussians > 0 or rule.min_view_share > 0:
            raise ValueError("vote: the rule's minimum support needs the patches' Gaussian counts.")
        counts = np.full(len(hist), 1, np.int64)
    counts = np.asarray(counts, np.int64)
    share = n / np.maximum(counts, 1)[:, None]  # [A, L]
    sims, omega = np.zeros(k), np.zeros(k, np.int64)
    supported = (counts[pairs[:, 0]] > rule.min_gaussians) & (counts[pairs[:, 1]] > rule.min_gaussians)
    step = max(1, VOTE_BLOCK // max(1, h.shape[1] * h.shape[2]))
    counts_h = np.ascontiguousarray(hist, np.int32)
    for lo in range(0, k, step):
        a, b = pairs[lo:lo + step, 0], pairs[lo:lo + step, 1]
        views = (share[a] > rule.min_view_share) & (share[b] > rule.min_view_share)  # [k, L]
        ok = supported[lo:lo + step] & (views.sum(axis=1) >= rule.min_views)
        supported[lo:lo + step] = ok
        same, total = _vote_sums(counts_h, np.ascontiguousarray(a), np.ascontiguousarray(b), views,
                                 rule.first_label, n)
        same, total = same.astype(np.float64), total.astype(np.float64)
        total = np.where(ok, total, 0.0)
        sims[lo:lo + step] = np.where(total > 0, same / np.maximum(total, 1), 0.0)
        omega[lo:lo + step] = total.astype(np.int64)
    return sims, omega, supported


@njit(cache=True)
def _vote_sums(hist, a, b, views, first_label, n):
    """Per pair k: same[k] = sum over voting views v (``views`` [K, L]) and labels l >= ``first_label`` of
    hist[a_k, v, l] hist[b_k, v, l], and total[k] = sum over those views of n[a_k, v] n[b_k, v], as int64
    (``hist`` [A, L, T] int32 counts, ``n`` [A, L] int64). Integers: :func:`vote`'s float64 sums of the same
    integer terms (each below 2^53) are exact, so their floats are these; the twin :func:`_vote_sums_numpy`."""
    k = a.shape[0]
    same = np.zeros(k, np.int64)
    total = np.zeros(k, np.int64)
    for p in range(k):
        pa, pb = a[p], b[p]
        s = 0
        t = 0
        for v in range(hist.shape[1]):
            if not views[p, v]:
                continue
            for lab in range(first_label, hist.shape[2]):
                s += np.int64(hist[pa, v, lab]) * np.int64(hist[pb, v, lab])
            t += n[pa, v] * n[pb, v]
        same[p] = s
        total[p] = t
    return same, total


def _vote_sums_numpy(hist, a, b, views, first_label, n) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_vote_sums` in float64 numpy, as :func:`vote` computed it before the kernel (the twin)."""
    h = hist[:, :, first_label:]
    ha, hb = h[a].astype(np.float64), h[b].astype(np.float64)
    same = ((ha * hb).sum(axis=2) * views).sum(axis=1)
    total = (n[a].astype(np.float64) * n[b] * views).sum(axis=1)
    return same, total


def pair_similarity(hist: np.ndarray, pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The plain similarity (every co-visible view, label 0 a label, no minimum support) of patch
    ``pairs`` [K, 2] from one source view's histograms [A, L, T].

    Returns:
        sim [K] float64 (0 where Omega is empty) and |Omega| [K] int64.
    """
    sims, omega, _ = vote(hist, pairs)
    return sims, omega


def _vote_per_gaussian(labels: np.ndarray, rows: Sequence[np.ndarray], pairs: np.ndarray, views: np.ndarray,
                       ok: np.ndarray, rule: VoteRule, num_labels: int) -> tuple[np.ndarray, np.ndarray]:
    """The vote with a minimum number of voting views per Gaussian (``rule.min_gaussian_views``).

    Args:
        labels: [n, L] int32 labels of the source view's visible Gaussians, -1 where they have no
            vote (unseen, uncovered under ``exclude``, or the source view itself).
        rows: per source patch, the row indices into ``labels`` of its Gaussians.
        pairs: [K, 2]; views: [K, L] bool voting views of each pair; ok: [K] bool supported pairs.
    Returns:
        sim [K] float64 and |Omega| [K] int64 (0 where not ``ok``).
    """
    sims, omega = np.zeros(len(pairs)), np.zeros(len(pairs), np.int64)
    for k, ((a, b), f, good) in enumerate(zip(pairs, views, ok)):
        if not good:
            continue
        cols = np.nonzero(f)[0]
        hists = []
        for p in (a, b):
            lab = labels[rows[p]][:, cols]  # [|G_p|, |F|]
            has = lab >= 0
            lab = lab[has.sum(axis=1) >= rule.min_gaussian_views]
            has = lab >= 0
            index = (np.arange(len(cols))[None, :] * num_labels + lab)[has]
            hists.append(np.bincount(index, minlength=len(cols) * num_labels).reshape(len(cols), num_labels))
        ha, hb = hists
        same = int((ha * hb).sum())
        total = int((ha.sum(axis=1) * hb.sum(axis=1)).sum())
        sims[k] = same / total if total else 0.0
        omega[k] = total
    return sims, omega


def pair_similarity_bruteforce(labels: np.ndarray, visible: np.ndarray, source_view: int, a: int,
                               b: int, rule: VoteRule = PLAIN) -> tuple[float, int]:
    """The definition as a literal loop over Gaussian pairs and views (the twin of the factored form).

    Args:
        labels: [N, L] argmax labels; visible: [N, L] bool; source_view: v0; a, b: patch ids in v0.
        rule: which Gaussians and views vote (:class:`VoteRule`).
    Returns:
        (sim, |Omega|); (0.0, 0) for a pair without the rule's minimum support.
    """
    ga = [i for i in range(labels.shape[0]) if visible[i, source_view] and labels[i, source_view] == a]
    gb = [i for i in range(labels.shape[0]) if visible[i, source_view] and labels[i, source_view] == b]
    if len(ga) <= rule.min_gaussians or len(gb) <= rule.min_gaussians:
        return 0.0, 0

    def votes(i, v):
        return v != source_view and visible[i, v] and labels[i, v] >= rule.first_label

    views = [v for v in range(labels.shape[1])
             if ga and gb and sum(votes(i, v) for i in ga) / len(ga) > rule.min_view_share
             and sum(votes(j, v) for j in gb) / len(gb) > rule.min_view_share]
    if len(views) < rule.min_views:
        return 0.0, 0
    ga = [i for i in ga if sum(votes(i, v) for v in views) >= rule.min_gaussian_views]
    gb = [j for j in gb if sum(votes(j, v) for v in views) >= rule.min_gaussian_views]
    same = total = 0
    for v in views:
        for i in ga:
            if not votes(i, v):
                continue
            for j in gb:
                if not votes(j, v):
                    continue
                total += 1
                same += int(labels[i, v] == labels[j, v])
    return (same / total if total else 0.0), total


def source_histograms(labels: np.ndarray, visible: np.ndarray, source_view: int, num_source: int,
                      num_labels: int) -> np.ndarray:
    """:func:`cooccurrence` of the Gaussians visible in ``source_view``, keyed by their label there,
    with the source view itself left out (its histogram slice is zero)."""
    rows = np.nonzero(visible[:, source_view] & (labels[:, source_view] >= 0))[0]
    source = labels[rows, source_view].astype(np.int64)
    vis = visible[rows].copy()
    vis[:, source_view] = False
    return cooccurrence(source, np.ascontiguousarray(labels[rows]), vis, int(num_source), int(num_labels))


@njit(cache=True)
def _all_source_histograms(indptr, indices, values, views, first, count, num_source, num_labels):
    hist = np.zeros((count, num_source, views, num_labels), np.int32)
    for i in range(len(indptr) - 1):  # every pair of views that sees Gaussian i (serial: the blocks overlap in i)
        lo, hi = indptr[i], indptr[i + 1]
        for k0 in range(lo, hi):
            v0 = indices[k0]
            if v0 < first or v0 >= first + count:
                continue
            a = values[k0]
            for k in range(lo, hi):
                v = indices[k]
                if v != v0:
                    hist[v0 - first, a, v, values[k]] += 1
    return hist


# Largest histogram block (int32 entries) computed at once: 64 M entries = 256 MB.
HISTOGRAM_BLOCK = 1 << 26


def _narrowest(top: int) -> type:
    """int16 when every value in [-1, top] fits it, else int32."""
    return np.int16 if top <= np.iinfo(np.int16).max else np.int32


def visible_lists(label_rows, visible: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per Gaussian, the views that see it with a label and its label there, as CSR lists.

    Args:
        label_rows: ``label_rows(lo, hi)`` -> [hi - lo, L] integer labels of Gaussians lo..hi-1
            (negative: none), called twice per row block, so that no [N, L] temporary is made.
        visible: [N, L] bool.
    Returns:
        indptr [N + 1] int64, indices [nnz] (views, ascending per Gaussian) and values [nnz] (labels):
        the entries where ``visible & (label >= 0)``, row-major; int16 where the views (the labels)
        fit it, else int32.
    """
    n, views = visible.shape
    step = max(1, ROW_BLOCK_ENTRIES // max(1, views))
    counts = np.zeros(n, np.int64)
    top = -1
    for lo in range(0, n, step):
        lab = label_rows(lo, lo + step)
        seen = visible[lo:lo + step] & (lab >= 0)
        counts[lo:lo + step] = seen.sum(axis=1)
        top = max(top, int(lab.max(initial=-1)))
    indptr = np.zeros(n + 1, np.int64)
    np.cumsum(counts, out=indptr[1:])
    del counts
    indices = np.empty(int(indptr[-1]), _narrowest(views - 1))
    values = np.empty(int(indptr[-1]), _narrowest(top))
    for lo in range(0, n, step):
        lab = label_rows(lo, lo + step)
        seen = visible[lo:lo + step] & (lab >= 0)
        a, b = indptr[lo], indptr[min(lo + step, n)]
        indices[a:b] = np.nonzero(seen)[1]
        values[a:b] = lab[seen]
    return indptr, indices, values


def _histograms_of_lists(lists, views: int, num_source: int, num_labels: int):
    """:func:`all_source_histograms` from :func:`visible_lists`' CSR lists."""
    indptr, indices, values = lists
    per_view = max(1, int(num_source) * views * int(num_labels))
    block = max(1, min(views, HISTOGRAM_BLOCK // per_view))
    for start in range(0, views, block):
        count = min(block, views - start)
        yield from _all_source_histograms(indptr, indices, values, views, start, count, int(num_source),
                                          int(num_labels))


def label_counts(lists, views: int, width: int) -> np.ndarray:
    """[views, width] int64: per view, its visible Gaussians per label, from :func:`visible_lists`' lists
    (labels below ``width``; the counts ``merge_view`` takes of a view's column, all views in one pass)."""
    indptr, indices, values = lists
    counts = np.zeros(views * width, np.int64)
    for lo in range(0, len(indices), ROW_BLOCK_ENTRIES):  # entries a block at a time: no [nnz] int64 temporary
        key = indices[lo:lo + ROW_BLOCK_ENTRIES].astype(np.int64) * width + values[lo:lo + ROW_BLOCK_ENTRIES]
        counts += np.bincount(key, minlength=views * width)
    return counts.reshape(views, width)


def merged_lists(lists, merges: Sequence["ViewMerge"]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`visible_lists` of :func:`merged_label_rows` from the labels' own lists (``visible_lists`` of
    the labels with the same visible mask): every entry whose label has an entry in its view's lut, the
    label replaced by its merged instance there; the same arrays without a pass over the [N, L] labels
    (entries a block at a time). The values are int16 when every lut's largest instance fits it, else
    int32 (the histograms do not depend on the width)."""
    indptr, indices, values = lists
    sizes = np.array([len(m.lut) for m in merges], np.int64)
    offsets = np.zeros(len(merges) + 1, np.int64)
    np.cumsum(sizes, out=offsets[1:])
    flat = np.concatenate([np.asarray(m.lut, np.int64) for m in merges]) if merges else np.zeros(0, np.int64)
    kind = _narrowest(max((int(m.lut.max(initial=-1)) for m in merges), default=-1))
    out_indices = np.empty_like(indices)
    out_values = np.empty(len(values), kind)
    dropped, at = [], 0
    for lo in range(0, len(indices), ROW_BLOCK_ENTRIES):
        view = indices[lo:lo + ROW_BLOCK_ENTRIES].astype(np.int64)
        label = values[lo:lo + ROW_BLOCK_ENTRIES].astype(np.int64)
        keep = label < sizes[view]
        if not keep.all():
            dropped.append(lo + np.flatnonzero(~keep))
        kept = int(keep.sum())
        out_indices[at:at + kept] = indices[lo:lo + ROW_BLOCK_ENTRIES][keep]
        out_values[at:at + kept] = flat[offsets[view[keep]] + label[keep]]
        at += kept
    if not dropped:
        return indptr, out_indices, out_values
    dropped = np.concatenate(dropped)
    out_indptr = indptr - np.searchsorted(dropped, indptr, side="left")  # entries dropped before each row
    return out_indptr, out_indices[:at].copy(), out_values[:at].copy()


def all_source_histograms(labels: np.ndarray, visible: np.ndarray, num_source: int, num_labels: int):
    """:func:`source_histograms` of every source view, yielded in order as [num_source, L, num_labels].

    Each Gaussian contributes only over the views it is visible in (a per-Gaussian list,
    :func:`visible_lists`), so the cost is the number of (Gaussian, source view, view)
    co-visibilities, sum_i k_i^2 for a Gaussian seen in k_i views, not N L^2, and the memory beyond
    ``labels`` and ``visible`` is the lists (4 or 8 bytes per visible entry). Source views come in
    blocks that bound the memory.
    """
    lists = visible_lists(lambda lo, hi: labels[lo:hi], visible)
    return _histograms_of_lists(lists, labels.shape[1], num_source, num_labels)


# ----------------------------------------------------------------------------------------------
# Union-find merging per view
# ----------------------------------------------------------------------------------------------


class UnionFind:
    def __init__(self, count: int):
        self.parent = list(range(count))

    def find(self, x: int) -> int:
        while self.parent[x] != x:
            self.parent[x] = self.parent[self.parent[x]]
            x = self.parent[x]
        return x

    def union(self, a: int, b: int) -> None:
        ra, rb = self.find(a), self.find(b)
        if ra != rb:
            self.parent[max(ra, rb)] = min(ra, rb)


@dataclass
class ViewMerge:
    """The merge of one view: ``lut`` [P + 1] maps patch id -> merged instance (0 -> 0, 1..G)."""

    frame: str
    lut: np.ndarray
    pairs: np.ndarray  # [K, 2] candidate pairs
    sims: np.ndarray  # [K]
    omega: np.ndarray  # [K]
    merged: np.ndarray  # [K] bool
    supported: np.ndarray | None = None  # [K] bool: the pair had the rule's minimum support
    collapsed: np.ndarray | None = None  # [C, 2] pairs joined without a vote (conflict_area's dominated areas)

    @property
    def num_instances(self) -> int:
        return int(self.lut.max(initial=0))


def candidate_pairs(hierarchy, candidates: str) -> np.ndarray:
    """[K, 2] patch pairs (a < b) of one view compared by the merge: ``coarser_mask``, the pairs
    inside a common coarser mask (:meth:`PatchHierarchy.candidate_pairs`); ``all_pairs``, all of them;
    ``conflict_area``, the pairs inside one of the released code's conflict areas (:func:`conflict_areas`)."""
    return view_candidates(hierarchy, candidates).pairs


@dataclass
class ViewCandidates:
    """What the candidate rule gives the vote and the grouping of one view.

    pairs: [K, 2] candidate pairs (a < b).
    collapsed: [C, 2] pairs joined without a vote (``conflict_area``: the areas one patch fills to
        :data:`CONFLICT_DOMINANCE`; empty otherwise).
    groups: the candidate groups in the released loop's order (``conflict_area``: the conflict areas'
        ids); ``None``: one group, every candidate pair.
    start: [P + 1] the id each patch carries before the vote (``conflict_area``: a dominated area's
        patches carry one of them); ``None``: its own.
    """

    pairs: np.ndarray
    collapsed: np.ndarray
    groups: list | None = None
    start: np.ndarray | None = None


def view_candidates(hierarchy, candidates: str) -> ViewCandidates:
    """The candidate pairs of one view (:func:`candidate_pairs`) with what the grouping needs."""
    none = np.zeros((0, 2), np.int64)
    if candidates == "coarser_mask":
        return ViewCandidates(hierarchy.candidate_pairs(), none)
    if candidates == "all_pairs":
        a, b = np.triu_indices(hierarchy.num_patches + 1, k=1)
        keep = a > 0
        return ViewCandidates(np.stack([a[keep], b[keep]], axis=1).astype(np.int64), none)
    if candidates == "conflict_area":
        classes, collapsed, start = conflict_areas(hierarchy)
        return ViewCandidates(_pairs_within(classes, hierarchy.num_patches),
                              _pairs_within(collapsed, hierarchy.num_patches), classes, start)
    raise ValueError(f"candidates must be coarser_mask, all_pairs or conflict_area, got {candidates!r}")


def _pairs_within(groups: Sequence[np.ndarray], num_patches: int) -> np.ndarray:
    """[K, 2] unique pairs (a < b) of patches that share one of ``groups``."""
    keys = []
    for g in groups:
        g = np.sort(np.asarray(g, np.int64))
        a, b = np.triu_indices(len(g), k=1)
        keys.append(g[a] * (num_patches + 1) + g[b])
    keys = np.unique(np.concatenate(keys)) if keys else np.zeros(0, np.int64)
    return np.stack([keys // (num_patches + 1), keys % (num_patches + 1)], axis=1).astype(np.int64)


# The released code's conflict areas (utils/con_mask_utils.py, SegmentationMask._union_area / _get_c_area):
# a set of masks joins an area when the pixels two or more of them cover are at least this share of the
# pixels any of them covers ...
CONFLICT_IOU = 0.05
# ... and an area one patch fills to this share is joined into one instance, without a vote.
CONFLICT_DOMINANCE = 0.95


def released_ids(hierarchy) -> np.ndarray:
    """[P + 1] int64: each patch's rank in the released code's patch numbering (``_get_mask``: the
    sorted unique rows of the per-pixel mask-membership vectors, i.e. the patches in lexicographic order
    of their membership, mask 0 most significant, uncovered first), ties by patch id. Row 0 is 0."""
    member = hierarchy.membership()
    count = len(member)
    if member.shape[1] == 0:
        return np.arange(count, dtype=np.int64)
    order = np.lexsort(tuple(member[:, m] for m in range(member.shape[1] - 1, -1, -1)))
    rank = np.empty(count, np.int64)
    rank[order] = np.arange(count)
    return rank


def conflict_areas(hierarchy, iou: float = CONFLICT_IOU,
                   dominance: float = CONFLICT_DOMINANCE) -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray]:
    """The released code's conflict areas of one view, computed on the patches (docs/tracing.md).

    The released ``SegmentationMask`` works on pixels: ``conflict`` counts the masks over each pixel;
    while some pixel has conflict > 1, the masks over the first such pixel of maximal conflict (raster
    order) are united when their IoU (pixels under two or more of them / pixels under any) is at least
    ``iou`` (their counts are then taken off ``conflict``; below it, only off the pixels they share),
    and the area grows by the masks over its first pixel of maximal remaining conflict until none is
    left. An area that one patch fills to ``dominance`` is relabelled to one id (no vote); the others
    are conflict areas, whose patches the vote compares. Every pixel of a patch has the same masks, so
    the same steps run on the patches, weighted by their pixel counts (the masks are the unions of the
    patches that list them; the patch step's absorbed slivers are counted in their patch), and "the
    first pixel" is the lowest patch id (ids follow the raster order of the first pixel).

    Returns:
        the conflict areas' candidate groups in the order found (each: the patches standing for its
        distinct ids, more than one), the dominated areas' patches (each joined into one instance) and
        [P + 1] the patch whose id each patch carries after those joins.
    """
    member = hierarchy.membership()  # [P + 1, M]
    area = np.zeros(len(member), np.int64)
    area[1:] = hierarchy.patch_areas
    conflict = member.sum(axis=1).astype(np.int64)
    rank = released_ids(hierarchy)
    current = np.arange(len(member))  # the patch whose id each patch carries (a dominated area takes one)

    def union_of(masks: np.ndarray) -> np.ndarray | None:
        temp = member[:, masks].sum(axis=1)
        union, inter = temp > 0, temp > 1
        if area[inter].sum() / max(area[union].sum(), 1) < iou:
            conflict[inter] -= temp[inter]
            return None
        conflict[:] -= temp
        return union

    areas, collapsed = [], []
    while conflict.max(initial=0) > 1:
        found = union_of(member[int(np.argmax(conflict))])
        if found is None:
            continue
        while conflict[found].max() > 0:
            grown = union_of(member[int(np.argmax(np.where(found, conflict, 0)))])
            if grown is not None:
                found |= grown
        ids = current[found]
        weight = np.bincount(ids, weights=area[found], minlength=len(member))
        patches = np.nonzero(found)[0]
        if weight.max() / max(area[found].sum(), 1) < dominance:
            areas.append(patches)
        else:
            keep = np.unique(ids)
            current[found] = keep[np.argmin(rank[keep])]
            collapsed.append(patches)
    classes = []
    for patches in areas:
        ids = np.unique(current[patches])
        if len(ids) > 1:
            classes.append(ids)
    return classes, collapsed, current


def released_greedy(pairs: np.ndarray, sims: np.ndarray, threshold: float, rank: np.ndarray,
                    groups: Sequence[np.ndarray] | None = None) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """The candidate pairs the released loop (``SegmentationMask.repair``) merges: [K] bool, and the
    merges (giver, receiver) in the loop's order.

    Per group (``groups``: the conflict areas in order; ``None``: one group of every pair), patches are
    visited in the released numbering (``rank``, :func:`released_ids`); each compares itself with its
    later candidates of the group in that order and joins the first one whose similarity exceeds
    ``threshold``; the receiver's Gaussian set is then intersected with the giver's
    (``c_w_masks[j] & c_w_masks[0]``), which is empty (a Gaussian has one argmax patch per view), so the
    receiver's similarity to every later patch is 0 (``cal_miou`` with no Gaussians): it neither gives
    nor receives again within the group. Within one group every instance holds at most 2 patches; the
    sets are taken afresh for every group, as the released loop does for every conflict area.
    """
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    merged = np.zeros(len(pairs), bool)
    moves: list[tuple[int, int]] = []
    if not len(pairs):
        return merged, moves
    swap = rank[pairs[:, 0]] > rank[pairs[:, 1]]
    first = np.where(swap, pairs[:, 1], pairs[:, 0])
    later = np.where(swap, pairs[:, 0], pairs[:, 1])
    order = np.lexsort((rank[later], rank[first]))
    top = int(pairs.max()) + 1
    for group in ([None] if groups is None else groups):
        if group is None:
            inside = np.ones(len(pairs), bool)
        else:
            group = np.asarray(group, np.int64)
            member = np.zeros(max(top, int(group.max(initial=0)) + 1), bool)
            member[group] = True
            inside = member[first] & member[later]
        done = np.zeros(top, bool)  # gave (left the list) or received (emptied)
        for k in order:
            a, b = first[k], later[k]
            if not inside[k] or done[a] or done[b]:
                continue
            if sims[k] > threshold:
                merged[k] = True
                done[a] = done[b] = True
                moves.append((int(a), int(b)))
    return merged, moves


def merge_view(stats: GITStats, view: int, num_patches: int, pairs: np.ndarray, threshold: float,
               min_visibility: float, hist: np.ndarray | None = None, rule: VoteRule = VoteRule(),
               visible: np.ndarray | None = None, grouping: str = "union_find", rank: np.ndarray | None = None,
               collapsed: np.ndarray | None = None, groups: Sequence[np.ndarray] | None = None,
               start: np.ndarray | None = None, counts: np.ndarray | None = None) -> ViewMerge:
    """Merge the patches of view ``view`` (ids 1..num_patches; 0 is uncovered and never merged).

    ``hist``: the view's [A, L, T] source histograms when already computed (:func:`all_source_histograms`);
    ``rule``: which Gaussians and views vote (default: the paper preset's); ``visible``: [N, L]
    ``stats.visible(min_visibility)`` when already computed. ``grouping``: ``union_find`` joins every
    pair above the threshold; ``released_greedy`` the pairs :func:`released_greedy` picks, in the order
    ``rank`` ([P + 1], :func:`released_ids`; default: patch ids), per group of ``groups`` (default: one).
    ``collapsed``: [C, 2] pairs joined without a vote; ``start``: [P + 1] the id each patch carries
    before the vote (the released grouping relabels ids as the released code relabels pixels: a giver's
    id becomes the receiver's, for every patch carrying it; default: its own). ``counts``: the view's
    visible Gaussians per label when already counted (:func:`label_counts`; at least ``len(hist)`` long).
    """
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    if visible is None:
        visible = stats.visible(min_visibility)
    num_labels = int(stats.num_labels.max(initial=1))
    num_source = max(num_patches + 1, int(stats.num_labels[view]))
    if hist is None:
        hist = source_histograms(stats.label, visible, view, num_source, num_labels)
    source = None
    if counts is None:
        source = visible[:, view] & (stats.label[:, view] >= 0)
        counts = np.bincount(stats.label[source, view], minlength=len(hist)).astype(np.int64)
    else:
        counts = np.asarray(counts, np.int64)[:len(hist)]
    if rule.min_gaussian_views > 0:
        sims, omega, supported = vote(hist, pairs, counts, VoteRule(rule.uncovered, rule.min_gaussians,
                                                                     rule.min_view_share, rule.min_views))
        if len(pairs):
            if source is None:
                source = visible[:, view] & (stats.label[:, view] >= 0)
            rows_all = np.nonzero(source)[0]
            masked = stats.label[rows_all].astype(np.int32, copy=False)  # a copy (rows), masked in place
            at_view = masked[:, view].copy()
            no_vote = visible[rows_all]
            no_vote &= masked >= rule.first_label
            np.invert(no_vote, out=no_vote)
            np.copyto(masked, -1, where=no_vote)
            del no_vote
            masked[:, view] = -1
            by_label = np.argsort(at_view, kind="stable")
            bounds = np.searchsorted(at_view[by_label], np.arange(len(hist) + 1))
            by_patch = [by_label[bounds[p]:bounds[p + 1]] for p in range(len(hist))]
            n = hist[:, :, rule.first_label:].sum(axis=2, dtype=np.int64)
            share = n / np.maximum(counts, 1)[:, None]
            views = (share[pairs[:, 0]] > rule.min_view_share) & (share[pairs[:, 1]] > rule.min_view_share)
            sims, omega = _vote_per_gaussian(masked, by_patch, pairs, views, supported, rule, num_labels)
    else:
        sims, omega, supported = vote(hist, pairs, counts, rule)
    collapsed = np.zeros((0, 2), np.int64) if collapsed is None else np.asarray(collapsed, np.int64).reshape(-1, 2)
    if grouping == "union_find":
        merged = sims > threshold
        uf = UnionFind(num_patches + 1)
        for (a, b), m in zip(pairs, merged):
            if m:
                uf.union(int(a), int(b))
        for a, b in collapsed:
            uf.union(int(a), int(b))
        roots = np.array([uf.find(p) for p in range(num_patches + 1)])
    elif grouping == "released_greedy":
        merged, moves = released_greedy(pairs, sims, threshold, np.arange(num_patches + 1) if rank is None else rank,
                                        groups)
        roots = np.arange(num_patches + 1) if start is None else np.asarray(start, np.int64).copy()
        if start is None:
            uf = UnionFind(num_patches + 1)
            for a, b in collapsed:
                uf.union(int(a), int(b))
            roots = np.array([uf.find(p) for p in range(num_patches + 1)])
        for a, b in moves:  # _change_class_id: the pixels carrying the giver's id take the receiver's
            roots[roots == a] = b
    else:
        raise ValueError(f"grouping must be union_find or released_greedy, got {grouping!r}")
    lut = np.zeros(num_patches + 1, np.int64)
    order: dict = {}
    for p in range(1, num_patches + 1):  # instances numbered by their lowest patch
        lut[p] = order.setdefault(int(roots[p]), len(order) + 1)
    return ViewMerge(stats.frames[view], lut, pairs, sims, omega, merged, supported, collapsed)


# ----------------------------------------------------------------------------------------------
# Ids across views
# ----------------------------------------------------------------------------------------------


def merged_label_rows(stats, merges: Sequence[ViewMerge], lo: int, hi: int) -> np.ndarray:
    """[hi - lo, L] int32: Gaussians lo..hi-1's merged instance in every view (-1: none; their
    label's entry of the view's lut)."""
    rows = stats.label[lo:hi]
    out = np.full(rows.shape, -1, np.int32)
    for v, m in enumerate(merges):
        lab = rows[:, v]
        ok = (lab >= 0) & (lab < len(m.lut))
        out[ok, v] = m.lut[lab[ok]]
    return out


def view_links(hist: np.ndarray, v: int, share: float, counts: Sequence[int],
               offsets: np.ndarray) -> list[tuple[float, int, int]]:
    """The links of view ``v``'s instances to later views' (:func:`associate`): (strength, a, b) for every
    (m, w, m') of the [G+1, L, G'+1] co-visibility counts ``hist`` with w > v whose strength (the least of
    the two shares) exceeds ``share``; a, b: global positions (``offsets`` [L + 1], ``counts`` [L]
    instances per view). Only the pairs that share a Gaussian are divided out: the totals are sums of
    integers (exact in any order and type) and a pair sharing none has strength 0, never above
    ``share`` > 0; the same floats as :func:`view_links_dense` (the twin, over the whole table)."""
    later = hist[:, v + 1:, :]
    fwd_total = later[1:].sum(axis=2, dtype=np.int64)  # [G, L']: Gaussians of (v, m) co-visible in w
    rev_total = later.sum(axis=0, dtype=np.int64)[:, 1:]  # [L', G']: Gaussians of (w, m') co-visible in v
    block = later[1:, :, 1:]
    m, w, mp = np.nonzero(block)
    both = block[m, w, mp].astype(np.float64)
    strength = np.minimum(both / np.maximum(fwd_total[m, w], 1), both / np.maximum(rev_total[w, mp], 1))
    keep = strength > share
    m, w, mp, strength = m[keep], w[keep], mp[keep], strength[keep]
    w_abs = w + v + 1
    ok = mp < np.asarray(counts)[w_abs]
    return [(float(s_), int(a_), int(b_))
            for s_, a_, b_ in zip(strength[ok], offsets[v] + m[ok], offsets[w_abs[ok]] + mp[ok])]


def view_links_dense(hist: np.ndarray, v: int, share: float, counts: Sequence[int],
                     offsets: np.ndarray) -> list[tuple[float, int, int]]:
    """:func:`view_links` over the whole table in float64 (the twin)."""
    hist = hist.astype(np.float64)  # [G+1, L, G'+1]
    fwd_total = hist.sum(axis=2)  # [G+1, L]
    rev_total = hist.sum(axis=0)  # [L, G'+1]
    block = hist[1:, v + 1:, 1:]  # later views only: each pair of views once
    fwd = block / np.maximum(fwd_total[1:, v + 1:, None], 1)
    rev = block / np.maximum(rev_total[None, v + 1:, 1:], 1)
    strength = np.minimum(fwd, rev)
    m, w, mp = np.nonzero(strength > share)
    w_abs = w + v + 1
    ok = mp < np.asarray(counts)[w_abs]
    return [(float(s_), int(a_), int(b_))
            for s_, a_, b_ in zip(strength[m, w, mp][ok], offsets[v] + m[ok], offsets[w_abs[ok]] + mp[ok])]


def associate(stats: GITStats, merges: Sequence[ViewMerge], min_visibility: float,
              share: float = 0.5, visible: np.ndarray | None = None, label_lists=None) -> list[np.ndarray]:
    """Global instance ids: for every view, [G_v + 1] lut from merged instance to a global id (0 -> 0).

    Instances (v, m) and (w, m') link when more than ``share`` of each one's Gaussians that are
    co-visible in the other view fall into the other; links are joined strongest first, never
    joining two instances of the same view. ``visible``: ``stats.visible(min_visibility)`` when
    already computed. The merged labels are built a row block at a time into per-Gaussian lists
    (:func:`visible_lists`), never as an [N, L] table; ``label_lists``: the labels' own lists with this
    visible mask when made already (:func:`merge_all`'s): the merged lists are then read from them
    (:func:`merged_lists`, the same entries).
    """
    views = len(merges)
    if label_lists is not None:
        lists = merged_lists(label_lists, merges)
    else:
        if visible is None:
            visible = stats.visible(min_visibility)
        lists = visible_lists(lambda lo, hi: merged_label_rows(stats, merges, lo, hi), visible)
    counts = [m.num_instances for m in merges]
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    width = int(max(counts, default=0)) + 1
    links = []
    for v, hist in enumerate(_histograms_of_lists(lists, stats.label.shape[1], width, width)):
        if counts[v] == 0:
            continue
        links += view_links(hist, v, share, counts, offsets)
    total = int(offsets[-1])
    uf = UnionFind(total)
    view_of = np.repeat(np.arange(views), counts)
    masks = {i: 1 << int(view_of[i]) for i in range(total)}
    for strength, a, b in sorted(links, key=lambda t: (-t[0], t[1], t[2])):
        ra, rb = uf.find(int(a)), uf.find(int(b))
        if ra == rb or masks[ra] & masks[rb]:
            continue
        uf.union(ra, rb)
        root = uf.find(ra)
        masks[root] = masks[ra] | masks[rb]
    roots = [uf.find(i) for i in range(total)]
    ids = {r: k + 1 for k, r in enumerate(sorted(set(roots)))}
    luts = []
    for v in range(views):
        lut = np.zeros(counts[v] + 1, np.int64)
        lut[1:] = [ids[roots[offsets[v] + m]] for m in range(counts[v])]
        luts.append(lut)
    return luts


# ----------------------------------------------------------------------------------------------
# The `merge` step
# ----------------------------------------------------------------------------------------------


def merge_all(stats: GITStats | GITVisible, hierarchies: Sequence,
              params: MergeParams) -> tuple[list[ViewMerge], list[np.ndarray]]:
    """Merge every traced view (``hierarchies``: the views' :class:`PatchHierarchy`, in stats order) and
    associate the results across views. Returns the per-view merges and global-id luts. ``stats``:
    the GIT table, or only its labels and visible mask (:class:`GITVisible`, what the step reads)."""
    merges = []
    num_labels = int(stats.num_labels.max(initial=1))
    num_source = max(num_labels, max((h.num_patches + 1 for h in hierarchies), default=1))
    visible = stats.visible(params.min_visibility)
    # the labels' per-Gaussian lists: the source histograms, every view's label counts and (through the
    # merges' luts) the association's lists are read from them
    lists = visible_lists(lambda lo, hi: stats.label[lo:hi], visible)
    every = _histograms_of_lists(lists, stats.label.shape[1], num_source, num_labels)
    counts = label_counts(lists, stats.label.shape[1], num_source) if params.method != "hierarchical" else None
    rule = params.rule
    if params.method == "hierarchical":
        comember = stack_comembership([comembership(h, num_labels, params.mask_weight) for h in hierarchies],
                                      num_labels)
    for v, (hierarchy, hist) in enumerate(zip(hierarchies, every)):
        if params.method == "hierarchical":
            pairs = candidate_pairs(hierarchy, "all_pairs")
            sims, omega = mask_vote(hist, pairs, comember, v)
            lut = average_linkage(hierarchy.num_patches, pairs, sims, omega, params.threshold)
            merges.append(ViewMerge(stats.frames[v], lut, pairs, sims, omega, sims > params.threshold))
            continue
        c = view_candidates(hierarchy, params.candidates)
        rank = released_ids(hierarchy) if params.grouping == "released_greedy" else None
        merges.append(merge_view(stats, v, hierarchy.num_patches, c.pairs, params.threshold, params.min_visibility,
                                 hist=hist, rule=rule, visible=visible, grouping=params.grouping, rank=rank,
                                 collapsed=c.collapsed, groups=c.groups, start=c.start, counts=counts[v]))
    hist = None  # the last histogram block
    every.close()
    luts = associate(stats, merges, params.min_visibility, params.association_share, visible=visible,
                     label_lists=lists)
    return merges, luts


def run_merge(scene, git_dir: Path, patches_dir: Path, out_dir: Path, params: dict) -> dict:
    """The ``merge`` step: consistent instance maps ``instances/<frame>.png`` (16-bit, ids consistent
    across views, 0 = no instance), ``merge.json`` and ``preview.png`` in ``out_dir``."""
    from ..errors import SceneFormatError
    from ..io import write_json
    from ..masks.patches import read_patches
    from ..params import from_mapping, to_dict
    from ..scene import write_u16

    p = from_mapping(MergeParams, params, "merge params")
    stats = GITVisible.load(Path(git_dir) / "git.npz", p.min_visibility)  # prob is not read, visibility only as the mask
    start = time.perf_counter()
    maps, hierarchies = [], []
    for frame in stats.frames:
        patch_map, hierarchy = read_patches(patches_dir, frame)
        maps.append(patch_map)
        hierarchies.append(hierarchy)
    for v, (frame, patch_map) in enumerate(zip(stats.frames, maps)):
        if int(patch_map.max(initial=0)) + 1 > int(stats.num_labels[v]) and int(patch_map.max(initial=0)) > 0:
            raise SceneFormatError(f"{Path(patches_dir) / (frame + '.png')}: the patch map has ids up to "
                                   f"{int(patch_map.max())} but the GIT trace saw {int(stats.num_labels[v])} labels; "
                                   f"the trace is stale (rerun the trace step).")
    merges, luts = merge_all(stats, hierarchies, p)
    frames = stats.frames
    del stats  # the [G, V] arrays: the rest reads the merges and the [V, P] maps
    seconds = time.perf_counter() - start
    out_dir = Path(out_dir)
    (out_dir / "instances").mkdir(parents=True, exist_ok=True)
    outputs = []
    for frame, patch_map, m, lut in zip(frames, maps, merges, luts):
        instance_map = lut[m.lut[patch_map.astype(np.int64)]]
        if instance_map.max(initial=0) > 65535:
            raise ValueError(f"merge: {frame}: more than 65535 global instances.")
        write_u16(out_dir / "instances" / f"{frame}.png", instance_map.astype(np.uint16))
        outputs.append(instance_map)
    views = []
    for m in merges:
        views.append({
            "frame": m.frame, "patches": int(len(m.lut) - 1), "instances": m.num_instances,
            "pairs_considered": int(len(m.pairs)),
            "unsupported": int((~m.supported).sum()) if m.supported is not None else 0,
            "collapsed": [[int(a), int(b)] for a, b in m.collapsed] if m.collapsed is not None else [],
            "merged": [[int(a), int(b), round(float(s), 4)] for (a, b), s, ok in zip(m.pairs, m.sims, m.merged) if ok],
            "similarities": [[int(a), int(b), round(float(s), 4), int(o)] for (a, b), s, o in zip(m.pairs, m.sims, m.omega)],
        })
    report = {
        "params": to_dict(p), "seconds": seconds, "views": len(merges),
        "global_instances": int(max((int(l.max(initial=0)) for l in luts), default=0)),
        "mean_patches": float(np.mean([len(m.lut) - 1 for m in merges])) if merges else 0.0,
        "mean_instances": float(np.mean([m.num_instances for m in merges])) if merges else 0.0,
        "merged_pairs": int(sum(int(m.merged.sum()) for m in merges)),
        "pairs_considered": int(sum(len(m.pairs) for m in merges)),
        "collapsed_pairs": int(sum(len(m.collapsed) for m in merges if m.collapsed is not None)),
    }
    if scene is not None and scene.has_instances and scene.objects is not None:
        table = scene.objects.lookup(p.ground_truth_level)
        truths = []
        for frame in frames:
            leaf = scene.instances(frame).astype(np.int64)
            truths.append(table[np.clip(leaf, 0, len(table) - 1)])
        before = segmentation_quality(truths, maps)
        after = segmentation_quality(truths, outputs)
        pair_total = PairQuality()
        for entry, truth, patch_map, m in zip(views, truths, maps, merges):
            q, reach = view_pair_quality(truth, patch_map, m)
            pair_total.add(q)
            entry["pairs_vs_truth"] = {**{key: int(getattr(q, key)) for key in q.__dataclass_fields__},
                                       "out_of_reach_pairs": reach}
        report["ground_truth"] = {"level": p.ground_truth_level, "before": before.__dict__, "after": after.__dict__,
                                  "pairs": pair_total.to_dict()}
        log.info("merge vs ground truth: ARI %.3f -> %.3f, covered %.3f -> %.3f, straddling %.3f -> %.3f",
                 before.ari, after.ari, before.covered, after.covered, before.straddling, after.straddling)
        log.info("merge pairs vs ground truth: %d merged of %d candidates, %d of %d should-merge pairs were "
                 "candidates (%d out of reach), precision %s, recall %s", pair_total.merged, pair_total.candidates,
                 pair_total.candidates_should_merge, pair_total.should_merge, pair_total.out_of_reach,
                 _fmt(pair_total.precision), _fmt(pair_total.recall))
        if p.preview_views > 0:
            write_merge_preview(scene, frames, maps, outputs, truths, out_dir / "preview.png", p.preview_views)
    report["per_view"] = views
    write_json(out_dir / "merge.json", report)
    return report


def _fmt(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.3f}"


def count_ids(label_map: np.ndarray) -> int:
    """Number of distinct non-zero ids in a label map."""
    ids = np.unique(label_map)
    return int((ids > 0).sum())


def write_merge_preview(scene, frames, patch_maps, instance_maps, truths, path: Path, count: int) -> None:
    """Rows of (image, raw patches, consistent instances, ground truth) for ``count`` views."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..preview import label_overlay

    picks = np.linspace(0, len(frames) - 1, min(count, len(frames))).round().astype(int)
    fig, axes = plt.subplots(len(picks), 4, figsize=(11, 2.3 * len(picks)), squeeze=False)
    for row, v in enumerate(picks):
        image = scene.image(frames[v])
        panels = [(image / 255.0, f"{frames[v]}"), (label_overlay(image, patch_maps[v]), f"patches ({count_ids(patch_maps[v])})"),
                  (label_overlay(image, instance_maps[v]), f"consistent ({count_ids(instance_maps[v])})"),
                  (label_overlay(image, truths[v]), "ground-truth objects")]
        for ax, (img, title) in zip(axes[row], panels):
            ax.imshow(np.clip(img, 0, 1))
            ax.set_title(title, fontsize=8)
            ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
