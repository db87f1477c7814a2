"""Objects without ground truth from a lifted scene (issue 48): ``segment``'s graph partition and
``extract``'s click selection on toy scenes whose answer is known, and their kernels against their twins."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from trace3d.extract import (ClickScene, ExtractParams, click_distances, click_distances_reference, click_query,
                             select_connected, select_connected_reference, stable_threshold)
from trace3d.segment import (SeenGraph, SegmentParams, _find, _merge_edges, _merge_edges_reference, _roots,
                             bottleneck_distances, edge_distances, feature_threshold, gaussian_graph,
                             neighbour_lists, segment_gaussians)


def _box(rng, centre, size, count):
    """``count`` points filling an axis-aligned box."""
    return np.asarray(centre) + (rng.random((count, 3)) - 0.5) * np.asarray(size)


def toy_room(seed=0):
    """A wall (4 x 2.5 m, 1 cm thick) with two boxes standing against it, each with its own feature, a
    third box 2 m away from them with box A's feature, and a 6-point speck on box B with a feature of
    its own. Features: one point per object in 8-D (10 apart), plus noise of 0.5 per channel.
    Returns means [N, 3], features [N, 8], weights [N] and the true object of every point (0 wall,
    1 box A, 2 box B, 3 the far twin of A, 4 the speck)."""
    rng = np.random.default_rng(seed)
    parts = [_box(rng, (0, 0, 1.25), (4.0, 0.01, 2.5), 3000),
             _box(rng, (-1.0, 0.3, 0.3), (0.6, 0.6, 0.6), 800),
             _box(rng, (0.6, 0.3, 0.3), (0.6, 0.6, 0.6), 800),
             _box(rng, (-1.0, 2.6, 0.3), (0.6, 0.6, 0.6), 800),
             _box(rng, (0.6, 0.3, 0.62), (0.05, 0.05, 0.02), 6)]
    truth = np.concatenate([np.full(len(p), k) for k, p in enumerate(parts)])
    centres = np.zeros((5, 8))
    centres[0, 0], centres[1, 1], centres[2, 2], centres[4, 3] = 10.0, 10.0, 10.0, 10.0
    centres[3] = centres[1]
    features = centres[truth] + rng.normal(0, 0.5, (len(truth), 8))
    weights = rng.uniform(0.5, 1.5, len(truth))
    return np.concatenate(parts), features, weights, truth


def test_segment_finds_the_objects_and_the_wall():
    means, features, weights, truth = toy_room()
    seg = segment_gaussians(means, features, weights, SegmentParams())
    # every true object is one segment (the speck, under the minimum size, joined box B under it)
    for obj in (0, 1, 2, 3):
        labels = np.unique(seg.instance[truth == obj])
        assert labels.size == 1 and labels[0] > 0, (obj, labels)
    assert len({int(seg.instance[truth == obj][0]) for obj in (0, 1, 2, 3)}) == 4  # A and its far twin apart
    assert set(np.unique(seg.instance[truth == 4]).tolist()) == {int(seg.instance[truth == 2][0])}
    assert seg.count == 4
    wall = int(seg.instance[truth == 0][0])
    assert seg.stuff.tolist() == [k == wall for k in range(1, 5)]  # the wall is stuff, the boxes are not
    # the threshold lies between the two modes: objects 10 * sqrt(2) apart, noise 0.5 * sqrt(2 * 8) = 2
    assert 2.0 < seg.threshold < 14.0, seg.threshold
    # unseen Gaussians follow their nearest seen neighbour (points inside box A, away from the wall)
    unseen = weights.copy()
    hidden = np.flatnonzero((truth == 1) & (means[:, 1] > 0.3))[:10]
    unseen[hidden] = 0.0
    seg2 = segment_gaussians(means, features, unseen, SegmentParams())
    assert (seg2.instance[hidden] == seg2.instance[np.flatnonzero(truth == 1)[-1]]).all()


def test_click_selects_the_object_under_it_and_not_its_far_twin():
    means, features, weights, truth = toy_room()
    click = ClickScene(means, features, weights, ExtractParams())
    on_a = np.flatnonzero(truth == 1)[:5]
    keep = click.select(features[truth == 1].mean(0), on_a)
    np.testing.assert_array_equal(keep, truth == 1)  # the whole box A, not its twin with the same feature
    on_wall = np.flatnonzero(truth == 0)[:5]
    np.testing.assert_array_equal(click.select(features[truth == 0].mean(0), on_wall), truth == 0)
    # the click's feature far from every seed's: nothing
    assert not click.select(np.full(8, 100.0), on_a).any()
    # selection: segment returns the segment the seeds' weight falls in
    seg_click = ClickScene(means, features, weights, ExtractParams(selection="segment"))
    np.testing.assert_array_equal(seg_click.select(features[on_a[0]], on_a, np.ones(on_a.size)),
                                  seg_click.segments().instance == seg_click.segments().instance[on_a[0]])


def test_click_query_is_the_seeds_medoid_not_a_heavy_stray():
    """The Gaussians under a click on box A, one of them a heavy stray with the wall's feature (a floater in
    front of the object, the support seen through a gap): ``query: top`` takes the stray's feature and
    returns the wall, ``medoid`` the feature the heavy seeds agree on and returns box A."""
    means, features, weights, truth = toy_room()
    on_a = np.flatnonzero(truth == 1)[:6]
    stray = np.flatnonzero(truth == 0)[0]
    seeds = np.concatenate([on_a, [stray]])
    seed_weights = np.array([0.30, 0.25, 0.20, 0.15, 0.10, 0.05, 0.40])
    # the medoid: the heavy seeds' feature with the least weighted distance to all seeds' (box A's)
    q = click_query(features[seeds], seed_weights)
    assert q.tolist() in features[on_a].tolist()
    np.testing.assert_array_equal(click_query(features[seeds], seed_weights, "top"), features[stray])
    # only the seeds with at least min_weight of the heaviest one's weight are candidates
    candidates = np.flatnonzero(seed_weights >= 0.5 * seed_weights.max())
    assert any(np.array_equal(click_query(features[seeds], seed_weights, min_weight=0.5), features[seeds[c]])
               for c in candidates)
    # fewer than 3 seeds: the heaviest one's feature
    np.testing.assert_array_equal(click_query(features[seeds[:2]], np.array([0.1, 0.3])), features[seeds[1]])
    medoid = ClickScene(means, features, weights, ExtractParams())
    np.testing.assert_array_equal(medoid.select(None, seeds, seed_weights), truth == 1)
    top = ClickScene(means, features, weights, ExtractParams(query="top"), medoid.shared)
    wrong = top.select(None, seeds, seed_weights)
    assert wrong[stray] and not wrong[truth != 0].any()  # part of the wall, nothing of box A
    with pytest.raises(ValueError, match="query_min_weight"):
        ExtractParams(query_min_weight=1.5)


def test_threshold_tells_same_object_pairs_from_others():
    """Objects as point clouds in 3D, each with its own feature point: the data's threshold lies above
    almost every neighbour pair on one object and below almost every pair on two."""
    rng = np.random.default_rng(1)
    for spread, gap in ((0.3, 5.0), (1.0, 20.0)):
        count = 12
        label = np.repeat(np.arange(count), 400)
        means = rng.random((label.size, 3)) * 0.5 + 3.0 * label[:, None]  # objects 3 apart in a row
        centres = rng.normal(0, gap, (count, 6))
        feats = centres[label] + rng.normal(0, spread, (label.size, 6))
        graph = gaussian_graph(means, np.arange(label.size), 8)
        t = feature_threshold(feats, np.ones(label.size), graph.edges, 50000, 0)
        i, j = rng.integers(0, label.size, (2, 20000))
        d = np.linalg.norm(feats[i] - feats[j], axis=1)
        assert np.mean(d[label[i] == label[j]] > t) < 0.02 and np.mean(d[label[i] != label[j]] <= t) < 0.05, t


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_merge_kernel_matches_its_twin(seed):
    rng = np.random.default_rng(seed)
    n, dim = 400, 5
    means = rng.random((n, 3))
    feats = rng.normal(0, 1, (n, dim)) + 4.0 * (means[:, :1] > 0.5)
    w = rng.uniform(0.1, 2.0, n)
    w[:7] = 1.0  # equal masses: the tie rule decides the root
    graph = gaussian_graph(means, np.arange(n), 6)
    d = np.sqrt(((feats[graph.edges[:, 0]] - feats[graph.edges[:, 1]]) ** 2).sum(1))
    order = np.lexsort((graph.edges[:, 1], graph.edges[:, 0], d))
    results = []
    for fn in (_merge_edges, _merge_edges_reference):
        parent = np.arange(n, dtype=np.int64)
        sums, mass = feats * w[:, None], w.copy()
        fn(np.ascontiguousarray(graph.edges[order]), np.ascontiguousarray(d[order]), sums, mass, 2.0, parent)
        roots = np.array([_find(parent.copy(), v) for v in range(n)])
        results.append((roots, sums[np.unique(roots)], mass[np.unique(roots)]))
    np.testing.assert_array_equal(results[0][0], results[1][0])
    np.testing.assert_array_equal(results[0][1], results[1][1])
    np.testing.assert_array_equal(results[0][2], results[1][2])
    assert 1 < np.unique(results[0][0]).size < n  # some joined, not all


@pytest.mark.parametrize("seed", [0, 1])
def test_select_connected_matches_its_twin(seed):
    rng = np.random.default_rng(seed)
    n = 600
    means = rng.random((n, 3))
    feats = rng.normal(0, 1, (n, 4))
    graph = gaussian_graph(means, np.arange(n), 5)
    seeds = rng.choice(n, 4, replace=False)
    for threshold in (1.5, 2.5, 4.0):
        fast = select_connected(feats, feats[seeds[0]], graph.edges, seeds, threshold)
        slow = select_connected_reference(feats, feats[seeds[0]], graph.edges, seeds, threshold)
        np.testing.assert_array_equal(fast, slow)
    assert fast.sum() > 1


@pytest.mark.parametrize("seed", [0, 1])
def test_click_distances_match_their_twin_and_every_threshold(seed):
    """The least threshold that selects each point (minimum-spanning-tree path) equals the Dijkstra twin's,
    and ``<= t`` is :func:`select_connected`'s selection at every t."""
    rng = np.random.default_rng(seed)
    n = 700
    means = rng.random((n, 3))
    feats = rng.normal(0, 1, (n, 4))
    graph = gaussian_graph(means, np.arange(n), 5)
    seeds = rng.choice(n, 5, replace=False)
    seeds[1] = seeds[0]  # a repeated seed counts once
    fast = click_distances(feats, feats[seeds[0]], graph.edges, seeds)
    slow = click_distances_reference(feats, feats[seeds[0]], graph.edges, seeds)
    np.testing.assert_array_equal(fast, slow)
    for t in (0.5, 1.5, 2.5, 4.0):
        np.testing.assert_array_equal(fast <= t, select_connected(feats, feats[seeds[0]], graph.edges, seeds, t))
    # with a limit: the same below it, inf beyond
    capped = click_distances(feats, feats[seeds[0]], graph.edges, seeds, 2.5)
    np.testing.assert_array_equal(capped, click_distances_reference(feats, feats[seeds[0]], graph.edges, seeds, 2.5))
    np.testing.assert_array_equal(capped, np.where(fast <= 2.5, fast, np.inf))
    # a point the graph never reaches from a seed: inf
    lonely = np.r_[means, [[50.0, 50.0, 50.0]]]
    g2 = gaussian_graph(lonely, np.arange(n + 1), 5)
    g2_edges = g2.edges[(g2.edges != n).all(1)]
    far = click_distances(np.r_[feats, feats[:1]], feats[seeds[0]], g2_edges, seeds)
    assert np.isinf(far[n]) and np.isfinite(far[:n]).any()
    assert np.isinf(click_distances(feats, feats[0], graph.edges, np.zeros(0, np.int64))).all()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_bottleneck_kernel_matches_the_tree_and_the_dijkstra(seed):
    """:func:`bottleneck_distances` (the click's flood kernel over neighbour lists, walking d in ascending
    order) gives the bits of :func:`click_distances` (a minimum spanning tree) and of its Dijkstra twin: with
    and without a limit, repeated seeds, seeds beyond the limit, points no path reaches, ties in d, no seed."""
    rng = np.random.default_rng(seed)
    n = 700
    means = np.r_[rng.random((n, 3)), [[50.0, 50.0, 50.0]]]  # the last point far from all
    feats = rng.normal(0, 1, (n + 1, 4))
    feats[10:40] = feats[9]  # ties in d
    graph = gaussian_graph(means, np.arange(n + 1), 5)
    edges = graph.edges[(graph.edges != n).all(1)]  # the far point linked to none
    indptr, nbrs = neighbour_lists(edges, n + 1)
    seeds = np.r_[rng.choice(n, 5, replace=False), 9]
    seeds[1] = seeds[0]
    for query in (feats[seeds[0]], feats[9], rng.normal(0, 1, 4)):
        d = np.sqrt(((feats - query[None, :]) ** 2).sum(1))
        for limit in (np.inf, 2.5, 1.0, 0.0):
            fast = bottleneck_distances(d, indptr, nbrs, seeds, limit)
            np.testing.assert_array_equal(fast, click_distances(feats, query, edges, seeds, limit))
            np.testing.assert_array_equal(fast, click_distances_reference(feats, query, edges, seeds, limit))
        assert np.isinf(fast[n])
    assert np.isinf(bottleneck_distances(d, indptr, nbrs, np.zeros(0, np.int64))).all()
    # the lists hold every edge from both ends
    got = {(a, int(b)) for a in range(n + 1) for b in nbrs[indptr[a]:indptr[a + 1]]}
    assert got == {(int(a), int(b)) for a, b in edges} | {(int(b), int(a)) for a, b in edges}


def test_roots_by_pointer_jumping_are_finds():
    rng = np.random.default_rng(4)
    n = 500
    parent = np.arange(n, dtype=np.int64)
    for a, b in rng.integers(0, n, (300, 2)):  # a forest with long chains
        ra, rb = _find(parent, a), _find(parent, b)
        if ra != rb:
            parent[rb] = ra
    parent[:50] = np.arange(50)  # more roots (a chain through them ends there now)
    before = parent.copy()
    assert (_roots(parent) != parent).any()  # paths longer than one step
    np.testing.assert_array_equal(_roots(parent), [_find(before.copy(), v) for v in range(n)])
    np.testing.assert_array_equal(parent, before)  # left as it was
    assert _roots(np.zeros(0, np.int64)).size == 0


def test_seen_graph_shares_what_each_user_would_compute():
    """One :class:`SeenGraph` for the segment and click steps gives the bits each computes on its own: the
    edges' distances and order, the threshold (with precomputed distances and order, and without), the
    segments, every click's selection; edges not in the graph's order take the lexsort."""
    means, features, weights, truth = toy_room()
    weights = weights.copy()
    weights[::97] = 0.0  # unseen Gaussians follow their nearest seen one
    shared = SeenGraph(means, features, weights, 12)
    f, w, edges = shared.seen_features, shared.seen_weights, shared.graph.edges
    plain = np.sqrt(((f[edges[:, 0]] - f[edges[:, 1]]) ** 2).sum(1))
    np.testing.assert_array_equal(shared.distances(), plain)
    np.testing.assert_array_equal(edge_distances(f, edges, block=7), plain)  # blocks and a last partial one
    np.testing.assert_array_equal(shared.grow_order(), np.lexsort((edges[:, 1], edges[:, 0], shared.distances())))
    assert shared.threshold(5000, 3) == feature_threshold(f, w, edges, 5000, 3)
    swapped = SeenGraph(means, features, weights, 12, dataclasses.replace(shared.graph, edges=edges[::-1].copy()))
    np.testing.assert_array_equal(swapped.grow_order(),
                                  np.lexsort((edges[::-1, 1], edges[::-1, 0], edge_distances(f, edges[::-1]))))
    for params in (SegmentParams(), SegmentParams(method="hdbscan_graph", samples=2000, min_share=0.005)):
        a = segment_gaussians(means, features, weights, params, shared)
        b = segment_gaussians(means, features, weights, params)
        for key in ("instance", "stuff", "gaussians", "weight", "extents"):
            np.testing.assert_array_equal(getattr(a, key), getattr(b, key))
        assert (a.threshold, a.threshold_source, a.stats) == (b.threshold, b.threshold_source, b.stats)
    params = ExtractParams()
    with_shared = ClickScene(means, features, weights, params, shared)
    own = ClickScene(means, features, weights, params)
    assert with_shared.threshold == own.threshold
    rng = np.random.default_rng(0)
    for _ in range(6):
        seeds = rng.choice(len(means), 8, replace=False)
        sw = rng.random(8)
        np.testing.assert_array_equal(with_shared.select(None, seeds, sw), own.select(None, seeds, sw))
        assert with_shared.last_threshold == own.last_threshold
        # the scene's click distances (the kernel) are click_distances' (the tree)
        local = np.searchsorted(own.seen, seeds[np.isin(seeds, own.seen)])
        q = own.features[seeds[0]]
        np.testing.assert_array_equal(own.click_distances(q, local, 3 * own.threshold),
                                      click_distances(f, q, edges, local, 3 * own.threshold))


def _bench_scene(seed=0):
    """A wall (3000 points, feature 20 from the rest) with a bench (1500 points, 2 m long) against it whose
    lifted feature drifts by 6 from one end to the other (as a large object's features do when its masks
    split it), noise 0.5 per channel in 8-D, and four far boxes with features 20 from everything. Returns
    means, features, weights, truth (0 wall, 1 bench, 2-5 far boxes)."""
    rng = np.random.default_rng(seed)
    parts = [_box(rng, (0, 0, 1.25), (4.0, 0.01, 2.5), 3000), _box(rng, (0.0, 0.3, 0.3), (2.0, 0.5, 0.5), 1500)]
    parts += [_box(rng, (-1.5 + k, 3.0, 0.3), (0.6, 0.6, 0.6), 800) for k in range(4)]
    truth = np.concatenate([np.full(len(p), k) for k, p in enumerate(parts)])
    means = np.concatenate(parts)
    centres = np.zeros((6, 8))
    centres[0, 0] = 20.0
    for k in range(2, 6):
        centres[k, k] = 20.0
    features = centres[truth] + rng.normal(0, 0.5, (len(truth), 8))
    bench = truth == 1
    features[bench, 1] += 6.0 * (means[bench, 0] + 1.0) / 2.0
    return means, features, rng.uniform(0.5, 1.5, len(truth)), truth


def test_stable_threshold_takes_the_whole_object():
    """A click at one end of the bench: the data's threshold (the same for every click) takes the half
    whose features lie near the click's; the click's own, most stable threshold returns the whole bench
    and nothing else (a toy scene where the answer is known)."""
    means, features, weights, truth = _bench_scene()
    on_end = np.flatnonzero((truth == 1) & (means[:, 0] < -0.9))[:5]
    data = ClickScene(means, features, weights, ExtractParams(threshold_rule="data"))
    assert data.select(features[on_end[0]], on_end)[truth == 1].mean() < 0.6
    stable = ClickScene(means, features, weights, ExtractParams())
    np.testing.assert_array_equal(stable.select(features[on_end[0]], on_end), truth == 1)
    assert stable.last_threshold > stable.threshold
    # a click on the wall (39 % of the scene's weight) returns the wall
    on_wall = np.flatnonzero(truth == 0)[:5]
    np.testing.assert_array_equal(stable.select(features[truth == 0].mean(0), on_wall), truth == 0)
    # with stable_max_share under the wall's share no threshold qualifies: the data's is used
    small = ClickScene(means, features, weights, ExtractParams(stable_max_share=0.2))
    small.select(features[truth == 0].mean(0), on_wall)
    assert small.last_threshold == small.threshold


def test_stable_threshold_picks_the_plateau():
    """The selection's weight as the threshold grows: 10 until 2, 100 from 2 to 8, the whole scene from 8:
    the threshold is on the plateau, the nearest one to the data's distance among equally flat ones."""
    reach = np.r_[np.full(10, 0.1), np.full(90, 2.0), np.full(900, 8.0)]
    weights = np.ones(reach.size)
    p = ExtractParams(stable_min_gaussians=5)
    t = stable_threshold(reach, weights, 4.0, p)
    assert 2.0 * 1.3 < t < 8.0 / 1.3, t
    # the data's distance at 1: the 10 points' plateau (0.1 to 2) is as flat and nearer; with fewer than
    # stable_min_gaussians there, the 100 points' plateau
    assert 0.1 <= stable_threshold(reach, weights, 1.0, p) < 2.0
    assert 2.0 <= stable_threshold(reach, weights, 1.0, dataclasses.replace(p, stable_min_gaussians=20)) < 8.0
    # nothing qualifies (every selection is the whole scene): the data's distance
    assert stable_threshold(np.zeros(50), np.ones(50), 3.0, p) == 3.0


def test_graph_lists_each_pair_once():
    rng = np.random.default_rng(3)
    means = rng.random((50, 3))
    g = gaussian_graph(means, np.arange(50), 4)
    assert (g.edges[:, 0] < g.edges[:, 1]).all()
    assert len(np.unique(g.edges, axis=0)) == len(g.edges)
    np.testing.assert_allclose(g.lengths, np.linalg.norm(means[g.edges[:, 0]] - means[g.edges[:, 1]], axis=1))
    # every point's nearest neighbour is linked to it
    from scipy.spatial import cKDTree

    nearest = cKDTree(means).query(means, k=2)[1][:, 1]
    pairs = {tuple(e) for e in g.edges.tolist()}
    assert all((min(i, j), max(i, j)) in pairs for i, j in enumerate(nearest.tolist()))


def test_bad_segment_and_extract_params():
    with pytest.raises(ValueError, match="threshold_scale"):
        ExtractParams(threshold_scale=0)
    with pytest.raises(ValueError, match="stable_span"):
        ExtractParams(stable_span=30)
    with pytest.raises(ValueError, match="stable_max_share"):
        ExtractParams(stable_max_share=0)
    with pytest.raises(ValueError, match="feature_threshold"):
        SegmentParams(feature_threshold=-1.0)
    with pytest.raises(ValueError, match="flat_ratio"):
        SegmentParams(flat_ratio=1.5)


def test_hdbscan_clusters_split_into_their_pieces_in_3d():
    """``method: hdbscan_graph``: the feature clusters (box A and its far twin share one) split where they
    are apart in 3D; the wall and box B stay whole."""
    means, features, weights, truth = toy_room()
    seg = segment_gaussians(means, features, weights, SegmentParams(method="hdbscan_graph", samples=2000,
                                                                     min_share=0.005))
    for obj in (0, 1, 2, 3):
        labels = np.unique(seg.instance[truth == obj])
        assert labels.size == 1 and labels[0] > 0, (obj, labels)
    assert len({int(seg.instance[truth == obj][0]) for obj in (0, 1, 2, 3)}) == 4


def test_click_weights_are_the_full_views_rows():
    """The 3x3 pixels' weights traced alone equal those rows of the full view's weights (the twin), and
    their seeds and summed weights equal, bit for bit, those read from the view's blend-order weights
    (what the evaluation's click score reads when the lifted scene keeps the view's)."""
    from trace3d.extract import click_seeds, click_weights
    from trace3d.render.pixel_weights import pixel_weights, pixel_weights_blend_order
    from trace3d.scene import Camera
    import torch

    from trace3d.gaussians import init_from_points

    rng = np.random.default_rng(0)
    points = torch.from_numpy(np.c_[rng.uniform(-1, 1, (300, 2)), rng.uniform(2, 4, 300)]).float()
    model = init_from_points(points, torch.full((300, 3), 0.5), sh_degree=0, opacity=0.6, seed=0)
    camera = Camera(name="v", split="train", width=24, height=18,
                    K=np.array([[20.0, 0, 12], [0, 20.0, 9], [0, 0, 1]]), world_to_camera=np.eye(4))
    with torch.no_grad():
        full = pixel_weights(model.splats(), camera)
        blend = pixel_weights_blend_order(model.splats(), camera)
    for x, y in ((12, 9), (0, 0), (23, 17), (5, 11)):
        a = click_seeds(full, x, y)
        b = click_seeds(click_weights(model, camera, x, y), x, y)
        c = click_seeds(blend, x, y)
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_allclose(a[1], b[1], rtol=1e-6)
        assert c[0].tobytes() == b[0].tobytes() and c[1].tobytes() == b[1].tobytes(), (x, y)
    assert a[0].size > 0 and c[0].size > 3
