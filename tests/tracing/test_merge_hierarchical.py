"""The hierarchical merge (trace3d/tracing/consistency.py): the mask-level vote against its literal
pair loop, and the grouping on hand-built views where the right answer is known."""

from __future__ import annotations

import numpy as np
import pytest

from tests.tracing.test_merge_rules import hierarchy, stats_from  # the hand-built GIT arrays and patch hierarchies
from trace3d.tracing.consistency import average_linkage, comembership, mask_vote, mask_vote_bruteforce
from trace3d.tracing.merge import MergeParams, merge_all, source_histograms

pytestmark = pytest.mark.usefixtures("single_numba_thread")


def test_comembership_is_shared_masks_and_the_diagonal():
    # patches 1, 2 under mask 0 (a whole); patch 3 alone in mask 1; patch 4 in no mask but its own 2
    c = comembership(hierarchy([[0], [0], [1], [2]]), 6)
    assert c.shape == (6, 6) and c.dtype == np.float64
    assert c[1, 2] == c[2, 1] == c[1, 1] == c[4, 4] == 1.0
    assert not c[1, 3] and not c[3, 4] and not c[0].any() and not c[:, 0].any() and not c[5].any()
    half = comembership(hierarchy([[0], [0], [1], [2]]), 6, mask_weight=0.25)
    assert half[1, 2] == 0.25 and half[1, 1] == 1.0 and half[1, 3] == 0.0


def _random_case(seed, weight=1.0):
    rng = np.random.default_rng(seed)
    n, views, labels_per_view = 60, 5, 5
    labels = rng.integers(-1, labels_per_view, size=(n, views)).astype(np.int32)
    visible = rng.random((n, views)) > 0.2
    hierarchies = []
    for _ in range(views):
        masks = [sorted(set(rng.choice(4, size=rng.integers(1, 3), replace=False).tolist()))
                 for _ in range(labels_per_view - 1)]
        hierarchies.append(hierarchy(masks))
    comember = [comembership(h, labels_per_view, weight) for h in hierarchies]
    return labels, visible, comember


@pytest.mark.parametrize("seed,weight", [(0, 1.0), (1, 0.4), (2, 0.75)])
def test_mask_vote_equals_the_literal_pair_loop(seed, weight):
    labels, visible, comember = _random_case(seed, weight)
    for v0 in range(labels.shape[1]):
        hist = source_histograms(labels, visible, v0, 5, 5)
        pairs = np.array([[a, b] for a in range(5) for b in range(a + 1, 5)])
        sims, omega = mask_vote(hist, pairs, comember, v0)
        for (a, b), s, o in zip(pairs, sims, omega):
            ref, ref_o = mask_vote_bruteforce(labels, visible, comember, v0, a, b)
            assert o == ref_o
            assert s == pytest.approx(ref, abs=1e-12)


def test_mask_weight_zero_is_the_papers_vote():
    labels, visible, _ = _random_case(3)
    rng = np.random.default_rng(3)
    views = [hierarchy([[int(m)] for m in rng.integers(0, 2, size=4)]) for _ in range(labels.shape[1])]
    identity = [comembership(h, 5, mask_weight=0.0) for h in views]
    assert not (identity[0] - np.diag(np.r_[0.0, np.ones(4)])).any()
    from trace3d.tracing.merge import VoteRule, vote
    hist = source_histograms(labels, visible, 0, 5, 5)
    pairs = np.array([[1, 2], [1, 3], [2, 4], [3, 4]])
    sims, omega = mask_vote(hist, pairs, identity, 0)
    ref, ref_o, _ = vote(hist, pairs, rule=VoteRule(uncovered="exclude"))
    np.testing.assert_allclose(sims, ref)
    np.testing.assert_array_equal(omega, ref_o)


def test_parts_under_a_whole_merge_where_the_patch_vote_cannot():
    # Gaussians 0-9: object A (parts a1 = 0-4, a2 = 5-9); 10-19: object B. Every view cuts A into its two
    # parts (as SAM's part masks do), with A's whole mask around them in views 1-4 of 6; B is one patch.
    # View 0 (the source): patches 1 = a1, 2 = a2, 3 = B; its own masks give no common mask to a1, a2.
    labels = np.zeros((20, 6), np.int32)
    labels[:, :] = np.r_[np.full(5, 1), np.full(5, 2), np.full(10, 3)][:, None]
    stats = stats_from(labels)
    parts_only = hierarchy([[0], [1], [2]])
    with_whole = hierarchy([[0, 3], [1, 3], [2]])
    views = [parts_only, with_whole, with_whole, with_whole, with_whole, parts_only]
    paper, _ = merge_all(stats, views, MergeParams(candidates="all_pairs"))
    assert paper[0].num_instances == 3  # the argmax-patch vote: a1 and a2 never share a patch
    merges, luts = merge_all(stats, views, MergeParams(method="hierarchical", mask_weight=1.0))
    m = merges[0]
    assert m.pairs.tolist() == [[1, 2], [1, 3], [2, 3]]
    np.testing.assert_allclose(m.sims, [0.8, 0.0, 0.0])  # 4 of the 5 other views hold a1, a2 under A's whole
    assert m.lut.tolist() == [0, 1, 1, 2]
    assert merges[1].sims[0] == pytest.approx(0.6) and merges[1].num_instances == 2
    assert luts[0][m.lut[1]] == luts[1][merges[1].lut[1]]  # A has one id in views 0 and 1
    # a threshold above the share of views with the whole keeps the parts apart
    apart, _ = merge_all(stats, views, MergeParams(method="hierarchical", mask_weight=1.0, threshold=0.8))
    assert apart[0].num_instances == 3


def test_average_linkage_does_not_chain_where_union_find_does():
    # 1-2 and 3-4 are two objects; one wrong high pair (2, 3) would chain them under a union of pairs.
    pairs = np.array([[1, 2], [3, 4], [2, 3], [1, 3], [1, 4], [2, 4]])
    sims = np.array([0.9, 0.9, 0.6, 0.1, 0.0, 0.1])
    lut = average_linkage(4, pairs, sims, np.ones(6), 0.5)
    assert lut.tolist() == [0, 1, 1, 2, 2]
    # the same pairs with a strong link between the groups: the mean (0.6+0.7+0.6+0.7)/4 exceeds 0.5
    sims2 = np.array([0.9, 0.9, 0.6, 0.7, 0.6, 0.7])
    assert average_linkage(4, pairs, sims2, np.ones(6), 0.5).tolist() == [0, 1, 1, 1, 1]
    # pairs nobody voted on (omega 0) do not count: 1-2 joins on its one compared pair
    lut = average_linkage(3, np.array([[1, 2], [1, 3]]), np.array([0.9, 0.0]), np.array([5, 0]), 0.5)
    assert lut.tolist() == [0, 1, 1, 2]
    assert average_linkage(0, np.zeros((0, 2)), np.zeros(0), np.zeros(0), 0.5).tolist() == [0]


def test_method_is_checked():
    with pytest.raises(ValueError, match="method"):
        MergeParams(method="votes")
    assert MergeParams(method="hierarchical").threshold == pytest.approx(0.4)
    assert MergeParams(method="hierarchical").mask_weight == pytest.approx(0.25)
