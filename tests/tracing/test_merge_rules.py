"""The merge's rules on hand-built GIT arrays (no rendering): candidate pairs, label 0 in the vote,
minimum support, and the per-pair precision / recall against the ground truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from trace3d.errors import ConfigError
from trace3d.masks.patches import PatchHierarchy
from trace3d.params import from_mapping
from trace3d.tracing.git import GITStats
from trace3d.tracing.merge import (PLAIN, MergeParams, ViewMerge, VoteRule, candidate_pairs, conflict_areas,
                                   merge_all, merge_view, pair_similarity_bruteforce, released_greedy, released_ids,
                                   source_histograms, view_candidates, vote)
from trace3d.tracing.merge_quality import patch_owners, view_pair_quality

pytestmark = pytest.mark.usefixtures("single_numba_thread")


def stats_from(labels) -> GITStats:
    labels = np.asarray(labels, np.int32)
    return GITStats(label=labels, prob=(labels >= 0).astype(np.float32), visibility=(labels >= 0).astype(np.float32),
                    frames=[f"v{i}" for i in range(labels.shape[1])],
                    num_labels=np.full(labels.shape[1], int(labels.max()) + 1, np.int64))


def hierarchy(masks: list[list[int]], areas: list[int] | None = None) -> PatchHierarchy:
    """Patches 1..P, each listed with the masks containing it (and its pixel count: 1 unless given)."""
    count = 1 + max((m for ms in masks for m in ms), default=0)
    areas = np.ones(len(masks), np.int64) if areas is None else np.asarray(areas, np.int64)
    mask_areas = np.array([sum(a for a, ms in zip(areas, masks) if m in ms) for m in range(count)], np.int64)
    return PatchHierarchy(masks, areas, mask_areas, np.ones(count, np.float32))


def whole(num_patches: int) -> PatchHierarchy:
    return hierarchy([[0]] * num_patches)


# ----------------------------------------------------------------------------------------------
# Candidate pairs
# ----------------------------------------------------------------------------------------------


def test_all_pairs_merges_an_object_no_coarser_mask_joins():
    # Gaussians 0-9: object A, 10-19: object B. View 0 splits A into patches 1 (0-4) and 2 (5-9),
    # B is patch 3; each patch is its own mask (no coarser mask around 1 and 2). Views 1, 2 see A
    # as label 1 and B as label 2.
    labels = np.zeros((20, 3), np.int32)
    labels[:, 0] = np.r_[np.full(5, 1), np.full(5, 2), np.full(10, 3)]
    labels[:, 1] = labels[:, 2] = np.r_[np.full(10, 1), np.full(10, 2)]
    stats = stats_from(labels)
    views = [hierarchy([[0], [1], [2]]), hierarchy([[0], [1]]), hierarchy([[0], [1]])]
    coarse, _ = merge_all(stats, views, MergeParams())
    assert len(coarse[0].pairs) == 0 and coarse[0].num_instances == 3  # out of reach of the coarser-mask rule
    every, luts = merge_all(stats, views, MergeParams(candidates="all_pairs"))
    assert every[0].pairs.tolist() == [[1, 2], [1, 3], [2, 3]]
    np.testing.assert_allclose(every[0].sims, [1.0, 0.0, 0.0])
    assert every[0].lut[1] == every[0].lut[2] != every[0].lut[3] and every[0].num_instances == 2
    assert luts[0][every[0].lut[1]] == luts[1][every[1].lut[1]]  # A has one id in views 0 and 1
    with pytest.raises(ConfigError, match="candidates"):
        from_mapping(MergeParams, {"candidates": "everything"}, "merge params")


# ----------------------------------------------------------------------------------------------
# Label 0 (uncovered pixels)
# ----------------------------------------------------------------------------------------------


def uncovered_elsewhere():
    """Patches 1 (Gaussians 0-4) and 2 (5-9) of view 0, inside one coarser mask; the Gaussians are
    uncovered (label 0) in views 1 and 2 and on different patches in view 3."""
    labels = np.zeros((10, 4), np.int32)
    labels[:, 0] = np.r_[np.full(5, 1), np.full(5, 2)]
    labels[:, 3] = np.r_[np.full(5, 1), np.full(5, 2)]
    return stats_from(labels), [whole(2), whole(1), whole(1), whole(2)]


def test_agreement_on_uncovered_pixels_is_not_a_vote():
    stats, views = uncovered_elsewhere()
    as_label, _ = merge_all(stats, views, MergeParams(uncovered="label"))
    assert as_label[0].sims[0] == pytest.approx(2 / 3) and as_label[0].omega[0] == 75  # 50 of 75 pairs "agree" on 0
    assert as_label[0].num_instances == 1  # the old behaviour merges them
    for preset in ("paper", "official"):
        assert MergeParams(preset=preset).uncovered == "exclude"
    excluded, _ = merge_all(stats, views, MergeParams())
    assert excluded[0].sims[0] == 0.0 and excluded[0].omega[0] == 25  # only view 3 votes: they disagree
    assert excluded[0].num_instances == 2
    # with view 3 gone, the two sets agree only on being uncovered: no vote at all, no merge
    stats.label[:, 3] = 0
    none, _ = merge_all(stats, views, MergeParams(threshold=0.0))
    assert none[0].omega[0] == 0 and none[0].num_instances == 2
    merged_anyway, _ = merge_all(stats, views, MergeParams(uncovered="label", threshold=0.0))
    assert merged_anyway[0].num_instances == 1


# ----------------------------------------------------------------------------------------------
# Minimum support (official preset)
# ----------------------------------------------------------------------------------------------


def test_official_preset_values():
    official, paper = MergeParams(preset="official"), MergeParams()
    assert (official.threshold, official.min_visibility, official.min_gaussians, official.min_view_share,
            official.min_views, official.min_gaussian_views) == (0.4, 0.0, 100, 0.2, 2, 3)
    assert (paper.threshold, paper.min_visibility, paper.min_gaussians, paper.min_view_share, paper.min_views,
            paper.min_gaussian_views) == (0.5, 0.0, 0, 0.0, 1, 0)
    assert MergeParams(preset="official", min_gaussians=5).min_gaussians == 5  # a key overrides the preset
    with pytest.raises(ConfigError, match="min_view_share"):
        from_mapping(MergeParams, {"min_view_share": 1.5}, "merge params")


def one_object_in_two_patches(size: int, views: int = 4) -> GITStats:
    """Patches 1 and 2 of view 0 hold ``size`` Gaussians each; every other view sees all of them as label 1."""
    labels = np.ones((2 * size, views), np.int32)
    labels[size:, 0] = 2
    return stats_from(labels)


def test_a_patch_needs_more_than_min_gaussians():
    rule = dict(preset="official", min_gaussian_views=0)
    for size, merged in ((100, False), (101, True)):  # GAUS_NUM_TH: more than 100
        stats = one_object_in_two_patches(size)
        merges, _ = merge_all(stats, [whole(2)] + [whole(1)] * 3, MergeParams(**rule))
        assert bool(merges[0].supported[0]) is merged and (merges[0].num_instances == 1) is merged
        assert merges[0].sims[0] == (1.0 if merged else 0.0)


def test_view_share_and_number_of_voting_views():
    # G_a = Gaussians 0-9 (patch 1), G_b = 10-19 (patch 2). View 1: all agree (label 1). View 2: only
    # Gaussians 0-1 of G_a (20 %) have a vote, on a label G_b does not have (3); the rest uncovered.
    labels = np.zeros((20, 3), np.int32)
    labels[:, 0] = np.r_[np.full(10, 1), np.full(10, 2)]
    labels[:, 1] = 1
    labels[:2, 2] = 3
    labels[10:, 2] = 1
    stats = stats_from(labels)
    views = [whole(2), whole(1), hierarchy([[0], [0], [0]])]
    every, _ = merge_all(stats, views, MergeParams(threshold=0.9))
    assert every[0].sims[0] == pytest.approx(100 / 120)  # view 2's 2 x 10 disagreeing pairs vote
    assert every[0].num_instances == 2
    share, _ = merge_all(stats, views, MergeParams(threshold=0.9, min_view_share=0.2))
    assert share[0].sims[0] == 1.0 and share[0].omega[0] == 100  # 20 % is not more than 0.2: view 2 is out
    assert share[0].num_instances == 1
    # one voting view left: under min_views 2 the pair is unsupported and stays apart
    two, _ = merge_all(stats, views, MergeParams(threshold=0.9, min_view_share=0.2, min_views=2))
    assert not two[0].supported[0] and two[0].sims[0] == 0.0 and two[0].num_instances == 2


def test_gaussians_with_few_voting_views_do_not_vote():
    # G_a = 0-9, G_b = 10-19. Views 1-3: all agree on label 1, except Gaussians 0-5 of G_a, which are
    # on label 2 in view 1 and uncovered in views 2 and 3 (one voting view each).
    labels = np.ones((20, 4), np.int32)
    labels[:, 0] = np.r_[np.full(10, 1), np.full(10, 2)]
    labels[:6, 1] = 2
    labels[:6, 2:] = 0
    stats = stats_from(labels)
    views = [whole(2)] + [hierarchy([[0], [0]])] * 3
    base = dict(threshold=0.8, min_gaussians=0, min_view_share=0.2, min_views=2)
    plain, _ = merge_all(stats, views, MergeParams(**base, min_gaussian_views=0))
    assert plain[0].sims[0] == pytest.approx((4 + 4 + 4) * 10 / ((10 + 4 + 4) * 10))  # 120 / 180
    assert plain[0].num_instances == 2
    strict, _ = merge_all(stats, views, MergeParams(**base, min_gaussian_views=3))
    assert strict[0].sims[0] == 1.0 and strict[0].omega[0] == 3 * 4 * 10  # Gaussians 0-5 are out
    assert strict[0].num_instances == 1


RULES = [PLAIN, VoteRule(), VoteRule("exclude", 3, 0.2, 2, 0), VoteRule("exclude", 2, 0.3, 2, 2),
         VoteRule("label", 0, 0.1, 1, 3)]


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("rule", RULES, ids=[str(i) for i in range(len(RULES))])
def test_merge_view_equals_the_literal_pair_loop(seed, rule):
    rng = np.random.default_rng(seed)
    n, views, t = 60, 6, 4
    labels = rng.integers(-1, t, size=(n, views)).astype(np.int32)
    labels[rng.random((n, views)) < 0.3] = 0  # plenty of uncovered labels
    stats = stats_from(labels)
    stats.num_labels[:] = t
    visible = stats.visible(0.0)
    pairs = np.array([(a, b) for a in range(1, t) for b in range(a + 1, t)])
    for v0 in range(views):
        m = merge_view(stats, v0, t - 1, pairs, 0.5, 0.0, rule=rule)
        for (a, b), s, o in zip(pairs, m.sims, m.omega):
            ref_s, ref_o = pair_similarity_bruteforce(labels, visible, v0, int(a), int(b), rule)
            assert o == ref_o
            assert s == pytest.approx(ref_s, abs=1e-12)
        if rule.min_gaussian_views == 0:  # the factored vote alone (the histograms' path)
            hist = source_histograms(labels, visible, v0, t, t)
            counts = np.bincount(labels[visible[:, v0], v0], minlength=t)
            sims, omega, _ = vote(hist, pairs, counts, rule)
            np.testing.assert_array_equal(omega, m.omega)


# ----------------------------------------------------------------------------------------------
# Precision and recall of the merge decisions against the ground truth
# ----------------------------------------------------------------------------------------------


def test_pair_precision_and_recall_on_a_hand_built_view():
    # one row of 14 pixels: object 1 on 0-5, object 2 on 6-9, unlabelled 10-13
    truth = np.array([[1] * 6 + [2] * 4 + [0] * 4])
    # patches: 1 = 0-2, 2 = 3-5 (object 1); 3 = 6-7, 4 = 8 (object 2); 6 = 9-12 (one pixel of object
    # 2, three unlabelled: mostly unlabelled, left out); 5 = 13 (unlabelled, left out)
    patches = np.array([[1, 1, 1, 2, 2, 2, 3, 3, 4, 6, 6, 6, 6, 5]])
    assert patch_owners(truth, patches, 6).tolist() == [0, 1, 1, 2, 2, 0, 0]
    pairs = np.array([[1, 2], [2, 3], [1, 5], [3, 6]])
    merged = np.array([True, True, True, False])
    lut = np.array([0, 1, 1, 1, 2, 1, 3])  # 1, 2, 3 (and 5) end in one instance; 4 and 6 alone
    view = ViewMerge("v0", lut, pairs, np.array([0.9, 0.6, 0.7, 0.1]), np.ones(4, np.int64), merged,
                     np.array([True, True, True, False]))
    q, reach = view_pair_quality(truth, patches, view)
    assert (q.patches, q.excluded_patches) == (4, 2)
    assert (q.candidates, q.candidates_should_merge, q.merged, q.merged_should_merge) == (2, 1, 2, 1)
    assert q.precision == 0.5 and q.recall == 1.0
    assert q.should_merge == 2 and q.out_of_reach == 1 and reach == [[3, 4]] and q.out_of_reach_share == 0.5
    assert (q.joined, q.joined_should_merge) == (3, 1)  # (1,2) right; (1,3), (2,3) wrong
    assert q.joined_precision == pytest.approx(1 / 3) and q.joined_recall == 0.5
    assert q.unsupported == 0  # the unsupported pair (3, 6) has a left-out patch
    assert q.to_dict()["precision"] == 0.5


def test_tracing_table_reports_pair_figures(tmp_path):
    from trace3d.report.tracing import write_tracing_table

    rows = []
    for scene, pairs in (("roomA", {"precision": 0.5, "recall": 1.0, "out_of_reach_share": 0.25, "joined_recall": 0.8}),
                         ("roomB", {"precision": None, "recall": 0.0, "out_of_reach_share": 0.75, "joined_recall": 0.2})):
        folder = tmp_path / scene / "merge-paper"
        folder.mkdir(parents=True)
        quality = {"ari": 0.8, "covered": 0.7, "straddling": 0.1}
        (folder / "merge.json").write_text(json.dumps({
            "params": {"preset": "paper"}, "mean_patches": 6.0, "mean_instances": 5.0, "merged_pairs": 3,
            "seconds": 0.1, "ground_truth": {"before": quality, "after": quality, "pairs": pairs}}))
        rows.append(folder)
    table = write_tracing_table(rows, None, tmp_path / "tracing.md")
    assert table["pair precision"].iloc[0] == 0.5 and np.isnan(table["pair precision"].iloc[1])
    assert table["should-merge out of reach"].tolist() == [0.25, 0.75]
    text = (tmp_path / "tracing.md").read_text()
    assert "should merge when both belong to one object" in text
    header = next(line for line in text.splitlines() if line.startswith("| scene"))
    mean = next(line for line in text.splitlines() if line.startswith("| mean"))
    cells = dict(zip([c.strip() for c in header.split("|")], [c.strip() for c in mean.split("|")]))
    assert cells["should-merge out of reach"] == "0.500" and cells["pair precision"] == "0.500"
    assert cells["should-merge joined"] == "0.500" and cells["pair recall"] == "0.500"


# ----------------------------------------------------------------------------------------------
# Grouping: union-find against the released greedy loop
# ----------------------------------------------------------------------------------------------


def object_in_three_patches() -> GITStats:
    """View 0: object A cut into patches 1, 2, 3 (Gaussians 0-4, 5-9, 10-14), object B is patch 4
    (15-19). Views 1 and 2 see A whole (label 1) and B (label 2): sim = 1 within A, 0 with B."""
    labels = np.zeros((20, 3), np.int32)
    labels[:, 0] = np.repeat([1, 2, 3, 4], 5)
    labels[:, 1] = labels[:, 2] = np.repeat([1, 1, 1, 2], 5)
    return stats_from(labels)


def test_released_greedy_joins_at_most_two_patches():
    stats = object_in_three_patches()
    views = [whole(4), hierarchy([[0], [1]]), hierarchy([[0], [1]])]
    uf, _ = merge_all(stats, views, MergeParams())
    greedy, _ = merge_all(stats, views, MergeParams(grouping="released_greedy"))
    assert uf[0].pairs.tolist() == greedy[0].pairs.tolist() == [[1, 2], [1, 3], [1, 4], [2, 3], [2, 4], [3, 4]]
    np.testing.assert_array_equal(uf[0].sims, greedy[0].sims)
    # union-find: every pair above 0.5 -> {1, 2, 3}, {4}
    assert uf[0].merged.tolist() == [True, True, False, True, False, False]
    assert uf[0].lut.tolist() == [0, 1, 1, 1, 2]
    # released loop: 1 joins 2 (the first later patch above the threshold); 2's Gaussian set empties
    # (c_w_masks[j] & c_w_masks[0]), so 2 gives to nobody and 3 cannot join it; 3 vs 4 is 0 -> {1, 2}, {3}, {4}
    assert greedy[0].merged.tolist() == [True, False, False, False, False, False]
    assert greedy[0].lut.tolist() == [0, 1, 1, 2, 3]
    assert MergeParams(preset="official").grouping == "released_greedy" and MergeParams().grouping == "union_find"
    with pytest.raises(ConfigError, match="grouping"):
        from_mapping(MergeParams, {"grouping": "greedy"}, "merge params")


def test_released_greedy_by_hand():
    rank = np.arange(7)
    pairs = np.array([[1, 2], [1, 3], [2, 3], [2, 4], [3, 4], [4, 5], [5, 6]])
    # 1 -> 2 is below the threshold, 1 -> 3 above: 1 joins 3. 2 -> 3: 3 received (0), 2 -> 4 above: 2 joins
    # 4. 3 and 4 received. 5 -> 6 above: 5 joins 6. The pair (3, 4) and (4, 5) are above too, never taken.
    sims = np.array([0.3, 0.9, 0.8, 0.6, 0.95, 0.99, 0.7])
    merged, moves = released_greedy(pairs, sims, 0.5, rank)
    assert merged.tolist() == [False, True, False, True, False, False, True]
    assert moves == [(1, 3), (2, 4), (5, 6)]
    # exactly the threshold does not merge ("miou > miou_th")
    assert released_greedy(np.array([[1, 2]]), np.array([0.4]), 0.4, np.arange(3))[0].tolist() == [False]
    # the order is the released numbering: with patch 2 first (rank 1 < 2), 2 gives to 1 and 3 stays alone
    merged, moves = released_greedy(pairs[:3], np.array([0.9, 0.9, 0.9]), 0.5, np.array([0, 2, 1, 3]))
    assert merged.tolist() == [True, False, False] and moves == [(2, 1)]


def test_released_greedy_takes_the_sets_afresh_per_area():
    # two conflict areas sharing patch 2: {1, 2, 3} then {2, 4}, every similarity 0.9. Area 1: 1 gives to
    # 2, whose set empties. Area 2 (sets taken afresh): 2 gives to 4. The released pixel relabelling
    # (_change_class_id: the pixels carrying the giver's id take the receiver's) carries 1's pixels along:
    # one instance {1, 2, 4}, and 3 alone. Over one group instead: 1 -> 2 only, 4 alone.
    pairs = np.array([[1, 2], [1, 3], [2, 3], [2, 4]])
    sims = np.full(4, 0.9)
    merged, moves = released_greedy(pairs, sims, 0.5, np.arange(5), groups=[np.array([1, 2, 3]), np.array([2, 4])])
    assert merged.tolist() == [True, False, False, True] and moves == [(1, 2), (2, 4)]
    labels = np.zeros((20, 3), np.int32)
    labels[:, 0] = np.repeat([1, 2, 3, 4], 5)
    labels[:, 1:] = 1
    stats = stats_from(labels)
    areas = merge_view(stats, 0, 4, pairs, 0.5, 0.0, grouping="released_greedy",
                       groups=[np.array([1, 2, 3]), np.array([2, 4])])
    assert areas.lut.tolist() == [0, 1, 1, 2, 1]
    assert merge_view(stats, 0, 4, pairs, 0.5, 0.0, grouping="released_greedy").lut.tolist() == [0, 1, 1, 2, 3]
    # a giver whose id has already moved takes no pixels along: 1 gives to 2, then (area 2) 1 gives to 3
    # again: no pixel carries id 1 any more, so 3 stays alone
    again = merge_view(stats, 0, 4, np.array([[1, 2], [1, 3]]), 0.5, 0.0, grouping="released_greedy",
                       groups=[np.array([1, 2]), np.array([1, 3])])
    assert again.merged.tolist() == [True, True] and again.lut.tolist() == [0, 1, 1, 2, 3]


def test_released_ids_follow_the_membership_order():
    # released _get_mask: patches are the sorted unique rows of the pixels' mask-membership vectors.
    # Patch 1 = (m0, m1) -> (1, 1, 0); patch 2 = (m0) -> (1, 0, 0); patch 3 = (m0, m2) -> (1, 0, 1):
    # sorted (1,0,0) < (1,0,1) < (1,1,0), i.e. 2, 3, 1
    h = hierarchy([[0, 1], [0], [0, 2]])
    assert released_ids(h).tolist() == [0, 3, 1, 2]
    # so the released loop starts with patch 2: with every sim 1, 2 joins 3, and 1 stays alone
    labels = np.zeros((15, 3), np.int32)
    labels[:, 0] = np.repeat([1, 2, 3], 5)
    labels[:, 1] = labels[:, 2] = 1
    merges, _ = merge_all(stats_from(labels), [h, whole(1), whole(1)], MergeParams(grouping="released_greedy"))
    assert merges[0].lut.tolist() == [0, 1, 2, 2]


# ----------------------------------------------------------------------------------------------
# Candidates: the released conflict areas
# ----------------------------------------------------------------------------------------------


def conflict_view() -> PatchHierarchy:
    """Thirteen patches (pixel counts in brackets) under eleven masks:

    - object A: m0 = {1 [50], 2 [30], 3 [20]}, m1 = {2}, m2 = {3};
    - object B: m3 = {4 [96], 5 [4]}, m4 = {4} (a near-duplicate of m3);
    - a lone mask m5 = {6 [10]};
    - two masks that barely touch: m6 = {7 [100], 8 [1]}, m7 = {8, 9 [100]};
    - a chain: m8 = {10, 11}, m9 = {11, 12}, m10 = {12, 13} (10 pixels each).
    """
    return hierarchy([[0], [0, 1], [0, 2], [3, 4], [3], [5], [6], [6, 7], [7], [8], [8, 9], [9, 10], [10]],
                     [50, 30, 20, 96, 4, 10, 100, 1, 100, 10, 10, 10, 10])


def test_conflict_areas_by_hand():
    # conflict (masks per patch): 1 1; 2 2; 3 2; 4 2; 5 1; 6 1; 7 1; 8 2; 9 1; 10 1; 11 2; 12 2; 13 1.
    # - patch 2 first (lowest id of conflict 2): m0, m1, IoU 30 / 100 -> area {1, 2, 3}; conflict left
    #   in it at 3 (m2): m0, m2, IoU 20 / 100 -> the same area; its largest patch is 50 % -> a conflict area.
    # - patch 4: m3, m4, IoU 96 / 100 -> area {4, 5}, where patch 4 is 96 % >= 95 %: joined, no vote.
    # - patch 8: m6, m7, IoU 1 / 201 < 0.05 -> no area (its conflict is taken off patch 8 only).
    # - patch 11: m8, m9, IoU 10 / 30 -> {10, 11, 12}; conflict left at 12: m9, m10 -> {10, 11, 12, 13}.
    classes, collapsed, start = conflict_areas(conflict_view())
    assert [c.tolist() for c in classes] == [[1, 2, 3], [10, 11, 12, 13]]
    assert [c.tolist() for c in collapsed] == [[4, 5]]
    # patch 4's membership (m3, m4) sorts after patch 5's (m3) in the released numbering: 5 carries the id
    assert start.tolist() == [0, 1, 2, 3, 5, 5, 6, 7, 8, 9, 10, 11, 12, 13]
    c = view_candidates(conflict_view(), "conflict_area")
    assert c.collapsed.tolist() == [[4, 5]] and [g.tolist() for g in c.groups] == [[1, 2, 3], [10, 11, 12, 13]]
    assert c.pairs.tolist() == [[1, 2], [1, 3], [2, 3], [10, 11], [10, 12], [10, 13], [11, 12], [11, 13], [12, 13]]
    # the coarser-mask rule instead: pairs sharing a mask; (7, 8), (8, 9) and (4, 5) are candidates there,
    # (10, 12), (10, 13), (11, 13) (a chain, no common mask) are not
    assert candidate_pairs(conflict_view(), "coarser_mask").tolist() == [
        [1, 2], [1, 3], [2, 3], [4, 5], [7, 8], [8, 9], [10, 11], [11, 12], [12, 13]]


def test_a_dominated_area_is_joined_without_a_vote():
    # patches 1 [96 px] and 2 [4 px] under m0, patch 1 also under m1 (a near-duplicate mask): the released
    # code relabels the area to one id before the vote. Their Gaussians disagree in every other view.
    labels = np.zeros((10, 3), np.int32)
    labels[:, 0] = np.repeat([1, 2], 5)
    labels[:, 1] = labels[:, 2] = np.repeat([1, 2], 5)
    views = [hierarchy([[0, 1], [0]], [96, 4]), hierarchy([[0], [1]]), hierarchy([[0], [1]])]
    coarse, _ = merge_all(stats_from(labels), views, MergeParams())
    assert coarse[0].pairs.tolist() == [[1, 2]] and coarse[0].sims.tolist() == [0.0] and coarse[0].num_instances == 2
    for grouping in ("union_find", "released_greedy"):
        released, _ = merge_all(stats_from(labels), views, MergeParams(candidates="conflict_area", grouping=grouping))
        assert len(released[0].pairs) == 0 and released[0].collapsed.tolist() == [[1, 2]]
        assert released[0].num_instances == 1
    # at 95 % of the area exactly it is still joined; at 94 % it is a conflict area and the vote (0) decides
    views[0] = hierarchy([[0, 1], [0]], [95, 5])
    assert merge_all(stats_from(labels), views, MergeParams(candidates="conflict_area"))[0][0].num_instances == 1
    views[0] = hierarchy([[0, 1], [0]], [94, 6])
    again, _ = merge_all(stats_from(labels), views, MergeParams(candidates="conflict_area"))
    assert again[0].pairs.tolist() == [[1, 2]] and again[0].num_instances == 2
