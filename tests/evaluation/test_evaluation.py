"""Evaluation: metrics on hand-made masks, the protocol's choices, the label-assignment lifting on a
toy scene solved by hand, and the evaluate step end to end on a tiny room (PLY round trip,
determinism, bad input)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from trace3d.errors import ConfigError, SceneFormatError, Trace3DError
from trace3d.evaluation.extraction import render_alone
from trace3d.evaluation.groundtruth import GroundTruth, membership, object_mask, occluded_fraction, touches_border
from trace3d.evaluation.metrics import MAX_PSNR, confusion, grown_box, psnr
from trace3d.evaluation.params import EvaluateParams
from trace3d.gaussians import GaussianModel
from trace3d.lifting import ObjectQuery, load_lifted
from trace3d.lifting.labels import (LabelledScene, _summed_label_weights_dense, assign_labels, summed_label_weights)
from trace3d.scene import Camera, ObjectTable, Scene, SceneObject, write_frame

from tests.lifted_room import oracle_room


# numba kernels on one thread: the tests compare sums whose order must not depend on the pool
pytestmark = pytest.mark.usefixtures("single_numba_thread")


# ----------------------------------------------------------------------------------------------
# metrics
# ----------------------------------------------------------------------------------------------


class TestMetrics:
    def test_confusion_counts_and_scores(self):
        truth = np.zeros((4, 5), bool)
        truth[1:3, 1:4] = True  # 6 px
        pred = np.zeros((4, 5), bool)
        pred[1:3, 2:5] = True  # 6 px, 4 shared
        c = confusion(pred, truth)
        assert (c.tp, c.fp, c.fn, c.tn) == (4, 2, 2, 12)
        assert c.iou == pytest.approx(4 / 8)
        assert c.accuracy == pytest.approx(16 / 20)
        assert c.precision == pytest.approx(4 / 6)

    def test_empty_cases(self):
        empty = np.zeros((3, 3), bool)
        full = np.ones((3, 3), bool)
        assert confusion(empty, empty).iou == 1.0
        assert confusion(empty, full).iou == 0.0
        assert confusion(empty, full).precision == 0.0
        assert confusion(full, empty).accuracy == 0.0
        with pytest.raises(ValueError):
            confusion(empty, np.zeros((2, 3), bool))

    def test_grown_box_clips_to_the_image(self):
        truth = np.zeros((30, 40), bool)
        truth[5:8, 20:25] = True
        assert grown_box(truth, 10) == (0, 18, 10, 35)
        assert grown_box(truth, 0) == (5, 8, 20, 25)
        with pytest.raises(ValueError):
            grown_box(np.zeros((3, 3), bool), 1)

    def test_psnr_known_values_and_box(self):
        a = np.zeros((10, 10, 3))
        b = np.full((10, 10, 3), 0.1)  # mse 0.01 -> 20 dB
        assert psnr(a, b) == pytest.approx(20.0)
        b[0:2, 0:2] = 0.0
        assert psnr(a, b, (0, 2, 0, 2)) == MAX_PSNR  # exact inside the box
        assert psnr(a, b, (5, 10, 5, 10)) == pytest.approx(20.0)


# ----------------------------------------------------------------------------------------------
# ground truth and the protocol's choices
# ----------------------------------------------------------------------------------------------


def test_membership_follows_the_hierarchy():
    table = ObjectTable([SceneObject(1, "group", "group"), SceneObject(2, "table", "object", parent=1),
                         SceneObject(3, "leg", "part", parent=2), SceneObject(4, "top", "part", parent=2),
                         SceneObject(5, "cup", "object", parent=1), SceneObject(6, "wall", "object")])
    assert np.nonzero(membership(table, 2))[0].tolist() == [2, 3, 4]
    assert np.nonzero(membership(table, 1))[0].tolist() == [1, 2, 3, 4, 5]
    assert np.nonzero(membership(table, 3))[0].tolist() == [3]
    instances = np.array([[3, 4, 5], [6, 0, 99]], np.uint16)  # 99: not listed, never a member
    np.testing.assert_array_equal(object_mask(instances, membership(table, 2)), [[True, True, False], [False] * 3])


def test_occlusion_counts_closer_neighbours_not_contact():
    mask = np.zeros((10, 10), bool)
    mask[3:7, 3:7] = True  # boundary: 12 pixels
    depth = np.full((10, 10), 3.0)
    depth[mask] = 2.0
    assert occluded_fraction(mask, depth, 0.05) == 0.0  # background behind
    depth[3:7, 7] = 1.0  # something in front on the right: the right column (4 px) is occluded
    assert occluded_fraction(mask, depth, 0.05) == pytest.approx(4 / 12)
    depth[3:7, 7] = 1.95  # 2.5 % closer: contact, not occlusion
    assert occluded_fraction(mask, depth, 0.05) == 0.0
    depth[3:7, 7] = 0.0  # invalid depth never occludes
    assert occluded_fraction(mask, depth, 0.05) == 0.0
    assert not touches_border(mask) and touches_border(np.pad(mask, 0)[:, 3:])


def write_hand_scene(root, with_depth=True):
    """Four 12x16 views of object 1 (a 3-part square) and object 2; view b has 1 partly hidden."""
    K = np.array([[10.0, 0, 8], [0, 10.0, 6], [0, 0, 1]])
    splits = {"a": "train", "b": "train", "c": "test", "d": "test"}
    cams = [Camera(n, s, 16, 12, K, np.eye(4)) for n, s in splits.items()]
    objects = ObjectTable([SceneObject(1, "box", "object", evaluated=True), SceneObject(3, "box/lid", "part", parent=1),
                           SceneObject(2, "ball", "object", evaluated=True), SceneObject(5, "wall", "object")])
    layouts = {  # (object 1 rows, cols), object 2 box, object 1 hidden by 2 in front?
        "a": ((2, 6, 2, 6), (8, 11, 10, 14), False),  # 16 px of 1, away from the border
        "b": ((1, 8, 1, 9), (3, 6, 7, 10), True),  # 56 px, but 2 stands in front of its right side
        "c": ((0, 6, 0, 10), (7, 11, 10, 15), False),  # 60 px, touches the border
        "d": ((4, 6, 4, 6), (6, 11, 2, 12), False),  # 4 px
    }
    for cam in cams:
        (y0, y1, x0, x1), (v0, v1, u0, u1), front = layouts[cam.name]
        ids = np.full((12, 16), 5, np.uint16)
        depth = np.full((12, 16), 4.0)
        ids[y0:y1, x0:x1] = 1
        ids[y0, x0:x1] = 3  # the lid is a part of the box
        depth[y0:y1, x0:x1] = 2.0
        ids[v0:v1, u0:u1] = 2
        depth[v0:v1, u0:u1] = 1.0 if front else 3.0
        rgb = np.zeros((12, 16, 3), np.uint8)
        rgb[..., 0] = ids * 40
        write_frame(root, cam.name, rgb, ids, depth if with_depth else None)
    Scene(root=root, cameras=cams, objects=objects).write_metadata()
    return Scene.read(root)


def test_protocols_choose_views_and_reference(tmp_path):
    scene = write_hand_scene(tmp_path / "s")
    standard = GroundTruth(scene, scene.cameras, EvaluateParams(min_pixels=10))
    assert standard.object_ids == [1, 2]
    assert int(standard.mask(1, "a").sum()) == 16  # lid and body together
    info_b = standard.info[1][1]
    assert info_b.pixels == 56 - 6 and info_b.occluded > 0.05  # the ball hides 6 px and bounds its right side
    # the largest training view (b) is occluded: the standard protocol prefers a, the official one b
    assert standard.reference(1) == "a"
    assert GroundTruth(scene, scene.cameras, EvaluateParams(protocol="official", min_pixels=10)).reference(1) == "b"
    # standard: test views with >= min_pixels; d has 4 px of the box
    assert standard.extraction_views(1) == ["c"] and standard.nvs_views(1) == ["c"]
    assert GroundTruth(scene, scene.cameras, EvaluateParams(min_pixels=4)).extraction_views(1) == ["c", "d"]
    # official: every view, occluded ones skipped for both tasks
    official = GroundTruth(scene, scene.cameras, EvaluateParams(protocol="official", min_pixels=10))
    assert official.extraction_views(1) == ["a", "c"] and official.nvs_views(1) == ["a", "c"]
    everything = GroundTruth(scene, scene.cameras, EvaluateParams(views="all", min_pixels=10))
    assert everything.extraction_views(1) == ["a", "c"] and everything.nvs_views(1) == ["a", "b", "c"]
    q = standard.query(1)
    assert q.reference == "a" and q.object_id == 1 and q.mask.sum() == 16
    # without depth maps there is no occlusion test
    flat = GroundTruth(write_hand_scene(tmp_path / "f", with_depth=False), scene.cameras, EvaluateParams(min_pixels=10))
    assert flat.info[1][1].occluded is None and flat.reference(1) == "b"


def test_ground_truth_view_facts_equal_the_per_object_mask_twin(tmp_path):
    """GroundTruth counts pixels per leaf id once per view and builds a mask only where the object is
    seen: every view fact and mask equals the per-object :func:`object_mask` computation."""
    for with_depth in (True, False):
        scene = write_hand_scene(tmp_path / f"s{with_depth}", with_depth=with_depth)
        params = EvaluateParams(min_pixels=10)
        gt = GroundTruth(scene, scene.cameras, params)
        for oid in gt.object_ids:
            for cam, info in zip(scene.cameras, gt.info[oid]):
                mask = object_mask(scene.instances(cam.name), gt.members[oid])
                pixels = int(mask.sum())
                occ = occluded_fraction(mask, scene.depth(cam.name), params.occlusion_depth_ratio) \
                    if pixels and with_depth else None
                assert (info.frame, info.pixels, info.occluded, info.border) == \
                    (cam.name, pixels, occ, touches_border(mask) if pixels else False)
                np.testing.assert_array_equal(gt.mask(oid, cam.name), mask)


def test_params_protocol_values_and_errors():
    assert EvaluateParams().min_pixels == 50 and EvaluateParams().accuracy == "accuracy"
    official = EvaluateParams(protocol="official")
    assert (official.min_pixels, official.views, official.accuracy) == (200, "all", "precision")
    assert EvaluateParams(protocol="official", min_pixels=7).min_pixels == 7
    from trace3d.params import from_mapping

    with pytest.raises(ConfigError, match="min_pixel"):
        from_mapping(EvaluateParams, {"min_pixel": 3}, "evaluate params")
    with pytest.raises(ConfigError):
        from_mapping(EvaluateParams, {"protocol": "paper"}, "evaluate params")


# ----------------------------------------------------------------------------------------------
# label assignment on a toy scene solved by hand
# ----------------------------------------------------------------------------------------------


def grid(x0, x1, y0, y1, z, step=0.05):
    xs, ys = np.arange(x0 + step / 2, x1, step), np.arange(y0 + step / 2, y1, step)
    gx, gy = np.meshgrid(xs, ys)
    n = gx.size
    return GaussianModel(means=torch.tensor(np.stack([gx.ravel(), gy.ravel(), np.full(n, z)], 1), dtype=torch.float32),
                         quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                         log_scales=torch.full((n, 2), math.log(step * 0.6)), opacity_logits=torch.full((n,), 4.0),
                         sh_dc=torch.zeros(n, 1, 3), sh_rest=torch.zeros(n, 0, 3))


def cat(*models):
    return GaussianModel(**{k: torch.cat([m.get(k) for m in models]) for k in GaussianModel.PARAM_NAMES})


def cam_at(x, name, split="train", width=48, height=32):
    w2c = np.eye(4)
    w2c[0, 3] = -x
    return Camera(name, split, width, height, np.array([[30.0, 0, width / 2], [0, 30.0, height / 2], [0, 0, 1]]), w2c)


def plane_x(cam):
    """[H, W] world x of each pixel centre on the plane z = 2."""
    u = np.arange(cam.width) + 0.5
    return np.broadcast_to((u - cam.K[0, 2]) / cam.K[0, 0] * 2.0 - cam.world_to_camera[0, 3], (cam.height, cam.width))


def toy():
    """Object 1 (x < 0) and object 2 (x >= 0) on the plane z = 2, seen by three cameras."""
    left, right = grid(-1.0, 0.0, -0.6, 0.6, 2.0), grid(0.0, 1.0, -0.6, 0.6, 2.0)
    model = cat(left, right)
    truth = np.concatenate([np.full(len(left), 1), np.full(len(right), 2)])
    cams = [cam_at(0.0, "a"), cam_at(0.2, "b"), cam_at(-0.2, "c")]
    maps = [np.where(plane_x(c) < 0.0, 1, 2) for c in cams]
    return model, truth, cams, maps


def test_labels_recover_the_objects_and_answer_queries():
    model, truth, cams, maps = toy()
    weights = summed_label_weights(model, cams, maps)
    label, confidence, total = assign_labels(weights, 0.5)
    seen = total > 0
    assert seen.mean() > 0.9
    # by hand: a Gaussian away from x = 0 lies on its own object's pixels in every view
    away = seen & (np.abs(model.means[:, 0].numpy()) > 0.1)
    np.testing.assert_array_equal(label[away], truth[away])
    assert confidence[away].min() > 0.99
    lifted = LabelledScene(model, label, confidence, cams)
    query = ObjectQuery("a", plane_x(cams[0]) < 0.0, 1)
    assert lifted.object_labels(query) == [1]
    keep = lifted.object_gaussians(query)
    assert (keep == (label == 1)).all() and (truth[keep] == 1).all()
    # a mask of a small part of object 2 still selects object 2 (its weight inside the mask wins)
    part = (plane_x(cams[0]) > 0.3) & (plane_x(cams[0]) < 0.4)
    assert LabelledScene(model, label, confidence, cams).object_labels(ObjectQuery("a", part, 2)) == [2]
    # masks at another view are the object's pixels there, up to the boundary column
    other = cam_at(0.3, "t", "test")
    (mask,) = lifted.object_masks(query, [other])
    x = plane_x(other)
    y = ((np.arange(other.height) + 0.5 - other.K[1, 2]) / other.K[1, 1] * 2.0)[:, None]
    inner = (np.abs(x) > 0.1) & (np.abs(y) < 0.5) & (x > -0.9)  # on the plane, away from its edges
    np.testing.assert_array_equal(mask[inner], (x < 0)[inner])
    with pytest.raises(Trace3DError, match="reference view"):
        lifted.object_labels(ObjectQuery("nope", query.mask))


def test_labels_sum_weights_over_views_not_votes():
    """A Gaussian on label 1 in two views with little weight and on label 2 in one view with much
    weight takes label 2 (votes would say 1); the confidence filter removes an even split."""
    dense = torch.tensor([[0.0, 0.2, 0.0], [0.0, 0.2, 0.0], [0.0, 0.0, 0.9]])  # rows: views
    weights = dense.sum(0, keepdim=True)  # one Gaussian
    label, confidence, total = assign_labels(weights.to_sparse(), 0.5)
    assert label.tolist() == [2] and confidence[0] == pytest.approx(0.9 / 1.3) and total[0] == pytest.approx(1.3)
    label, _, _ = assign_labels(torch.tensor([[0.0, 0.5, 0.5], [0.0, 0.0, 0.0]]), 0.6)
    assert label.tolist() == [-1, -1]  # below the confidence / never seen


def test_summed_weights_match_the_dense_backward_twin():
    model, _, cams, maps = toy()
    small = model.subset(torch.arange(0, len(model), 7))
    fast = summed_label_weights(small, cams[:2], maps[:2]).to_dense()
    slow = _summed_label_weights_dense(small, cams[:2], maps[:2])
    assert fast.shape == slow.shape
    torch.testing.assert_close(fast, slow, rtol=1e-4, atol=1e-5)


# ----------------------------------------------------------------------------------------------
# the evaluate step end to end on a tiny room
# ----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny_lifted(tmp_path_factory):
    """A tiny synthetic room, Gaussians on its ground-truth depth (no fit needed), lifted by label
    assignment from the ground-truth object ids (an oracle for the label maps)."""
    from trace3d.lifting.labels import run_labels_lift

    root = tmp_path_factory.mktemp("eval")
    scene = oracle_room(root, {"seed": 3, "width": 48, "height": 36, "num_views": 8, "test_every": 2, "num_objects": 6,
                               "supersample": 1})
    (root / "lift").mkdir()
    run_labels_lift(scene, None, root / "gaussians", root / "labels", root / "lift", {})
    return root


EVAL_PARAMS = json.dumps({"min_pixels": 20, "max_occluded_fraction": 0.25, "turntable_views": 3, "turntable_size": 24, "picture_objects": 2})


def test_evaluate_end_to_end_objects_and_determinism(tiny_lifted, tmp_path):
    from trace3d.cli import main

    root = tiny_lifted
    label = json.dumps({"variant": "oracle", "consistent_masks": True, "density_control": False})
    args = ["evaluate", "--scene", str(root / "scene"), "--gaussians", str(root / "gaussians"), "--lift",
            str(root / "lift"), "--params", EVAL_PARAMS, "--label", label]
    assert main(args + ["--out", str(tmp_path / "a")]) == 0
    assert main(args + ["--out", str(tmp_path / "b"), "--objects", str(tmp_path / "b_objects")]) == 0
    a, b = (json.loads((tmp_path / d / "metrics.json").read_text()) for d in ("a", "b"))
    for m in (a, b):
        m.pop("seconds")
        m["lift"].pop("seconds")
    assert a == b
    assert a["variant"] == {"variant": "oracle", "consistent_masks": True, "density_control": False}
    assert a["lift"]["method"] == "labels" and a["protocol"] == "standard"
    # the oracle labels on Gaussians placed on the true surfaces extract the objects, shuffled labels do not
    assert a["extraction"]["objects"] >= 2 and a["nvs"]["objects"] >= 3
    assert a["extraction"]["mIoU"] > 0.4 and a["nvs"]["mIoU"] > 0.45 and a["extraction"]["PSNR"] > 15
    shuffled = tmp_path / "shuffled_lift"
    shuffled.mkdir()
    (shuffled / "lift.json").write_text((root / "lift" / "lift.json").read_text())
    with np.load(root / "lift" / "labels.npz") as data:
        label, confidence = data["label"].copy(), data["confidence"]
    np.random.default_rng(0).shuffle(label)
    np.savez(shuffled / "labels.npz", label=label, confidence=confidence)
    quick = json.dumps({**json.loads(EVAL_PARAMS), "object_files": False, "picture_objects": 0})
    assert main(args[:6] + [str(shuffled), "--params", quick, "--out", str(tmp_path / "s")]) == 0
    s = json.loads((tmp_path / "s" / "metrics.json").read_text())
    assert s["extraction"]["mIoU"] < a["extraction"]["mIoU"] - 0.25
    assert s["nvs"]["mIoU"] < a["nvs"]["mIoU"] - 0.25
    assert 0 < a["nvs"]["mAcc"] <= 1
    scored = [o for o in a["objects"] if o["extraction"]["views"]]
    for o in scored:
        assert o["reference"] in {c.name for c in Scene.read(root / "scene").train_cameras}
        for v in o["extraction"]["views"]:
            assert v["pixels"] >= 20 and v["frame"] in {"view_001", "view_003", "view_005", "view_007"}
    assert (tmp_path / "a" / "pictures.png").stat().st_size > 5000
    for o in a["objects"]:
        assert (tmp_path / "a" / "objects" / f"{o['id']}.ply").is_file()
        assert (tmp_path / "a" / "objects" / f"{o['id']}.png").is_file()
        # --objects: the same files in the folder named (the workflow's <variant>/objects), none in the eval folder
        ply = (tmp_path / "b_objects" / f"{o['id']}.ply").read_bytes()
        assert ply == (tmp_path / "a" / "objects" / f"{o['id']}.ply").read_bytes()
    assert not (tmp_path / "b" / "objects").exists()
    assert (tmp_path / "a" / "pictures.png").read_bytes() == (tmp_path / "b" / "pictures.png").read_bytes()


def test_object_ply_reloads_and_renders_as_inside_the_scene(tiny_lifted, tmp_path):
    from trace3d.evaluation.step import run_evaluate

    root = tiny_lifted
    (tmp_path / "e").mkdir()
    metrics = run_evaluate(root / "scene", None, root / "gaussians", root / "lift", tmp_path / "e",
                           json.loads(EVAL_PARAMS), {"variant": "x"})
    scene = Scene.read(root / "scene")
    model = GaussianModel.read_ply(root / "gaussians" / "point_cloud.ply")
    lifted = load_lifted(root / "lift", model, scene, scene.train_cameras)
    obj = max((o for o in metrics["objects"] if o["nvs"]["views"]), key=lambda o: o["gaussians"])
    query = ObjectQuery(obj["reference"], GroundTruth(scene, scene.cameras, EvaluateParams(min_pixels=20)).mask(
        obj["id"], obj["reference"]), obj["id"])
    keep = lifted.object_gaussians(query)
    assert keep.sum() == obj["gaussians"] > 0
    reloaded = GaussianModel.read_ply(tmp_path / "e" / "objects" / f"{obj['id']}.ply")
    assert len(reloaded) == keep.sum()
    cam = scene.camera(obj["nvs"]["views"][0]["frame"])
    rgb_ply, alpha_ply = render_alone(reloaded, cam)
    rgb_sub, alpha_sub = render_alone(model.subset(torch.from_numpy(keep)), cam)
    np.testing.assert_array_equal(rgb_ply, rgb_sub)
    np.testing.assert_array_equal(alpha_ply, alpha_sub)
    # ... and as the scene's own Gaussians with every other one made transparent
    hidden = model.detached_copy()
    hidden.opacity_logits[~torch.from_numpy(keep)] = -30.0
    rgb_in, alpha_in = render_alone(hidden, cam)
    np.testing.assert_allclose(rgb_ply, rgb_in, atol=1e-5)
    np.testing.assert_allclose(alpha_ply, alpha_in, atol=1e-5)
    assert alpha_ply.max() > 0.5


def test_evaluate_bad_input(tiny_lifted, tmp_path):
    from trace3d.cli import main

    root = tiny_lifted
    base = ["evaluate", "--scene", str(root / "scene"), "--gaussians", str(root / "gaussians")]
    assert main(base + ["--lift", str(tmp_path / "none"), "--out", str(tmp_path / "o1")]) == 2
    assert not (tmp_path / "o1").exists()
    assert main(base + ["--lift", str(root / "lift"), "--out", str(tmp_path / "o2"), "--label", "[1]"]) == 2
    assert main(base + ["--lift", str(root / "lift"), "--out", str(tmp_path / "o3"), "--params", "{min_pixel: 3}"]) == 2
    (tmp_path / "stale").mkdir()
    (tmp_path / "stale" / "lift.json").write_text(json.dumps({"method": "labels"}))
    np.savez(tmp_path / "stale" / "labels.npz", label=np.zeros(3, np.int32), confidence=np.zeros(3, np.float32))
    with pytest.raises(SceneFormatError, match="stale"):
        from trace3d.evaluation.step import register_lifting_methods

        register_lifting_methods()
        load_lifted(tmp_path / "stale", GaussianModel.read_ply(root / "gaussians" / "point_cloud.ply"),
                    Scene.read(root / "scene"), [])


def test_official_protocol_scores_all_views_with_precision(tiny_lifted, tmp_path):
    from trace3d.evaluation.step import run_evaluate

    root = tiny_lifted
    (tmp_path / "o").mkdir()
    m = run_evaluate(root / "scene", None, root / "gaussians", root / "lift", tmp_path / "o",
                     {"protocol": "official", "min_pixels": 20, "object_files": False, "picture_objects": 1}, None)
    assert m["protocol"] == "official" and m["nvs"]["mAcc_definition"].startswith("precision")
    assert m["params"]["views"] == "all" and m["params"]["accuracy"] == "precision"
    frames = {v["frame"] for o in m["objects"] for v in o["nvs"]["views"]}
    assert frames & {"view_000", "view_002", "view_004", "view_006"}  # training views count too
    for o in m["objects"]:
        for v in o["nvs"]["views"]:  # precision: TP / predicted, never above the ground-truth share
            assert 0.0 <= v["acc"] <= 1.0
            assert v["acc"] * v["predicted_pixels"] <= v["pixels"] + 1e-9
            occluded = next(g for g in o["ground_truth_views"] if g["frame"] == v["frame"])["occluded_fraction"]
            assert occluded is None or occluded <= 0.05
    assert not (tmp_path / "o" / "objects").exists()


def test_nvos_scribbles_select_instances_and_scores_are_hand_counted():
    from trace3d.evaluation.nvos import mask_scores, scribble_mask

    labels = np.zeros((6, 8), np.int64)
    labels[1:4, 1:4] = 3  # the object, in two instances
    labels[4:6, 1:4] = 5
    labels[:, 5:] = 7  # a neighbour that a negative stroke crosses
    pos = np.array([[2.5, 2.2], [1.1, 4.9], [6.0, 1.0]])  # (x, y): instance 3, instance 5, and 7
    neg = np.array([[6.5, 3.0], [0.2, 0.2]])  # instance 7, and unlabelled
    mask, chosen = scribble_mask(labels, pos, neg)
    assert chosen == [3, 5] and mask.sum() == 15
    # every hit instance also negative: the one with more positive than negative hits
    mask, chosen = scribble_mask(labels, np.array([[6.0, 1.0], [6.0, 2.0]]), np.array([[7.0, 0.0]]))
    assert chosen == [7]
    mask, chosen = scribble_mask(labels, np.array([[0.0, 0.0]]), neg)  # only unlabelled pixels hit
    assert chosen == [] and not mask.any()
    pred = np.zeros((4, 5), bool)
    truth = np.zeros((4, 5), bool)
    pred[0, :3] = True  # 3 predicted
    truth[0, 1:4] = True  # 3 true, 2 shared
    s = mask_scores(pred, truth)
    assert (s["tp"], s["fp"], s["fn"], s["tn"]) == (2, 1, 1, 16)
    assert s["iou"] == pytest.approx(0.5) and s["accuracy"] == pytest.approx(18 / 20)
