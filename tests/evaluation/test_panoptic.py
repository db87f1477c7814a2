"""PQ^scene on hand-counted label sets, HDBSCAN on separated feature clusters, the scene ground truth's
nesting, and the evaluate step's panoptic and single-query-point protocols on a tiny room."""

from __future__ import annotations

import json

import numpy as np
import pytest

from trace3d.evaluation.panoptic import FeatureClusters, cluster_features, hdbscan, panoptic_quality, scene_truth

pytestmark = pytest.mark.usefixtures("single_numba_thread")


# ----------------------------------------------------------------------------------------------
# PQ^scene by hand: object 1 has 100 px, object 2 has 100 px (0 = void)
# ----------------------------------------------------------------------------------------------

def labels(*runs):
    return np.concatenate([np.full(n, v, np.int64) for v, n in runs])


TRUTH = labels((1, 100), (2, 100))


def test_perfect_segmentation_scores_one_whatever_the_ids():
    s = panoptic_quality(labels((7, 100), (3, 100)), TRUTH)
    assert (s.pq, s.sq, s.rq, s.miou) == (1.0, 1.0, 1.0, 1.0)
    assert (s.tp, s.fp, s.fn) == (2, 0, 0)
    assert sorted(s.matches) == [(1, 7, 1.0), (2, 3, 1.0)]


def test_one_object_split_in_two():
    # 60 / 40: the 60 piece matches (IoU 0.6), the 40 piece is a false positive
    s = panoptic_quality(labels((5, 60), (6, 40), (7, 100)), TRUTH)
    assert (s.tp, s.fp, s.fn) == (2, 1, 0)
    assert s.sq == pytest.approx(0.8) and s.rq == pytest.approx(2 / 2.5) and s.pq == pytest.approx(1.6 / 2.5)
    assert s.miou == pytest.approx(0.8)
    # 50 / 50: IoU 0.5 is not > 0.5, so object 1 is missed and both halves are false positives
    s = panoptic_quality(labels((5, 50), (6, 50), (7, 100)), TRUTH)
    assert (s.tp, s.fp, s.fn) == (1, 2, 1)
    assert s.sq == 1.0 and s.rq == pytest.approx(1 / 2.5) and s.pq == pytest.approx(0.4)
    assert s.miou == pytest.approx((0.5 + 1.0) / 2)  # Hungarian: one half still covers object 1 at 0.5


def test_two_objects_merged():
    truth = labels((1, 100), (2, 50))
    s = panoptic_quality(labels((9, 150)), truth)
    assert (s.tp, s.fp, s.fn) == (1, 0, 1)
    assert s.sq == pytest.approx(100 / 150) and s.rq == pytest.approx(1 / 1.5)
    assert s.pq == pytest.approx((100 / 150) / 1.5)
    assert s.object_iou == {1: pytest.approx(100 / 150), 2: 0.0}
    assert s.miou == pytest.approx(100 / 150 / 2)


def test_false_positives_void_and_unmatched_objects():
    truth = labels((1, 100), (0, 100), (2, 100))
    # object 1 right plus 20 void pixels (void does not enlarge the union); a segment all on void is
    # ignored; a segment on 10 void px and 30 px of object 2 is a false positive (a quarter void);
    # object 2's other 70 px go to a segment that matches (IoU 0.7)
    pred = labels((4, 100), (4, 20), (8, 60), (6, 10), (0, 10), (6, 30), (5, 70))
    s = panoptic_quality(pred, truth)
    assert s.matches == [(1, 4, 1.0), (2, 5, 0.7)]
    assert (s.tp, s.fp, s.fn, s.ignored) == (2, 1, 0, 1)
    assert s.pq == pytest.approx(1.7 / 2.5)
    # nothing predicted: every object a false negative, PQ 0; nothing at all: undefined
    empty = panoptic_quality(np.zeros(300, np.int64), truth)
    assert (empty.pq, empty.tp, empty.fn, empty.miou) == (0.0, 0, 2, 0.0)
    assert panoptic_quality(np.zeros(5, np.int64), np.zeros(5, np.int64)).pq is None
    with pytest.raises(ValueError):
        panoptic_quality(np.zeros(3, np.int64), np.zeros(4, np.int64))


def test_scene_pq_sees_ids_that_change_between_views():
    # two views of the same two objects; per view the segmentation is perfect, but the second view swaps
    # the predicted ids: over the concatenated views no instance is one object
    view = labels((1, 100), (2, 100))
    pred = np.concatenate([labels((10, 100), (20, 100)), labels((20, 100), (10, 100))])
    s = panoptic_quality(pred, np.concatenate([view, view]))
    assert s.tp == 0 and s.pq == 0.0
    assert panoptic_quality(labels((10, 100), (20, 100)), view).pq == 1.0


def test_scene_truth_takes_the_finest_evaluated_object():
    # leaf ids: 1 = table top, 2 = table leg (both under table 3); 4 = lamp; 5 = unevaluated
    table = np.zeros(6, bool)
    table[[1, 2, 3]] = True
    leg = np.zeros(6, bool)
    leg[2] = True
    lamp = np.zeros(6, bool)
    lamp[4] = True
    instances = np.array([[1, 2, 4, 5, 0]])
    out = scene_truth(instances, {3: table, 2: leg, 4: lamp})
    assert out.tolist() == [[3, 2, 4, 0, 0]]


# ----------------------------------------------------------------------------------------------
# clustering
# ----------------------------------------------------------------------------------------------

def blobs(seed=0):
    rng = np.random.default_rng(seed)
    centres = np.eye(16)[:5] * 4.0
    sizes = (400, 250, 150, 60, 30)
    x = np.concatenate([c + rng.normal(scale=0.15, size=(n, 16)) for c, n in zip(centres, sizes)])
    truth = np.repeat(np.arange(5), sizes)
    return x, truth, rng


def test_hdbscan_recovers_separated_clusters_and_leaves_scatter_as_noise():
    x, truth, rng = blobs()
    scatter = rng.uniform(-6, 10, size=(20, 16))
    got = hdbscan(np.concatenate([x, scatter]), min_cluster_size=10)
    assert got.max() == 4
    for k in range(5):  # each blob is one cluster of its own
        ids = set(got[:len(x)][truth == k].tolist())
        assert len(ids) == 1 and -1 not in ids
    assert len(set(got[:len(x)].tolist())) == 5
    assert (got[len(x):] == -1).mean() >= 0.9
    # a blob smaller than min_cluster_size is no cluster
    small = hdbscan(x, min_cluster_size=40)
    assert (small[truth == 4] == -1).all() and small.max() == 3


def test_hdbscan_one_blob_is_one_cluster():
    rng = np.random.default_rng(1)
    got = hdbscan(rng.normal(size=(300, 4)), min_cluster_size=10)
    assert set(got.tolist()) <= {-1, 0} and (got == 0).mean() > 0.8


def test_cluster_features_gives_every_gaussian_its_blob():
    x, truth, _ = blobs(2)
    weights = np.ones(len(x))
    weights[::7] = 0.0  # never seen: never sampled, still labelled
    c = cluster_features(x, weights, samples=500, min_share=0.02, seed=0)
    assert isinstance(c, FeatureClusters) and c.count == 5 and c.min_cluster_size == 10
    assert c.samples == 500 and not np.isin(c.sample_index, np.flatnonzero(weights == 0)).any()
    again = cluster_features(x, weights, samples=500, min_share=0.02, seed=0)
    assert np.array_equal(c.instance, again.instance) and np.array_equal(c.sample_index, again.sample_index)
    assert panoptic_quality(c.instance, truth + 1).pq == 1.0  # every Gaussian, sampled or not, in its blob


# ----------------------------------------------------------------------------------------------
# the evaluate step: panoptic and single-query-point protocols on a tiny contrastive lift
# ----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny_features(tmp_path_factory):
    """A tiny room, Gaussians on its ground-truth depth, and a "contrastive" lift whose features are
    one well-separated point per label of an oracle label assignment (the ideal lift)."""
    from trace3d.cli import main
    from trace3d.gaussians import init_from_depth
    from trace3d.lifting.labels import run_labels_lift
    from trace3d.scene import Scene, write_u16

    root = tmp_path_factory.mktemp("panoptic")
    synthetic = json.dumps({"seed": 3, "width": 48, "height": 36, "num_views": 8, "test_every": 2, "num_objects": 6,
                            "supersample": 1})
    assert main(["scene", "synthetic", "--out", str(root / "scene"), "--params", synthetic]) == 0
    scene = Scene.read(root / "scene")
    model = init_from_depth(scene, cameras=scene.cameras, stride=1, max_points=None, sh_degree=0, opacity=0.95)
    model.log_scales = model.log_scales - 0.3
    (root / "gaussians").mkdir()
    model.write_ply(root / "gaussians" / "point_cloud.ply")
    lookup = scene.objects.lookup("object")
    for cam in scene.train_cameras:
        write_u16(root / "labels" / f"{cam.name}.png", lookup[scene.instances(cam.name)].astype(np.uint16))
    (root / "labels_lift").mkdir()
    run_labels_lift(scene, None, root / "gaussians", root / "labels", root / "labels_lift", {})
    with np.load(root / "labels_lift" / "labels.npz") as data:
        label = data["label"]
    centres = np.random.default_rng(0).normal(size=(int(label.max()) + 2, 16)).astype(np.float32) * 10.0
    for name, feats in (("lift", centres[label + 1]), ("merged", np.zeros_like(centres[label + 1]))):
        (root / name).mkdir()
        np.save(root / name / "features.npy", feats)
        (root / name / "lift.json").write_text(json.dumps({"method": "contrastive", "params": {}}))
    return root


QUICK = {"min_pixels": 20, "max_occluded_fraction": 0.25, "object_files": False, "picture_objects": 0,
         "panoptic_samples": 1500, "panoptic_min_share": 0.0025}


def run(root, out, lift="lift", **params):
    from trace3d.evaluation.step import run_evaluate

    return run_evaluate(root / "scene", None, root / "gaussians", root / lift, out, {**QUICK, **params})


def test_evaluate_writes_panoptic_and_single_point_beside_the_old_keys(tiny_features, tmp_path):
    root = tiny_features
    m = run(root, tmp_path / "a")
    pan = m["panoptic"]
    # the ideal lift: one feature point per label of an oracle assignment, so clustering finds the
    # objects (at 48x36 the objects are ~100 px over the four test views: the IoUs stay near 0.6-0.85)
    assert pan["PQ"] > 0.4 and pan["mIoU"] > 0.5 and pan["TP"] >= 3 and pan["objects"] == 4
    assert pan["PQ"] == pytest.approx(pan["SQ"] * pan["RQ"])
    assert pan["views"] == 4 and pan["pixels"] == 4 * 48 * 36
    # every feature equal: one instance for the whole scene, at most one object can match
    merged = run(root, tmp_path / "m", lift="merged")["panoptic"]
    assert merged["clusters"] == 1 and merged["TP"] == 0 and merged["PQ"] == 0.0
    one = m["single_point"]
    assert one["max_queries"] == 1 and all(o["query_points"] == 1 for o in one["objects"])
    assert [o["id"] for o in one["objects"]] == [o["id"] for o in m["objects"]]
    assert one["nvs"]["objects"] == m["nvs"]["objects"] and one["nvs"]["mIoU"] is not None
    # the protocols' old keys do not change when the new ones are switched off (or on)
    off = run(root, tmp_path / "b", single_point=False, panoptic=False, segment=False, click=False)
    assert not {"panoptic", "single_point", "segment", "click"} & set(off)
    for key in ("extraction", "nvs", "objects", "skipped", "gaussians"):
        assert json.dumps(off[key]) == json.dumps(m[key])
    # the segment step's objects (features over the 3D kNN graph) and one click per object find the
    # objects of the ideal lift too
    seg, click = m["segment"], m["click"]
    assert seg["PQ"] > 0.4 and seg["TP"] >= 3 and seg["objects"] == 4 and seg["views"] == 4
    # (with the data's threshold for every click 3 of the 4 objects scored 0.52-0.70 and at 48x36 the
    # fourth click selected its background too; with the click's own threshold all four score > 0.5)
    assert click["objects"] == 4 and click["mIoU"] > 0.5 and click["selection"] == "features"
    assert all(o["iou"] > 0.5 for o in click["per_object"]), [o["iou"] for o in click["per_object"]]
    assert all(o["threshold"] > 0 for o in click["per_object"])
    assert all(len(o["point"]) == 2 and o["gaussians"] > 0 for o in click["per_object"])
    # the 2D region growing of before, scored the same way
    region = run(root, tmp_path / "r", single_point=False, panoptic=False, segment=False,
                 click_selection="region")["click"]
    assert region["selection"] == "region" and region["objects"] == 4 and 0.0 < region["mIoU"] <= 1.0
    # every feature equal: the segments are the kNN graph's pieces in 3D (2 in this tiny room), and at
    # most one of them matches an object
    flat = run(root, tmp_path / "m2", lift="merged")["segment"]
    assert flat["grown_segments"] <= 2 and flat["segments"] <= 2 and flat["TP"] <= 1
    # the official protocol computes none of them by default
    official = run(root, tmp_path / "o", protocol="official")
    assert not {"panoptic", "single_point", "segment", "click"} & set(official)
    saved = json.loads((tmp_path / "a" / "metrics.json").read_text())
    assert saved["panoptic"]["PQ"] == pan["PQ"] and saved["single_point"]["nvs"]["mIoU"] == one["nvs"]["mIoU"]


def test_bad_panoptic_parameters_are_refused(tiny_features, tmp_path):
    from trace3d.errors import Trace3DError

    with pytest.raises((Trace3DError, ValueError)):
        run(tiny_features, tmp_path / "x", panoptic_min_share=0.0)


def test_single_point_shares_traced_objects_only_when_the_query_points_agree(tiny_features):
    """``with_query`` siblings share the traced object Gaussians by query-point content: each answer
    equals that of a fresh lifted scene that shares nothing (the twin)."""
    from trace3d.lifting.query import FeatureLifted, QueryParams

    lifted, queries, _, train = _lifted_and_queries(tiny_features)
    model, features = lifted.model, lifted.features
    many = [lifted.object_gaussians(q).copy() for q in queries]
    one = lifted.with_query(max_queries=1)
    shared = [one.object_gaussians(q) for q in queries]
    fresh_many = FeatureLifted(model, features, train)
    fresh_one = FeatureLifted(model, features, train, QueryParams(max_queries=1))
    for q, a, b in zip(queries, many, shared):
        np.testing.assert_array_equal(a, fresh_many.object_gaussians(q))
        np.testing.assert_array_equal(b, fresh_one.object_gaussians(q))
        # the stacked one-call masks against each view's own mask
        points = lifted.query_points(q)
        stacked = lifted.train_masks(points)
        assert len(stacked) == len(train)
        for cam, m in zip(train, stacked):
            np.testing.assert_array_equal(m, points.mask(fresh_many.feature_map(cam)))
    # what the cache holds: one entry per distinct query-point content
    assert len(lifted._shared.by_points) == len({(lifted.query_points(q).features.tobytes(),
                                           lifted.query_points(q).thresholds.tobytes()) for q in queries}
                                         | {(one.query_points(q).features.tobytes(),
                                             one.query_points(q).thresholds.tobytes()) for q in queries})


def test_bench_evaluate_reports_every_phase_and_the_step_metrics(tiny_features, tmp_path):
    """``trace3d bench evaluate`` on a results-like folder: every phase timed, and the evaluation it
    times is the step's (no timing asserted: speed is the benchmark's business)."""
    from trace3d.bench.evaluate import run_bench

    room = tmp_path / "room"
    (room / "full").mkdir(parents=True)
    (room / "scene").symlink_to(tiny_features / "scene")
    (room / "gaussians").symlink_to(tiny_features / "gaussians")
    (room / "full" / "lift").symlink_to(tiny_features / "lift")
    out = run_bench(room, "full", {**QUICK, "object_files": True}, out=tmp_path / "kept")
    (timed,) = out["runs"]
    assert {"load", "ground_truth", "object_gaussians", "extraction", "nvs", "object_files", "single_point",
            "panoptic", "pictures", "write"} <= set(timed["phases"])
    assert all(v["wall_s"] >= 0 and v["cpu_s"] >= 0 for v in timed["phases"].values())
    saved = json.loads((tmp_path / "kept" / "run0" / "eval" / "metrics.json").read_text())
    direct = run(tiny_features, tmp_path / "direct", **{"object_files": True})
    for key in ("extraction", "nvs", "objects", "skipped", "gaussians"):
        assert json.dumps(saved[key]) == json.dumps(direct[key])


def _lifted_and_queries(root, **kwargs):
    from trace3d.evaluation.groundtruth import GroundTruth
    from trace3d.evaluation.params import EvaluateParams
    from trace3d.lifting.query import FeatureLifted
    from trace3d.scene import Scene
    from trace3d.tracing.git import load_fitted

    scene = Scene.read(root / "scene")
    model, cameras = load_fitted(scene, None, root / "gaussians")
    train = [c for c in cameras if c.split == "train"]
    features = np.load(root / "lift" / "features.npy")
    gt = GroundTruth(scene, cameras, EvaluateParams(**{k: v for k, v in QUICK.items() if not k.startswith("panoptic")}))
    queries = [q for q in (gt.query(oid) for oid in gt.object_ids) if q is not None]
    assert len(queries) >= 3
    return FeatureLifted(model, features, train, **kwargs), queries, cameras, train


def test_the_pass_over_the_views_equals_the_all_views_at_once_path(tiny_features):
    """Every object's Gaussians, masks and the visibility from one planned pass over the views (one
    view's weights at a time, the single-point sibling in the same pass) are, bit for bit, those of the
    path that holds every training view's pixel weights and feature maps at once (the twin)."""
    from trace3d.lifting.query import FeatureLifted, QueryParams, summed_weights

    lifted, queries, cameras, train = _lifted_and_queries(tiny_features, map_budget_mb=0)
    one = lifted.with_query(max_queries=1)
    for q in queries:
        lifted.plan(q, cameras)
        one.plan(q, cameras[::2])
    lifted.run_plan()
    assert not lifted._shared.pending_traces and not lifted._shared.pending_masks
    at_once = FeatureLifted(lifted.model, lifted.features, train)
    at_once_one = FeatureLifted(lifted.model, lifted.features, train, QueryParams(max_queries=1))
    weights = at_once.train_weights()
    assert len(weights) == len(train)
    assert lifted.visibility().tobytes() == summed_weights(weights).tobytes()
    for q in queries:
        for scene_, twin, cams in ((lifted, at_once, cameras), (one, at_once_one, cameras[::2])):
            keep = scene_.object_gaussians(q)
            expected = twin.object_gaussians_at_once(q)
            assert keep.dtype == bool and keep.any()
            np.testing.assert_array_equal(keep, expected)
            points = twin.query_points(q)
            np.testing.assert_array_equal(scene_.query_points(q).features, points.features)
            for cam, m in zip(cams, scene_.object_masks(q, cams)):
                assert m.dtype == bool
                np.testing.assert_array_equal(m, points.mask(twin.feature_map(cam)))
    # the masks came from the pass (stored), not from feature maps rendered afterwards
    assert len(lifted._shared.masks) >= len(queries) * len(cameras)
    # a query that was not planned gets a pass of its own, with the same answer
    fresh = FeatureLifted(lifted.model, lifted.features, train)
    np.testing.assert_array_equal(fresh.object_gaussians(queries[0]), at_once.object_gaussians_at_once(queries[0]))


def test_the_pass_holds_one_view_at_a_time(tiny_features, monkeypatch):
    """Instrumented: however many views there are, the pass keeps at most one view's pixel weights
    (and, with no map and weights budget, one feature map) alive, computes each view's weights once
    and reads each view's feature map from them (no render)."""
    import weakref

    import trace3d.lifting.contrastive as contrastive
    import trace3d.render.pixel_weights as pw
    import trace3d.render.weight_maps as weight_maps

    live = {"weights": 0, "maps": 0, "plain": 0}
    peak = {"weights": 0, "maps": 0, "plain": 0}
    calls = {"weights": 0, "maps": 0, "plain": 0}

    def counted(kind, fn):
        def wrapper(*args, **kwargs):
            out = fn(*args, **kwargs)
            calls[kind] += 1
            live[kind] += 1
            peak[kind] = max(peak[kind], live[kind])
            weakref.finalize(out, lambda: live.__setitem__(kind, live[kind] - 1))
            return out
        return wrapper

    # the pass's weights (rows in blending order); the plain ones must not be computed at all
    monkeypatch.setattr(pw, "pixel_weights_blend_order", counted("weights", pw.pixel_weights_blend_order))
    monkeypatch.setattr(pw, "pixel_weights", counted("plain", pw.pixel_weights))
    monkeypatch.setattr(contrastive, "render_feature_map", counted("plain", contrastive.render_feature_map))
    monkeypatch.setattr(weight_maps, "feature_map", counted("maps", weight_maps.feature_map))
    lifted, queries, cameras, train = _lifted_and_queries(tiny_features, map_budget_mb=0, weights_budget_mb=0)
    one = lifted.with_query(max_queries=1)
    for q in queries:
        lifted.plan(q, cameras)
        one.plan(q, cameras)
    peak.update(weights=0, maps=0)
    calls.update(weights=0, maps=0)
    lifted.run_plan()
    assert calls["weights"] == len(cameras) and peak["weights"] == 1
    assert calls["maps"] == len(cameras) and peak["maps"] == 1
    # the answers need no further view
    for q in queries:
        lifted.object_gaussians(q), one.object_gaussians(q), lifted.object_masks(q, cameras)
    assert calls["weights"] == len(cameras) and calls["maps"] == len(cameras) and calls["plain"] == 0


def test_evaluate_metrics_are_those_of_the_all_views_at_once_path(tiny_features, tmp_path, monkeypatch):
    """The evaluation with its one pass over the views writes the same metrics.json, bytes but the
    seconds, as the evaluation that traces each object from every view's weights held at once."""
    from trace3d.lifting.query import FeatureLifted

    def without_seconds(path):
        data = json.loads(path.read_text())
        data.pop("seconds")
        for key in ("single_point", "panoptic", "segment", "click"):
            data[key].pop("seconds")
        return json.dumps(data, sort_keys=True)

    run(tiny_features, tmp_path / "streamed", picture_objects=2)
    monkeypatch.delattr(FeatureLifted, "plan")
    monkeypatch.setattr(FeatureLifted, "object_gaussians", FeatureLifted.object_gaussians_at_once)
    run(tiny_features, tmp_path / "at_once", picture_objects=2)
    assert without_seconds(tmp_path / "streamed" / "metrics.json") == without_seconds(tmp_path / "at_once" / "metrics.json")
    for protocol in ("official",):
        run(tiny_features, tmp_path / f"{protocol}-at-once", protocol=protocol, picture_objects=2)
        monkeypatch.undo()
        run(tiny_features, tmp_path / f"{protocol}-streamed", protocol=protocol, picture_objects=2)
        a = json.loads((tmp_path / f"{protocol}-at-once" / "metrics.json").read_text())
        b = json.loads((tmp_path / f"{protocol}-streamed" / "metrics.json").read_text())
        a.pop("seconds"), b.pop("seconds")
        assert json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


def test_segment_and_click_scores_share_one_knn_graph(tiny_features, tmp_path, monkeypatch):
    """With both scores on, the evaluation builds the seen Gaussians' kNN graph once (the click scene's,
    handed to the segment score) and writes the segment section it writes with a graph of its own."""
    import trace3d.evaluation.step as step
    import trace3d.segment as segment

    calls = []
    real = segment.gaussian_graph

    def counted(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(segment, "gaussian_graph", counted)
    shared = run(tiny_features, tmp_path / "shared")
    assert len(calls) == 1 and shared["segment"]["segments"] > 0
    calls.clear()
    monkeypatch.setattr(step._ClickScene, "graph_for", lambda self, neighbours: None)
    own = run(tiny_features, tmp_path / "own")
    assert len(calls) == 2
    for key in ("segment", "click"):
        shared[key].pop("seconds"), own[key].pop("seconds")
        assert json.dumps(shared[key], sort_keys=True) == json.dumps(own[key], sort_keys=True)


def test_click_masks_from_kept_weights_equal_the_rendered_ones(tiny_features, tmp_path, monkeypatch):
    """The click score reads a view's mask from the weights the lifted scene keeps; with no weights kept
    it renders every mask (extract.object_mask) and writes the same section."""
    import trace3d.lifting.query as query
    import trace3d.render.weight_maps as weight_maps

    calls = []
    real = weight_maps.set_mask
    monkeypatch.setattr(weight_maps, "set_mask", lambda *a: calls.append(1) or real(*a))
    kept = run(tiny_features, tmp_path / "kept")["click"]
    assert calls and kept["objects"] > 0
    calls.clear()
    init = query._Shared.__init__
    monkeypatch.setattr(query._Shared, "__init__", lambda self, maps, weights: init(self, maps, 0))
    rendered = run(tiny_features, tmp_path / "rendered")["click"]
    assert not calls
    kept.pop("seconds"), rendered.pop("seconds")
    assert json.dumps(kept, sort_keys=True) == json.dumps(rendered, sort_keys=True)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_mutual_reachability_mst_kernel_equals_its_twin_bit_for_bit(seed):
    """HDBSCAN's minimum spanning tree: the kernel (points swapped to a contiguous front, distances
    vectorised across points) against the dense numpy Prim, edge by edge to the bit, on data full of
    ties (integer coordinates, repeated points, equal core distances) where the lowest-index rule
    decides, and on continuous data; its total weight equals scipy's spanning tree of the same graph."""
    from scipy.sparse.csgraph import minimum_spanning_tree

    from trace3d.evaluation.panoptic import _mutual_reachability_mst, _mutual_reachability_mst_reference

    rng = np.random.default_rng(seed)
    tied = rng.integers(0, 4, size=(60, 3)).astype(np.float64)
    tied[10:15] = tied[3]  # repeated points: zero distances
    cont = rng.normal(size=(97, 16))
    for x, core in ((tied, np.full(60, 1.0)), (tied, rng.integers(0, 3, 60).astype(np.float64)),
                    (cont, np.sort(rng.random(97))[rng.permutation(97)])):
        got = _mutual_reachability_mst(x, core)
        want = _mutual_reachability_mst_reference(x, core)
        assert got.shape == (len(x) - 1, 3)
        assert got.tobytes() == want.tobytes()
        d = np.sqrt(((x[:, None, :] - x[None, :, :]) ** 2).sum(2))
        reach = np.maximum(np.maximum(d, core[:, None]), core[None, :]) + 1.0  # + 1: scipy drops zero weights
        np.fill_diagonal(reach, 0.0)
        assert np.isclose(got[:, 2].sum() + len(got), minimum_spanning_tree(reach).sum())
