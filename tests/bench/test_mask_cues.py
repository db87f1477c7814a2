"""`trace3d bench mask-cues`: the pair classes, the AUC, the depth jumps and the mask recall it reports."""

from __future__ import annotations

import itertools
import json
import shutil

import numpy as np
import pytest

from trace3d.bench.mask_cues import auc, best_mask_iou, classify_pairs, depth_jumps
from trace3d.cli import main as cli_main

pytestmark = pytest.mark.usefixtures("single_numba_thread")


def test_auc_matches_counting_every_pair_with_ties():
    rng = np.random.default_rng(3)
    for _ in range(20):
        pos = rng.integers(0, 6, rng.integers(1, 15)).astype(float)
        neg = rng.integers(0, 6, rng.integers(1, 15)).astype(float)
        counted = sum(1.0 if p > n else 0.5 if p == n else 0.0 for p, n in itertools.product(pos, neg))
        assert auc(pos, neg) == pytest.approx(counted / (len(pos) * len(neg)))
    assert auc([2.0, 3.0], [0.0, 1.0]) == 1.0 and auc([0.0], [1.0]) == 0.0
    assert np.isnan(auc([], [1.0]))


def test_pairs_are_classed_by_leaf_and_object_in_the_geometry_sources_order():
    # leaves 1, 2 belong to object 10 (evaluated); leaf 3 is object 20 (not evaluated); 0 is nothing
    leaf = np.array([[1, 1, 2],
                     [3, 0, 2]])
    lookup = {0: 0, 1: 10, 2: 10, 3: 20}
    obj = np.vectorize(lookup.get)(leaf)
    evaluated = obj == 10
    cls, use = classify_pairs(leaf, obj, evaluated)
    # horizontal pairs row by row: (1,1) (1,2) | (3,0) (0,2); then vertical pairs: (1,3) (1,0) (2,2)
    assert cls.tolist() == [0, 1, 2, 2, 2, 2, 0]
    assert use.tolist() == [True, True, False, False, True, False, True]


def test_depth_jumps_are_zero_on_a_slanted_plane_and_measure_a_step():
    H, W = 6, 12
    x = np.arange(W)[None, :].repeat(H, 0).astype(float)
    plane = 1.0 / (0.5 + 0.02 * x)  # inverse depth linear in x: a slanted plane
    jumps = depth_jumps(plane, np.zeros((H, W), bool), reach=1)
    # away from the image's edge (where the span is clipped) the plane jumps nowhere
    assert np.allclose(jumps[: H * (W - 1)].reshape(H, W - 1)[:, 2:-2], 0.0, atol=1e-9)
    assert np.allclose(jumps[H * (W - 1):], 0.0, atol=1e-9)
    step = np.where(x < 6, 2.0, 4.0)  # a wall at 4 behind an object at 2
    jumps = depth_jumps(step, np.zeros((H, W), bool), reach=1)
    horizontal = jumps[: H * (W - 1)].reshape(H, W - 1)
    assert horizontal[:, 5] == pytest.approx(np.full(H, (1 / 2 - 1 / 4) / (1 / 2)))  # gap / depth of the nearer
    assert np.allclose(horizontal[:, :3], 0.0) and np.allclose(jumps[H * (W - 1):], 0.0)
    empty = np.zeros((H, W), bool)
    empty[2, 4] = True
    jumps = depth_jumps(plane, empty, reach=1)
    assert np.isinf(jumps[: H * (W - 1)].reshape(H, W - 1)[2, 3:5]).all()
    assert np.isfinite(jumps).sum() == len(jumps) - 4


def test_best_mask_iou():
    truth = np.zeros((4, 4), bool)
    truth[:2, :2] = True
    masks = np.zeros((2, 4, 4), bool)
    masks[0, :2, :] = True  # IoU 4 / 8
    masks[1, :2, :1] = True  # IoU 2 / 4
    assert best_mask_iou(masks, truth) == 0.5
    masks[1, :2, :2] = True
    assert best_mask_iou(masks, truth) == 1.0
    assert best_mask_iou(np.zeros((0, 4, 4), bool), truth) == 0.0


@pytest.fixture(scope="module")
def fitted_room(tmp_path_factory):
    """A tiny synthetic room (ground truth, true depth, its own masks) with Gaussians on its depth standing in
    for a 2DGS fit."""
    from trace3d.datasets.synthetic.params import SyntheticParams
    from trace3d.datasets.synthetic.writer import generate_scene
    from trace3d.gaussians import init_from_depth
    from trace3d.masks import run_masks
    from trace3d.scene import Scene

    root = tmp_path_factory.mktemp("cues")
    generate_scene(root / "room" / "scene", SyntheticParams(seed=5, width=64, height=48, num_views=4, test_every=4,
                                                            supersample=1))
    scene = Scene.read(root / "room" / "scene")
    model = init_from_depth(scene, cameras=scene.cameras, stride=1, max_points=None, sh_degree=0, opacity=0.95)
    model.log_scales = model.log_scales - 0.3
    (root / "room" / "gaussians").mkdir()
    model.write_ply(root / "room" / "gaussians" / "point_cloud.ply")
    run_masks(scene, root / "room" / "masks", "simulated", {"model": "nested"})
    return root / "room"


def test_bench_on_a_room_with_ground_truth(fitted_room, tmp_path, capsys):
    out, plot = tmp_path / "cues.json", tmp_path / "cues.png"
    args = ["bench", "mask-cues", "--room", str(fitted_room), "--masks", "{room}/masks", "--stride", "1",
            "--out", str(out), "--plot", str(plot)]
    assert cli_main(args) == 0
    result = json.loads(out.read_text())
    assert result["views"] == 4 and plot.stat().st_size > 0
    assert min(result["pairs"].values()) > 0
    true = result["cues"]["true_depth_jump"]
    # the true depth jumps at objects' outlines, never inside a leaf's smooth surface
    assert true["auc_boundary_vs_within_part"] > 0.7
    assert true["median"]["object_boundary"] > true["median"]["within_part"]
    assert set(result["cues"]) == {"render_depth_jump", "true_depth_jump", "crease_deg", "colour"}
    recall = result["masks"]["room/masks"]
    assert recall["object_views"] > 0 and 0.0 < recall["share_iou_0.8"] <= recall["share_iou_0.5"] <= 1.0
    # without depth/: no true-depth cue, the rest unchanged
    bare = tmp_path / "bare"
    shutil.copytree(fitted_room, bare)
    shutil.rmtree(bare / "scene" / "depth")
    args = ["bench", "mask-cues", "--room", str(bare), "--stride", "1", "--out", str(tmp_path / "b.json")]
    assert cli_main(args) == 0
    other = json.loads((tmp_path / "b.json").read_text())
    assert "true_depth_jump" not in other["cues"]
    assert other["cues"]["colour"] == result["cues"]["colour"]


def test_bad_input_is_one_sentence(fitted_room, tmp_path, capsys):
    assert cli_main(["bench", "mask-cues", "--room", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "needs a fitted room's results folder" in err and "Traceback" not in err and len(err.splitlines()) == 1
    assert cli_main(["bench", "mask-cues", "--room", str(fitted_room), "--masks", "{room}/nothing"]) == 2
    err = capsys.readouterr().err.strip()
    assert "missing; give bench mask-cues a masks folder" in err and len(err.splitlines()) == 1
    assert cli_main(["bench", "mask-cues", "--room", str(fitted_room), "--masks", "{scene}/masks"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--masks may name the room as {room}" in err and len(err.splitlines()) == 1
