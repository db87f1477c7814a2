"""Consistency beyond the paper: the mask-level vote and average-linkage grouping
(``merge: {method: hierarchical}``; docs/tracing.md, "The hierarchical merge").

The paper's vote (:mod:`.merge`) asks, for two patches P_a, P_b of a view v0, whether the Gaussians
of G_a and G_b fall into the *same patch* of the other views. Patches are the finest pieces of a
view's nested masks, and the other views cut an object into the same kind of pieces, so two parts
of one object mostly land in different patches there and the vote says "different" (median 0.33 on
the benchmark's should-merge pairs). What the other views do say, most of the time, is that the two
parts lie under one *common mask* (the whole object, SAM's "whole" level), while two different
objects lie under a common mask only when the view happened to emit a mask of their group.

The mask-level vote replaces the identity "same patch" by the co-membership C_v of view v:
C_v[l, l'] = 1 when patches l and l' of view v lie under at least one common mask of v (l = l'
included), from the view's patch hierarchy. Over the other views,

    sim(P_a, P_b) = sum_v sum_{i in G_a, j in G_b voting in v} C_v[label_v(i), label_v(j)]
                    / sum_v n_a[v] n_b[v],

the chance that a Gaussian of P_a and one of P_b share a mask in a view that sees both. With C_v
the identity it is the paper's vote. It factors like the paper's vote into the per-view label
histograms: sum_v h_a[v]^T C_v h_b[v] (:func:`mask_vote`; :func:`mask_vote_bruteforce` is the
literal pair loop the tests compare against). Label 0 (pixels no mask covers) has no vote.

Every pair of patches of the view is compared (a part with no enclosing mask in v0 is still in
reach) and the view's patches are grouped by average linkage (:func:`average_linkage`): the two
groups whose mean pair similarity is largest join while it exceeds the threshold, so one high pair
cannot chain two objects together as a union of pairs does.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np


def patch_pair_matrix(values: np.ndarray, num_labels: int) -> np.ndarray:
    """[T, T] float64 from ``values`` [P + 1, P + 1] (a score for every pair of one view's patches): 1 on
    the diagonal (the same patch), 0 in row and column 0 (uncovered pixels), cut or padded with zeros to
    T = ``num_labels``."""
    p = values.shape[0]
    size = max(int(num_labels), p)
    out = np.zeros((size, size))
    out[:p, :p] = values
    idx = np.arange(1, p)
    out[idx, idx] = 1.0
    out[0, :] = 0.0
    out[:, 0] = 0.0
    return out[:num_labels, :num_labels]


def comembership(hierarchy, num_labels: int, mask_weight: float = 1.0) -> np.ndarray:
    """[T, T] float64 co-membership of one view's patches (T = ``num_labels``, padded with zeros):
    1 where l == l' (the same patch), ``mask_weight`` where patches l != l' lie under a common mask of
    the view, 0 otherwise (l, l' >= 1); row and column 0 (uncovered pixels) are 0."""
    member = hierarchy.membership().astype(np.int64)  # [P + 1, M]
    return patch_pair_matrix(np.where((member @ member.T) > 0, float(mask_weight), 0.0), num_labels)


def stack_comembership(comember: Sequence[np.ndarray], num_labels: int) -> np.ndarray:
    """[L, T - 1, T - 1] float64: every view's :func:`comembership` over labels 1..T-1 (label 0 has no
    vote), padded with zeros to ``num_labels`` = T (a view's labels beyond its array share nothing)."""
    out = np.zeros((len(comember), max(0, num_labels - 1), max(0, num_labels - 1)))
    for v, c in enumerate(comember):
        t = min(num_labels, c.shape[0])
        out[v, :t - 1, :t - 1] = c[1:t, 1:t]
    return out


def mask_vote(hist: np.ndarray, pairs: np.ndarray, comember: np.ndarray | Sequence[np.ndarray],
              source_view: int) -> tuple[np.ndarray, np.ndarray]:
    """Mask-level similarities of patch ``pairs`` of one source view (factored form).

    Args:
        hist: [A, L, T] int label histograms of each source patch's Gaussians per view (the merge's
            :func:`.merge.all_source_histograms`; the source view's slice is zero).
        pairs: [K, 2] source patch ids.
        comember: [L, T - 1, T - 1] (:func:`stack_comembership`), or L arrays [T_v, T_v] bool
            (:func:`comembership` of each view).
        source_view: v0, left out of the vote.
    Returns:
        sim [K] float64 (0 where no view votes) and |Omega| [K] int64, the (Gaussian, Gaussian,
        view) triples that voted.
    """
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    num_labels = hist.shape[2]
    if not isinstance(comember, np.ndarray) or comember.ndim != 3:
        comember = stack_comembership(comember, num_labels)
    if len(pairs) == 0:
        return np.zeros(0), np.zeros(0, np.int64)
    h = hist[:, :, 1:].astype(np.float64)  # [A, L, T - 1]: label 0 has no vote
    h[:, source_view] = 0.0
    n = h.sum(axis=2)  # [A, L]
    per_view = np.ascontiguousarray(h.transpose(1, 0, 2))  # [L, A, T - 1]
    spread = np.matmul(per_view, comember)  # each view's histograms times its C_v
    same_all = np.tensordot(spread, per_view, axes=([0, 2], [0, 2]))  # [A, A]: sum_v h_a[v]^T C_v h_b[v]
    a, b = pairs[:, 0], pairs[:, 1]
    same = same_all[a, b]
    total = np.einsum("kv,kv->k", n[a], n[b])
    return np.where(total > 0, same / np.maximum(total, 1), 0.0), total.astype(np.int64)


def mask_vote_bruteforce(labels: np.ndarray, visible: np.ndarray, comember: Sequence[np.ndarray],
                         source_view: int, a: int, b: int) -> tuple[float, int]:
    """The mask-level vote as a literal loop over Gaussian pairs and views (the twin of
    :func:`mask_vote`). labels: [N, L] argmax labels; visible: [N, L] bool."""
    ga = [i for i in range(labels.shape[0]) if visible[i, source_view] and labels[i, source_view] == a]
    gb = [i for i in range(labels.shape[0]) if visible[i, source_view] and labels[i, source_view] == b]
    same, total = 0.0, 0
    for v in range(labels.shape[1]):
        if v == source_view:
            continue
        for i in ga:
            li = labels[i, v]
            if not visible[i, v] or li < 1:
                continue
            for j in gb:
                lj = labels[j, v]
                if not visible[j, v] or lj < 1:
                    continue
                total += 1
                c = comember[v]
                same += float(c[li, lj]) if li < c.shape[0] and lj < c.shape[0] else 0.0
    return (same / total if total else 0.0), total


def average_linkage(num_patches: int, pairs: np.ndarray, sims: np.ndarray, omega: np.ndarray,
                    threshold: float) -> np.ndarray:
    """Group patches 1..num_patches of one view by average linkage.

    Every patch starts alone; the two groups whose mean similarity over their compared pairs
    (pairs with ``omega`` > 0; a pair never compared does not count) is largest join while that mean
    exceeds ``threshold``. Ties go to the pair of groups with the smallest ids.

    Returns:
        lut [num_patches + 1] int64: patch id -> group id (0 -> 0; groups numbered 1.. in the order
        of their smallest patch).
    """
    n = int(num_patches)
    lut = np.zeros(n + 1, np.int64)
    if n == 0:
        return lut
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    sum_ = np.zeros((n + 1, n + 1))
    cnt = np.zeros((n + 1, n + 1))
    for (a, b), s, o in zip(pairs, sims, omega):
        if o > 0 and a != b and a > 0 and b > 0:
            sum_[a, b] += s
            sum_[b, a] += s
            cnt[a, b] += 1
            cnt[b, a] += 1
    alive = list(range(1, n + 1))
    members = {p: [p] for p in alive}
    while len(alive) > 1:
        idx = np.asarray(alive)
        c = cnt[np.ix_(idx, idx)]
        mean = np.where(c > 0, sum_[np.ix_(idx, idx)] / np.maximum(c, 1), -np.inf)
        np.fill_diagonal(mean, -np.inf)
        k = int(np.argmax(mean))
        i, j = divmod(k, len(idx))
        if not mean[i, j] > threshold:
            break
        keep, gone = int(idx[min(i, j)]), int(idx[max(i, j)])
        sum_[keep, :] += sum_[gone, :]
        sum_[:, keep] += sum_[:, gone]
        cnt[keep, :] += cnt[gone, :]
        cnt[:, keep] += cnt[:, gone]
        sum_[keep, keep] = cnt[keep, keep] = 0.0
        members[keep] += members.pop(gone)
        alive.remove(gone)
    for g, root in enumerate(sorted(alive, key=lambda r: min(members[r])), start=1):
        lut[members[root]] = g
    return lut
