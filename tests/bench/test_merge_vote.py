"""``trace3d bench merge-vote`` (trace3d/bench/merge_vote.py): its precision-recall figures and the
Jaccard co-membership on hand-worked cases (the bench on a traced room: tests/test_tracing.py)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.tracing.test_merge_rules import hierarchy
from trace3d.bench.merge_vote import _jaccard_comembership, binned_bayes, recall_at_precision


def test_recall_at_precision_by_hand():
    # merged in score order: P 1, 1, 2/3, 3/4 at R 1/3, 2/3, 2/3, 1
    out = recall_at_precision(np.array([0.9, 0.8, 0.7, 0.6]), np.array([True, True, False, True]))
    assert out["recall_at_0.95"] == out["recall_at_0.9"] == out["recall_at_0.8"] == pytest.approx(2 / 3)
    assert out["pr_auc"] == pytest.approx(1 / 3 + 1 / 3 + 0.75 / 3)
    # a tie enters together: one threshold, precision 1/2 (never 1 with the positive alone)
    tie = recall_at_precision(np.array([0.5, 0.5]), np.array([True, False]))
    assert tie["recall_at_0.95"] == 0.0 and tie["pr_auc"] == pytest.approx(0.5)
    assert recall_at_precision(np.array([0.1]), np.array([False]))["pr_auc"] is None


def test_jaccard_comembership_by_hand():
    # patch 1 in {0}, 2 in {0, 1}, 3 in {1}, 4 in {2}
    c = _jaccard_comembership(hierarchy([[0], [0, 1], [1], [2]]), 6)
    assert c[1, 2] == c[2, 1] == c[2, 3] == pytest.approx(0.5)
    assert c[1, 3] == c[1, 4] == 0.0 and c[1, 1] == c[4, 4] == 1.0
    assert not c[0].any() and not c[:, 0].any() and not c[5].any()


def test_binned_bayes_is_the_cells_share_of_positives():
    same = np.array([0.05, 0.05, 0.05, 0.95])
    common = np.array([0.5, 0.55, 0.9, 0.95])
    positive = np.array([True, False, True, True])
    np.testing.assert_allclose(binned_bayes(same, common, positive), [0.5, 0.5, 1.0, 1.0])


def test_a_room_without_its_trace_is_named(tmp_path):
    from trace3d.bench.merge_vote import room_pairs, run_bench
    from trace3d.cli import main
    from trace3d.errors import Trace3DError

    (tmp_path / "scene").mkdir()
    missing = r"bench merge-vote: .*trace-paper/git\.npz is missing; run the room's trace"
    with pytest.raises(Trace3DError, match=missing):
        room_pairs(tmp_path)
    with pytest.raises(Trace3DError, match=r"name at least one room"):
        run_bench([])
    assert main(["bench", "merge-vote", "--rooms", str(tmp_path)]) == 2
