"""The merge step's memory (issue 36 part 2): what it reads of the GIT table, the per-Gaussian view
lists that replace its [G, V] temporaries, and that none of it changes a merge."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

import trace3d.tracing.merge as merge
from trace3d.errors import SceneFormatError
from trace3d.masks.patches import PatchHierarchy
from trace3d.tracing.git import GITStats, GITVisible
from trace3d.tracing.merge import (MergeParams, ViewMerge, associate, label_counts, merge_all, merged_label_rows,
                                   merged_lists, view_links, view_links_dense, visible_lists)
from trace3d.tracing.merge import _vote_sums, _vote_sums_numpy

pytestmark = pytest.mark.usefixtures("single_numba_thread")


def random_table(seed: int, n: int, views: int, patches: int, share: float) -> GITStats:
    """A GIT table whose Gaussians see about ``share`` of the views, labels 0..patches, some -1."""
    rng = np.random.default_rng(seed)
    label = rng.integers(0, patches + 1, size=(n, views)).astype(np.int32)
    seen = rng.random((n, views)) < share
    label[~seen & (rng.random((n, views)) < 0.5)] = -1
    visibility = np.where(seen, rng.random((n, views)).astype(np.float32) + 0.01, 0).astype(np.float32)
    visibility[rng.random((n, views)) < 0.05] = 0.3  # ties with a threshold below
    return GITStats(label=label, prob=rng.random((n, views)).astype(np.float32), visibility=visibility,
                    frames=[f"v{i}" for i in range(views)], num_labels=np.full(views, patches + 1, np.int64))


def whole(num_patches: int) -> PatchHierarchy:
    """Patches 1..P inside one coarser mask (every pair is a candidate)."""
    return PatchHierarchy([[0]] * num_patches, np.ones(num_patches, np.int64), np.ones(1, np.int64),
                          np.ones(1, np.float32))


@pytest.mark.parametrize("top", [5, 32767, 40000])
@pytest.mark.parametrize("block_entries", [1, 7, 1 << 21])
def test_visible_lists_are_the_visible_entries_row_major(monkeypatch, top, block_entries):
    monkeypatch.setattr(merge, "ROW_BLOCK_ENTRIES", block_entries)
    rng = np.random.default_rng(top)
    labels = rng.integers(-1, top + 1, size=(50, 6)).astype(np.int32)
    labels[3, 2] = top
    visible = rng.random((50, 6)) > 0.3
    visible[3, 2] = True
    indptr, indices, values = visible_lists(lambda lo, hi: labels[lo:hi], visible)
    seen = visible & (labels >= 0)
    np.testing.assert_array_equal(indptr, np.concatenate([[0], np.cumsum(seen.sum(axis=1))]))
    np.testing.assert_array_equal(indices, np.nonzero(seen)[1])
    np.testing.assert_array_equal(values, labels[seen])
    assert indices.dtype == np.int16
    assert values.dtype == (np.int16 if top <= 32767 else np.int32)


@pytest.mark.parametrize("block_entries", [1, 7, 1 << 21])
def test_merged_lists_and_label_counts_are_read_from_the_label_lists(monkeypatch, block_entries):
    """The association's lists read from the labels' lists (:func:`merged_lists`) are the lists of
    :func:`merged_label_rows` (the twin: a pass over the [N, L] labels), also where a label has no entry in
    its view's lut (dropped) or every lut is short; the views' label counts are each view's bincount."""
    monkeypatch.setattr(merge, "ROW_BLOCK_ENTRIES", block_entries)
    stats = random_table(6, 120, 5, 6, 0.5)
    visible = stats.visible(0.0)
    labels = visible_lists(lambda lo, hi: stats.label[lo:hi], visible)
    rng = np.random.default_rng(0)
    for sizes in ([7, 7, 7, 7, 7], [7, 4, 7, 1, 6]):  # [P + 1] luts; shorter ones drop the labels beyond them
        merges = [ViewMerge(f"v{v}", np.r_[0, rng.integers(1, 4, size - 1)], np.zeros((0, 2), np.int64), np.zeros(0),
                            np.zeros(0, np.int64), np.zeros(0, bool)) for v, size in enumerate(sizes)]
        fast = merged_lists(labels, merges)
        slow = visible_lists(lambda lo, hi, merges=merges: merged_label_rows(stats, merges, lo, hi), visible)
        for a, b in zip(fast, slow):
            np.testing.assert_array_equal(a, b)
            assert a.dtype == b.dtype
        assert len(fast[1]) < len(labels[1]) or sizes[1] == 7  # the short luts dropped entries
    counts = label_counts(labels, 5, 9)
    for v in range(5):
        seen = visible[:, v] & (stats.label[:, v] >= 0)
        np.testing.assert_array_equal(counts[v], np.bincount(stats.label[seen, v], minlength=9))


@pytest.mark.parametrize("first_label", [0, 1])
def test_vote_sums_kernel_gives_the_floats_of_the_numpy_sums(first_label):
    """The vote's integer sums (kernel) as float64 are the float64 numpy sums of the twin, bit for bit, with
    counts up to a default room's (80,000 Gaussians) and views that do not vote."""
    rng = np.random.default_rng(first_label)
    patches, views, labels = 9, 7, 6
    hist = (rng.random((patches, views, labels)) < 0.4) * rng.integers(0, 80000, (patches, views, labels))
    hist = hist.astype(np.int32)
    n = hist[:, :, first_label:].sum(axis=2, dtype=np.int64)
    a, b = np.triu_indices(patches, 1)
    vote_views = rng.random((len(a), views)) < 0.7
    same, total = _vote_sums(hist, a.astype(np.int64), b.astype(np.int64), vote_views, first_label, n)
    ref_same, ref_total = _vote_sums_numpy(hist, a, b, vote_views, first_label, n)
    np.testing.assert_array_equal(same.astype(np.float64), ref_same)
    np.testing.assert_array_equal(total.astype(np.float64), ref_total)
    assert same.max() > 2 ** 32  # past int32: the int64 products and sums are needed


@pytest.mark.parametrize("seed", [0, 1])
def test_view_links_of_the_co_visible_pairs_are_the_whole_tables(seed):
    """The association's links from the pairs that share a Gaussian (:func:`view_links`) are the twin's
    over the whole float table: the same strengths, bit for bit, in the same order; exact ties with the
    share included (a count of 1 of 2), views whose later instances are fewer than the table's width."""
    rng = np.random.default_rng(seed)
    views, width = 6, 5
    counts = [4, 3, 0, 4, 2, 4]  # instances per view (the table is as wide as the most)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    for v in range(views):
        hist = (rng.random((width, views, width)) < 0.3) * rng.integers(1, 4, (width, views, width))
        hist[1, -1, :] = 0
        hist[1, -1, 1] = 1  # a share of exactly 1/2 against another 1 of the same instance
        hist[1, -1, 2] = 1
        hist = hist.astype(np.int32)
        for share in (0.5, 0.3):
            fast = view_links(hist, v, share, counts, offsets)
            assert fast == view_links_dense(hist, v, share, counts, offsets)
            assert all(type(s) is float for s, _, _ in fast)
        assert v == views - 1 or fast  # something links: the comparison means something


@pytest.mark.parametrize("min_visibility", [0.0, 0.3])
def test_git_visible_reads_the_labels_and_the_mask_of_git_stats(tmp_path, min_visibility):
    stats = random_table(1, 300, 7, 4, 0.4)
    stats.save(tmp_path / "git.npz")
    back = GITVisible.load(tmp_path / "git.npz", min_visibility)
    np.testing.assert_array_equal(back.label, stats.label)
    assert back.label.dtype == np.int32
    np.testing.assert_array_equal(back.visible(min_visibility), stats.visible(min_visibility))
    assert back.visible(min_visibility) is back.visible(min_visibility)  # the held mask, not a new one
    assert back.frames == stats.frames == GITStats.load_frames(tmp_path / "git.npz")
    np.testing.assert_array_equal(back.num_labels, stats.num_labels)
    with pytest.raises(ValueError, match="visibility"):
        back.visible(min_visibility + 0.1)


def test_git_visible_refuses_bad_files(tmp_path):
    stats = random_table(2, 10, 3, 2, 0.5)
    np.savez_compressed(tmp_path / "short.npz", label=stats.label, prob=stats.prob, visibility=stats.visibility[:, :2],
                        frames=np.asarray(stats.frames), num_labels=stats.num_labels)
    with pytest.raises(SceneFormatError, match="disagree in shape"):
        GITVisible.load(tmp_path / "short.npz", 0.0)
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    for loader in (lambda p: GITVisible.load(p, 0.0), GITStats.load_frames):
        with pytest.raises(SceneFormatError, match="bad.npz"):
            loader(tmp_path / "bad.npz")
        with pytest.raises(SceneFormatError, match="missing"):
            loader(tmp_path / "none.npz")


def _same_merges(a, b):
    (merges_a, luts_a), (merges_b, luts_b) = a, b
    assert len(merges_a) == len(merges_b)
    for x, y in zip(merges_a, merges_b):
        for key in ("lut", "pairs", "sims", "omega", "merged", "supported"):
            np.testing.assert_array_equal(getattr(x, key), getattr(y, key))
    for x, y in zip(luts_a, luts_b):
        np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("preset", ["paper", "official"])
def test_merge_of_git_visible_in_row_blocks_equals_git_stats_at_once(tmp_path, monkeypatch, preset):
    stats = random_table(3, 400, 6, 4, 0.6)
    stats.save(tmp_path / "git.npz")
    # random labels agree by chance (about a quarter): a low threshold so that some pairs merge
    params = MergeParams(preset=preset, threshold=0.22, min_gaussians=10 if preset == "official" else None)
    hierarchies = [whole(4)] * 6
    at_once = merge_all(stats, hierarchies, params)
    assert sum(int(m.merged.sum()) for m in at_once[0]) > 0  # something merges: the comparison means something
    monkeypatch.setattr(merge, "ROW_BLOCK_ENTRIES", 5)  # one Gaussian at a time
    monkeypatch.setattr(merge, "HISTOGRAM_BLOCK", 5 * 6 * 5)  # one source view at a time
    _same_merges(merge_all(GITVisible.load(tmp_path / "git.npz", params.min_visibility), hierarchies, params), at_once)
    merges = at_once[0]
    _same_merges((merges, associate(stats, merges, 0.0, 0.5, visible=stats.visible(0.0))), at_once)


def test_merge_holds_no_gv_temporary(monkeypatch):
    """merge_all on the step's table allocates (numpy, traced) less than 4 bytes per (Gaussian, view)
    beyond its input. Measured: 1.8 (paper) and 3.1 (official) here, where the per-Gaussian view lists
    (4 bytes per visible entry, a fifth of the entries, + 8 bytes per Gaussian for the row pointers:
    0.4 per entry at V = 20) are held through the official rule's copy of one source view's Gaussians
    (int32 labels and a bool per entry: 6 bytes x a fifth); row blocks are of a fixed size, made small
    here so that they are a small part of this small table. The code before this held an int32 [G, V]
    table and its astype copy at once (8 bytes) besides np.nonzero's int64 pairs and the merged labels."""
    monkeypatch.setattr(merge, "ROW_BLOCK_ENTRIES", 1 << 14)

    def table(n, views, seed):
        stats = random_table(seed, n, views, 6, 0.2)
        return GITVisible(label=stats.label, mask=stats.visible(0.0), min_visibility=0.0, frames=stats.frames,
                          num_labels=stats.num_labels)

    n, views = 20000, 20
    big, small = table(n, views, 4), table(100, views, 5)
    hierarchies = [whole(6)] * views
    for preset in ("paper", "official"):
        merge_all(small, hierarchies, MergeParams(preset=preset))  # numba compiled outside the trace
        tracemalloc.start()
        merge_all(big, hierarchies, MergeParams(preset=preset))
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        assert peak / (n * views) < 4.0, (preset, peak / (n * views))
