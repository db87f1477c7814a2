"""Tests of Trace3D's own stages: GIT statistics, consistent instance maps, GIT-guided refinement."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from trace3d.errors import ConfigError, SceneFormatError
from trace3d.gaussians import GaussianModel
from trace3d.masks.patches import PatchHierarchy
from trace3d.render import trace, trace_by_backward
from trace3d.scene import Camera
from trace3d.tracing.git import GITStats, TraceParams, trace_views
from trace3d.tracing.merge import (MergeParams, associate, merge_all, merge_view, pair_similarity,
                                   pair_similarity_bruteforce, source_histograms)
from trace3d.tracing.merge_quality import adjusted_rand_index, segmentation_quality
from trace3d.tracing.refine import (GENERATION, GITStrategy, RefineParams, ambiguity_scores, boundary_band,
                                    find_ambiguous, with_generation)
from trace3d.training import split_gaussians


# numba kernels on one thread: the tests compare sums whose order must not depend on the pool
pytestmark = pytest.mark.usefixtures("single_numba_thread")


def stats_from(labels: np.ndarray, prob: np.ndarray | None = None, visibility: np.ndarray | None = None) -> GITStats:
    labels = np.asarray(labels, np.int32)
    prob = np.ones(labels.shape, np.float32) if prob is None else np.asarray(prob, np.float32)
    if visibility is None:
        visibility = (labels >= 0).astype(np.float32)
    return GITStats(label=labels, prob=np.where(labels >= 0, prob, 0).astype(np.float32),
                    visibility=np.asarray(visibility, np.float32), frames=[f"v{i}" for i in range(labels.shape[1])],
                    num_labels=np.full(labels.shape[1], int(labels.max()) + 1, np.int64))


def hierarchy(num_patches: int, masks: list[list[int]]) -> PatchHierarchy:
    """Patches 1..P, each listed with the masks containing it."""
    return PatchHierarchy(masks, np.ones(num_patches, np.int64), np.ones(1 + max((m for ms in masks for m in ms), default=0),
                                                                          np.int64), np.ones(1, np.float32))


# ----------------------------------------------------------------------------------------------
# A constructed scene: two flat objects in front of the camera, seen from two views
# ----------------------------------------------------------------------------------------------


def grid_model(x0: float, x1: float, y0: float, y1: float, z: float, step: float = 0.05) -> GaussianModel:
    xs = np.arange(x0 + step / 2, x1, step)
    ys = np.arange(y0 + step / 2, y1, step)
    gx, gy = np.meshgrid(xs, ys)
    n = gx.size
    means = torch.tensor(np.stack([gx.ravel(), gy.ravel(), np.full(n, z)], 1), dtype=torch.float32)
    return GaussianModel(means=means, quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                         log_scales=torch.full((n, 2), math.log(step * 0.6)), opacity_logits=torch.full((n,), 4.0),
                         sh_dc=torch.zeros(n, 1, 3), sh_rest=torch.zeros(n, 0, 3))


def concat(*models: GaussianModel) -> GaussianModel:
    return GaussianModel(**{name: torch.cat([m.get(name) for m in models]) for name in GaussianModel.PARAM_NAMES})


def camera_at(x: float, name: str, width: int = 48, height: int = 32) -> Camera:
    w2c = np.eye(4)
    w2c[0, 3] = -x
    K = np.array([[30.0, 0, width / 2], [0, 30.0, height / 2], [0, 0, 1]])
    return Camera(name, "train", width, height, K, w2c)


def two_objects():
    """Object 1 at x in [-1, 0), object 2 at x in [0, 1), both on the plane z = 2; cameras at x = 0, 0.2."""
    left = grid_model(-1.0, 0.0, -0.6, 0.6, 2.0)
    right = grid_model(0.0, 1.0, -0.6, 0.6, 2.0)
    model = concat(left, right)
    truth = np.concatenate([np.full(len(left), 1), np.full(len(right), 2)])
    cameras = [camera_at(0.0, "a"), camera_at(0.2, "b")]
    return model, truth, cameras


def pixel_x_world(camera: Camera) -> np.ndarray:
    """[H, W] world x of each pixel centre on the plane z = 2."""
    u = np.arange(camera.width) + 0.5
    x = (u - camera.K[0, 2]) / camera.K[0, 0] * 2.0 - camera.world_to_camera[0, 3]
    return np.broadcast_to(x, (camera.height, camera.width))


def test_split_object_merges_and_nothing_else_does():
    model, truth, cameras = two_objects()
    xa, xb = pixel_x_world(cameras[0]), pixel_x_world(cameras[1])
    # view a: object 1 split into two patches (x < -0.5, the rest), object 2 one patch; view b: whole objects
    map_a = np.where(xa < -0.5, 1, np.where(xa < 0.0, 2, 3))
    map_b = np.where(xb < 0.0, 1, 2)
    stats = trace_views(model, cameras, [map_a, map_b])
    # every Gaussian is traced to its own object's patch in the view where its object is whole
    seen_b = stats.visible(0.0)[:, 1]
    assert (stats.label[seen_b, 1] == truth[seen_b]).mean() > 0.9
    all_pairs = [[1], [1], [1]]  # one coarse mask around everything: every pair is a candidate
    merges, luts = merge_all(stats, [hierarchy(3, all_pairs), hierarchy(2, [[1], [1]])], MergeParams())
    a, b = merges
    assert a.lut[1] == a.lut[2] != a.lut[3]  # the two halves of object 1 merge, object 2 stays apart
    assert b.lut[1] != b.lut[2]
    assert a.num_instances == 2 and b.num_instances == 2
    # ids across views: object 1 has one id in both views, object 2 another
    assert luts[0][a.lut[1]] == luts[1][b.lut[1]]
    assert luts[0][a.lut[3]] == luts[1][b.lut[2]]
    assert luts[0][a.lut[1]] != luts[0][a.lut[3]]


def test_pairs_outside_a_common_mask_are_not_considered():
    model, _, cameras = two_objects()
    xa, xb = pixel_x_world(cameras[0]), pixel_x_world(cameras[1])
    map_a = np.where(xa < -0.5, 1, np.where(xa < 0.0, 2, 3))
    map_b = np.where(xb < 0.0, 1, 2)
    stats = trace_views(model, cameras, [map_a, map_b])
    separate = hierarchy(3, [[1], [2], [3]])  # no coarser mask holds both halves
    merges, _ = merge_all(stats, [separate, hierarchy(2, [[1], [2]])], MergeParams())
    assert len(merges[0].pairs) == 0 and merges[0].num_instances == 3
    everything, _ = merge_all(stats, [separate, hierarchy(2, [[1], [2]])], MergeParams(candidates="all_pairs"))
    assert everything[0].num_instances == 2


def test_straddling_patch_is_not_merged_into_either_object():
    # Gaussians 0-9 are object 1, 10-19 object 2. View 0: L = 0-4, S = 5-14 (straddles), R = 15-19;
    # views 1 and 2 see the two objects whole.
    labels = np.zeros((20, 3), np.int32)
    labels[:, 0] = np.r_[np.full(5, 1), np.full(10, 2), np.full(5, 3)]
    labels[:, 1] = labels[:, 2] = np.r_[np.full(10, 1), np.full(10, 2)]
    stats = stats_from(labels)
    common = [[0], [0], [0]]
    merges, _ = merge_all(stats, [hierarchy(3, common), hierarchy(2, [[0], [0]]), hierarchy(2, [[0], [0]])],
                          MergeParams())
    assert merges[0].num_instances == 3  # S merges with neither L nor R
    np.testing.assert_allclose(merges[0].sims, [0.5, 0.0, 0.5])  # (1,2), (1,3), (2,3)
    assert merges[1].num_instances == 2 and merges[2].num_instances == 2
    # the official threshold (0.4) does merge at 0.5: the preset reaches the code
    # (its minimum support, made for real scenes, would leave these 5-10 Gaussian patches out)
    views = [hierarchy(3, common), hierarchy(2, [[0], [0]]), hierarchy(2, [[0], [0]])]
    official, _ = merge_all(stats, views, MergeParams(preset="official", min_gaussians=0, min_gaussian_views=0,
                                                      grouping="union_find"))
    assert official[0].num_instances == 1
    # the official grouping, the released greedy loop: L joins S, which then takes no one else -> {L, S}, {R}
    official, _ = merge_all(stats, views, MergeParams(preset="official", min_gaussians=0, min_gaussian_views=0))
    assert official[0].lut.tolist() == [0, 1, 1, 2]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_factored_similarity_equals_bruteforce_pair_loop(seed):
    rng = np.random.default_rng(seed)
    n, views, t = 40, 5, 4
    labels = rng.integers(-1, t, size=(n, views)).astype(np.int32)
    visible = (rng.random((n, views)) > 0.25) & (labels >= 0)
    for v0 in range(views):
        hist = source_histograms(labels, visible, v0, t, t)
        pairs = np.array([(a, b) for a in range(t) for b in range(a + 1, t)])
        sims, omega = pair_similarity(hist, pairs)
        for (a, b), s, o in zip(pairs, sims, omega):
            ref_s, ref_o = pair_similarity_bruteforce(labels, visible, v0, int(a), int(b))
            assert o == ref_o
            assert s == pytest.approx(ref_s, abs=1e-12)


def test_association_links_by_mutual_majority():
    # view 0: instance 1 = Gaussians 0-2, instance 2 = Gaussian 3; view 1: one instance of all four
    labels = np.array([[1, 1], [1, 1], [1, 1], [2, 1]], np.int32)
    stats = stats_from(labels)
    merges = [merge_view(stats, 0, 2, np.zeros((0, 2), np.int64), 0.5, 0.0),
              merge_view(stats, 1, 1, np.zeros((0, 2), np.int64), 0.5, 0.0)]
    luts = associate(stats, merges, 0.0, 0.5)
    assert luts[1][1] == luts[0][1] != luts[0][2]


def test_association_never_joins_two_instances_of_one_view():
    # view 0: A = {0, 1}, B = {2, 3}; view 1 sees {0, 1, 2} as X; view 2 sees {1, 2, 3} as Y.
    # Mutual majorities link A-X, X-Y and Y-B: joining all would put A and B under one id.
    labels = np.array([[1, 1, -1], [1, 1, 1], [2, 1, 1], [2, -1, 1]], np.int32)
    stats = stats_from(labels)
    merges = [merge_view(stats, 0, 2, np.zeros((0, 2), np.int64), 0.5, 0.0),
              merge_view(stats, 1, 1, np.zeros((0, 2), np.int64), 0.5, 0.0),
              merge_view(stats, 2, 1, np.zeros((0, 2), np.int64), 0.5, 0.0)]
    luts = associate(stats, merges, 0.0, 0.5)
    assert luts[1][1] == luts[2][1] == luts[0][1]  # strongest first: X-Y (1.0), then A-X (2/3)
    assert luts[0][2] != luts[0][1]  # B-Y (2/3) would join view 0 twice: refused


def test_ground_truth_quality_figures():
    truth = np.array([[1, 1, 2, 2]] * 30)
    perfect = segmentation_quality([truth], [truth.copy()], min_pixels=10)
    assert perfect.ari == pytest.approx(1.0) and perfect.covered == 1.0 and perfect.straddling == 0.0
    merged = segmentation_quality([truth], [np.ones_like(truth)], min_pixels=10)
    assert merged.covered == 1.0 and merged.straddling == 1.0 and merged.ari == pytest.approx(0.0)
    split = np.array([[1, 3, 2, 2]] * 30)
    fragments = segmentation_quality([truth], [split], min_pixels=10)
    assert fragments.covered == 0.5 and fragments.straddling == 0.0
    assert adjusted_rand_index(np.array([0, 0, 1, 1]), np.array([5, 5, 7, 7])) == pytest.approx(1.0)


# ----------------------------------------------------------------------------------------------
# GIT statistics and the trace kernel's options
# ----------------------------------------------------------------------------------------------


def test_trace_views_matches_trace_and_counts_pixels():
    model, _, cameras = two_objects()
    cam = cameras[1]
    labels = np.where(pixel_x_world(cam) < 0.0, 1, 2).astype(np.uint16)
    stats = trace_views(model, [cam], [labels])
    weights = trace(model.splats(), cam, torch.from_numpy(labels), 3).to_dense()  # uint16 accepted
    total = weights.sum(1).numpy()
    np.testing.assert_allclose(stats.visibility[:, 0], total, rtol=1e-6)
    seen = total > 0
    np.testing.assert_array_equal(stats.label[seen, 0], weights.argmax(1).numpy()[seen])
    np.testing.assert_allclose(stats.prob[seen, 0], (weights.max(1).values / weights.sum(1)).numpy()[seen], rtol=1e-5)
    # pixel counting: the number of pixels of each label with a non-zero weight, from the dense reference
    per_pixel = trace_by_backward(model.splats(), cam, torch.arange(cam.width * cam.height).reshape(cam.height, cam.width),
                                  cam.width * cam.height, backend="reference")
    contributes = (per_pixel > 1e-7).float()  # [N, H*W]
    flat = torch.from_numpy(labels.astype(np.int64)).reshape(-1)
    expected = torch.zeros(len(model), 3).index_add_(1, flat, contributes)
    counts = trace(model.splats(), cam, torch.from_numpy(labels), 3, count_pixels=True).to_dense()
    assert (counts - expected).abs().max() <= 1.0  # a weight at the 1/255 alpha cut may round either way
    assert (counts == expected).float().mean() > 0.99


def test_trace_memory_batches_give_the_same_weights():
    from trace3d.render.kernels.coalesce import coalesce_triplets
    from trace3d.render.kernels.trace import trace_triplets
    from trace3d.render.projection import project

    model, _, cameras = two_objects()
    cam = cameras[0]
    per_pixel = torch.arange(cam.width * cam.height).reshape(cam.height, cam.width)
    proj = project(model.splats(), cam)
    whole, batched = (coalesce_triplets(*trace_triplets(proj, cam.width, cam.height, per_pixel, batch_slots=slots),
                                        len(model)) for slots in (1 << 22, 1))
    for a, b in zip(whole, batched):
        np.testing.assert_array_equal(a, b)
    # one label per pixel gives each splat's weight at each pixel: rows sum to its visibility
    labels = torch.zeros(cam.height, cam.width, dtype=torch.int64)
    by_splat = np.zeros(len(model), np.float32)
    np.add.at(by_splat, whole[0], whole[2])
    torch.testing.assert_close(torch.from_numpy(by_splat), trace(model.splats(), cam, labels, 1).to_dense()[:, 0])


def test_git_stats_round_trip_and_bad_file(tmp_path):
    stats = stats_from(np.array([[0, 1], [-1, 2]]))
    stats.save(tmp_path / "git.npz")
    back = GITStats.load(tmp_path / "git.npz")
    np.testing.assert_array_equal(back.label, stats.label)
    assert back.frames == ["v0", "v1"]
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(SceneFormatError, match="bad.npz"):
        GITStats.load(tmp_path / "bad.npz")
    with pytest.raises(SceneFormatError, match="missing"):
        GITStats.load(tmp_path / "none.npz")


# ----------------------------------------------------------------------------------------------
# Ambiguity and the split
# ----------------------------------------------------------------------------------------------


def test_gaussian_straddling_a_boundary_is_ambiguous_and_inner_ones_are_not():
    model, _, cameras = two_objects()
    # a large disk centred on the boundary x = 0, in front of the objects
    straddler = grid_model(-0.15, 0.15, -0.15, 0.15, 1.9, step=0.3)
    straddler.opacity_logits[:] = 0.0
    scene = concat(model, straddler)
    maps = [np.where(pixel_x_world(c) < 0.0, 1, 2) for c in cameras]
    stats = trace_views(scene, cameras, maps)
    ambiguous = find_ambiguous(stats, gamma=0.8, threshold=0.5, min_visibility=0.0)
    assert ambiguous[-1]
    # Gaussians well inside an object (|x| > 0.3) are never ambiguous
    inner = np.abs(model.means[:, 0].numpy()) > 0.3
    assert not ambiguous[: len(model)][inner].any()
    scores, views = ambiguity_scores(stats, 0.8, 0.0)
    assert scores[-1] == 1.0 and views[-1] == 2


def test_split_halves_scales_inside_parent_support():
    parent = grid_model(0.0, 0.2, 0.0, 0.2, 2.0, step=0.2)
    parent.log_scales = torch.log(torch.tensor([[0.1, 0.04]]))
    parent.quats = torch.tensor([[math.cos(0.3), 0.0, 0.0, math.sin(0.3)]])  # rotated about the normal
    parent = with_generation(parent)
    children = split_gaussians(parent, 2, torch.Generator().manual_seed(0), scale_divisor=2.0)
    assert len(children) == 2
    torch.testing.assert_close(children.scales, parent.scales.repeat(2, 1) / 2.0)
    offsets = children.means - parent.means
    assert (offsets[:, 2].abs() < 1e-6).all()  # in the tangent plane (normal = z)
    # inside the parent's support: within 3 sigma along its own axes
    rot = parent.rotations[0]
    local = offsets @ rot
    assert (local[:, 0].abs() <= 0.3).all() and (local[:, 1].abs() <= 0.12).all()
    assert (children.extras[GENERATION] == 0).all()  # the strategy marks children, not split_gaussians


# Lines of the released code (github.com/trace-3d/Trace3D, commit 712aa57), quoted as they stand there:
# the ``official`` presets must be what these lines say, so the expected values below are read from
# the quotes, not typed a second time.
RELEASED = {
    "remove_ab_gaus.py": (
        "threshold = 25#unseen th",  # a view sees a Gaussian above 25 pixels (split_mask: w.sum(-1) > threshold)
        "soft_th = 0.8",  # gamma: ab = (value < soft_th) & seen
        "sp_th = 0.4",  # theta_As: sp_mask = (ab_nums / (nums + 1e-6)) > sp_th
        "scale = 0.8#",  # weights_split(sp_mask, opt.opacity_cull, scale=scale)
        "gaussians.weights_prune(sp_mask, 0, -1)",  # strategy -1: every still-ambiguous Gaussian, right after the split
        "if iteration == 1 or iteration== opt.iterations:",  # opt.prune: remove the unseen at the first and last
        "weights = torch.zeros((gaussians.get_opacity.shape[0], len(viewpoints)), dtype=torch.int).cuda()",
    ),
    "scene/gaussian_model.py": (
        "def weights_split(self, split_mask, scene_extent, scale=0.8, N=2):",
        "self.get_scaling[selected_pts_mask].repeat(N, 1) / (scale*N))",
    ),
    "script/replica.sh": ("--iterations 9000", "--split_cycle_interval 1200", "--prune"),
    "arguments/__init__.py": ("self.split_from_iter = 10#prune gaussina", "self.split_cycle_num=4 #Number of split cycles"),
    "merge_patches.py": ("mask.repair(weights, miou_th=0.4)", 'parser.add_argument("--alpha_w", action="store_true")'),
    "utils/con_mask_utils.py": (
        "GAUS_NUM_TH = 100",  # filter_mask = count > GAUS_NUM_TH
        "vf_th: float = 0.2,) -> float:",  # view_filter = (w_a_valid > vf_th) & (w_b_valid > vf_th)
        "if val_views < 2:",  # return 0
        "count = count*(valid_weight_mask(uni).sum(-1) > ct_th+1)",  # ct_th = iter_num = val_views//MAX_VIEWS+1
    ),
    "conf/con_masks_conf.py": ("MAX_VIEWS = 160",),
}


def _released(file: str, name: str) -> float:
    """The number a quoted line of ``file`` gives ``name`` (``name = 0.4``, ``name=4``, ``--name 9000``,
    ``name: float = 0.2``)."""
    import re

    for line in RELEASED[file]:
        m = re.search(rf"(?:^|[\s(,]){re.escape(name)}(?:\s*:\s*\w+)?\s*[= ]\s*([0-9.]+)", line)
        if m:
            return float(m.group(1))
    raise KeyError(f"{file}: no quoted line sets {name}")


def test_presets_reach_the_code():
    """The ``official`` presets against the released code's lines (:data:`RELEASED`); the ``paper``
    presets against the paper (Sec. 3.3, 3.4: gamma 0.8, theta_As 0.5, scales halved, sim > 0.5)."""
    official = RefineParams(preset="official")
    split_from = int(_released("arguments/__init__.py", "self.split_from_iter"))
    interval = int(_released("script/replica.sh", "--split_cycle_interval"))
    cycles = int(_released("arguments/__init__.py", "self.split_cycle_num"))
    # the trace counts pixels (an int tensor of counts) unless --alpha_w, which replica.sh does not pass
    assert "dtype=torch.int" in RELEASED["remove_ab_gaus.py"][-1] and "store_true" in RELEASED["merge_patches.py"][1]
    assert not any("--alpha_w" in line for line in RELEASED["script/replica.sh"])
    assert "/ (scale*N)" in RELEASED["scene/gaussian_model.py"][1]
    assert (official.statistic, official.min_visibility, official.ambiguity_threshold, official.scale_divisor,
            official.iterations, official.detect_at) == (
        "pixels", _released("remove_ab_gaus.py", "threshold"), _released("remove_ab_gaus.py", "sp_th"),
        _released("remove_ab_gaus.py", "scale") * _released("scene/gaussian_model.py", "N"),
        _released("script/replica.sh", "--iterations"), [split_from + k * interval for k in range(cycles)])
    assert official.gamma == _released("remove_ab_gaus.py", "soft_th")
    assert official.detect_at == [10, 1210, 2410, 3610]
    assert official.detection_iterations() == [1, 121, 241, 361]
    # after_split: weights_prune(..., -1) removes every Gaussian still ambiguous right after the split; no
    # detection after the last iteration (the last split_mask only prints); the unseen pruned at 1 and the end
    assert RELEASED["remove_ab_gaus.py"][4].endswith("0, -1)") and "--prune" in RELEASED["script/replica.sh"]
    assert (official.prune, official.final_prune, official.prune_unseen) == ("after_split", False, True)
    paper = RefineParams()
    assert (paper.statistic, paper.gamma, paper.ambiguity_threshold, paper.scale_divisor) == ("weights", 0.8, 0.5, 2.0)
    assert (paper.prune, paper.final_prune, paper.prune_unseen) == ("next_detection", True, False)
    with pytest.raises(ValueError, match="prune"):
        RefineParams(prune="never")
    with pytest.raises(ValueError, match="final_prune"):
        RefineParams(prune="after_split")  # the paper preset's final_prune needs next_detection
    assert RefineParams(preset="official", scale_divisor=3.0).scale_divisor == 3.0  # a key overrides the preset
    merge = MergeParams(preset="official")
    assert merge.threshold == _released("merge_patches.py", "miou_th") and MergeParams().threshold == 0.5
    # a Gaussian votes in more than ct_th + 1 views (at least ct_th + 2), ct_th = val_views // MAX_VIEWS + 1,
    # which is 1 for any number of voting views below MAX_VIEWS
    max_views = int(_released("conf/con_masks_conf.py", "MAX_VIEWS"))
    ct_th = (max_views - 1) // max_views + 1
    assert "> ct_th+1" in RELEASED["utils/con_mask_utils.py"][3]
    assert (merge.min_gaussians, merge.min_view_share, merge.min_views, merge.min_gaussian_views) == (
        _released("utils/con_mask_utils.py", "GAUS_NUM_TH"), _released("utils/con_mask_utils.py", "vf_th"),
        _released("utils/con_mask_utils.py", "val_views <"), ct_th + 2)
    assert TraceParams(preset="official").statistic == "pixels" and TraceParams().statistic == "weights"
    from trace3d.params import from_mapping

    with pytest.raises(ConfigError, match="gama"):
        from_mapping(RefineParams, {"gama": 0.7}, "refine params")


def test_git_strategy_splits_then_prunes_children_that_stay_ambiguous():
    from trace3d.training import GaussianOptimizer, TrainParams, learning_rates

    model, _, cameras = two_objects()
    straddler = grid_model(-0.15, 0.15, -0.15, 0.15, 1.9, step=0.3)
    straddler.opacity_logits[:] = 0.0
    scene = with_generation(concat(model, straddler))
    maps = [np.where(pixel_x_world(c) < 0.0, 1, 2) for c in cameras]
    params = RefineParams(iterations=3, detect_at=[1, 2], schedule_scale=1.0)
    strategy = GITStrategy(cameras, maps, params, torch.Generator().manual_seed(0))
    state = GaussianOptimizer(scene, learning_rates(TrainParams(), 1.0), TrainParams(), 1.0)
    strategy.initialize(state, {})
    n = len(scene)
    event = strategy.after_step(1, state)
    assert event["git_split"] >= 1 and event["git_pruned"] == 0
    assert len(state) == n + event["git_split"]  # each split replaces one parent by two children
    assert int((state.model.extras[GENERATION] == 1).sum()) == 2 * event["git_split"]
    # children that are still ambiguous at the next detection are removed, not split again
    ambiguous = torch.from_numpy(strategy.detect(state.model))
    children = state.model.extras[GENERATION] > 0
    expected_pruned = int((ambiguous & children).sum())
    assert expected_pruned >= 1
    before = len(state)
    event2 = strategy.after_step(2, state)
    assert event2["git_pruned"] == expected_pruned
    assert event2["git_split"] == int((ambiguous & ~children).sum())
    assert len(state) == before - expected_pruned + event2["git_split"]
    assert (state.model.extras[GENERATION] <= 1).all()
    assert strategy.after_step(3, state) is None  # not a detection iteration


def test_after_split_pruning_removes_what_stays_ambiguous_and_unseen_gaussians_go():
    """The released code's pruning (official preset): at a detection every ambiguous Gaussian is split
    and whatever is still ambiguous right after is removed; at iteration 1 Gaussians no view sees go."""
    from trace3d.training import GaussianOptimizer, TrainParams, learning_rates

    model, _, cameras = two_objects()
    straddler = grid_model(-0.15, 0.15, -0.15, 0.15, 1.9, step=0.3)
    straddler.opacity_logits[:] = 0.0
    hidden = grid_model(40.0, 40.3, 40.0, 40.3, 2.0, step=0.3)  # far outside every view
    scene = with_generation(concat(concat(model, straddler), hidden))
    n_hidden = len(hidden)
    maps = [np.where(pixel_x_world(c) < 0.0, 1, 2) for c in cameras]
    params = RefineParams(iterations=3, detect_at=[1, 2], schedule_scale=1.0, prune="after_split",
                          final_prune=False, prune_unseen=True)
    strategy = GITStrategy(cameras, maps, params, torch.Generator().manual_seed(0))
    assert strategy.unseen(scene)[-n_hidden:].all() and not strategy.unseen(scene)[: len(model)].any()
    state = GaussianOptimizer(scene, learning_rates(TrainParams(), 1.0), TrainParams(), 1.0)
    strategy.initialize(state, {})
    ambiguous_before = int(strategy.detect(scene).sum())
    assert ambiguous_before >= 1
    # what the round should remove: the same split (same seed) replayed by hand, then detected
    replay = GITStrategy(cameras, maps, params, torch.Generator().manual_seed(0))
    state_r = GaussianOptimizer(scene.subset(~torch.from_numpy(replay.unseen(scene))),
                                learning_rates(TrainParams(), 1.0), TrainParams(), 1.0)
    replay._split(state_r, torch.from_numpy(replay.detect(state_r.model)), torch.zeros(len(state_r), dtype=torch.bool))
    still = replay.detect(state_r.model)
    assert still.any() and (state_r.model.extras[GENERATION].numpy()[still] == 1).any()

    event = strategy.after_step(1, state)
    assert strategy.rounds[-1]["unseen_pruned"] == n_hidden and event["git_unseen_pruned"] == n_hidden
    assert event["git_ambiguous"] == ambiguous_before and event["git_split"] == ambiguous_before
    assert event["git_pruned"] == int(still.sum())  # every Gaussian still ambiguous after the split goes
    torch.testing.assert_close(state.model.means, state_r.model.means[torch.from_numpy(~still)])
    assert len(state) == len(scene) - n_hidden + event["git_split"] - event["git_pruned"]
    assert not strategy.unseen(state.model).any()
    # the paper's pruning on the same scene keeps the children until the next detection
    paper = GITStrategy(cameras, maps, RefineParams(iterations=3, detect_at=[1, 2], schedule_scale=1.0),
                        torch.Generator().manual_seed(0))
    state2 = GaussianOptimizer(scene, learning_rates(TrainParams(), 1.0), TrainParams(), 1.0)
    event2 = paper.after_step(1, state2)
    assert event2["git_pruned"] == 0 and len(state2) == len(scene) + event2["git_split"]


def test_boundary_band_marks_both_sides():
    truth = np.array([[1, 1, 1, 2, 2, 2, 2]])
    band = boundary_band(truth, width=1)
    np.testing.assert_array_equal(band[0], [False, True, True, True, True, False, False])


# ----------------------------------------------------------------------------------------------
# The steps on a tiny synthetic room (deterministic, preset files, bad input)
# ----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny_fitted(tmp_path_factory):
    from trace3d.cli import main

    root = tmp_path_factory.mktemp("tiny")
    synthetic = json.dumps({"seed": 4, "width": 48, "height": 36, "num_views": 8, "test_every": 4,
                            "num_objects": 8, "supersample": 1})
    train = json.dumps({"schedule_scale": 1.0, "iterations": 60, "densify_from": 10, "densify_until": 40,
                        "densify_interval": 10, "sh_degree": 1, "sh_degree_interval": 30, "device": "cpu",
                        "max_gaussians": 4000})
    assert main(["scene", "synthetic", "--out", str(root / "scene"), "--params", synthetic]) == 0
    assert main(["poses", "--scene", str(root / "scene"), "--out", str(root / "poses"), "--params", "{mode: dataset}"]) == 0
    assert main(["masks", "--scene", str(root / "scene"), "--out", str(root / "masks")]) == 0
    assert main(["patches", "--scene", str(root / "scene"), "--masks", str(root / "masks"), "--out", str(root / "patches")]) == 0
    assert main(["gaussians", "--scene", str(root / "scene"), "--poses", str(root / "poses"), "--out",
                 str(root / "gaussians"), "--params", train]) == 0
    return root


def test_steps_are_deterministic_and_write_their_files(tiny_fitted, tmp_path):
    from trace3d.cli import main

    root = tiny_fitted
    common = ["--scene", str(root / "scene")]
    for run in ("a", "b"):
        assert main(["trace", *common, "--poses", str(root / "poses"), "--gaussians", str(root / "gaussians"),
                     "--labels", str(root / "patches"), "--out", str(tmp_path / run / "trace")]) == 0
        assert main(["merge", *common, "--git", str(tmp_path / run / "trace"), "--patches", str(root / "patches"),
                     "--out", str(tmp_path / run / "merge")]) == 0
        assert main(["refine", *common, "--poses", str(root / "poses"), "--gaussians", str(root / "gaussians"),
                     "--labels", str(tmp_path / run / "merge" / "instances"), "--out", str(tmp_path / run / "refine"),
                     "--params", json.dumps({"iterations": 30, "detect_at": [1, 10, 20], "schedule_scale": 1.0,
                                             "highlight_views": 1})]) == 0
    a, b = tmp_path / "a", tmp_path / "b"
    np.testing.assert_array_equal(np.load(a / "trace" / "git.npz")["label"], np.load(b / "trace" / "git.npz")["label"])
    merge_a, merge_b = (json.loads((d / "merge" / "merge.json").read_text()) for d in (a, b))
    merge_a.pop("seconds"), merge_b.pop("seconds")
    assert merge_a == merge_b
    for name in sorted(p.name for p in (a / "merge" / "instances").iterdir()):
        assert (a / "merge" / "instances" / name).read_bytes() == (b / "merge" / "instances" / name).read_bytes()
    refine_a, refine_b = (json.loads((d / "refine" / "refine.json").read_text()) for d in (a, b))
    for key in ("rounds", "gaussians_after", "test_psnr_after", "split", "pruned"):
        if key == "rounds":
            for ra, rb in zip(refine_a[key], refine_b[key]):
                ra.pop("seconds"), rb.pop("seconds")
        assert refine_a[key] == refine_b[key]
    assert (a / "refine" / "point_cloud.ply").read_bytes() == (b / "refine" / "point_cloud.ply").read_bytes()
    for name in ("ambiguous.png", "train.csv"):
        assert (a / "refine" / name).is_file()
    assert "before" in merge_a["ground_truth"] and "boundary" in refine_a
    pairs = merge_a["ground_truth"]["pairs"]  # every should-merge pair is a candidate or out of reach
    assert pairs["should_merge"] == pairs["candidates_should_merge"] + pairs["out_of_reach"]
    assert sum(len(v["pairs_vs_truth"]["out_of_reach_pairs"]) for v in merge_a["per_view"]) == pairs["out_of_reach"]
    assert refine_a["test_psnr_before"] is not None and refine_a["split"] >= refine_a["rounds"][0]["split"]


def test_bench_merge_vote_orders_the_votes(tiny_fitted, tmp_path):
    """Per pair, same patch <= Jaccard of the mask sets <= common mask (each view's score is ordered so);
    the classes split the pairs; the pooled figures are the one room's."""
    from trace3d.bench.merge_vote import room_pairs, run_bench
    from trace3d.cli import main

    root, room = tiny_fitted, tmp_path / "room"
    room.mkdir()
    for name in ("scene", "patches"):
        (room / name).symlink_to(root / name)
    assert main(["trace", "--scene", str(root / "scene"), "--poses", str(root / "poses"), "--gaussians",
                 str(root / "gaussians"), "--labels", str(root / "patches"), "--out", str(room / "trace-paper")]) == 0
    pairs = room_pairs(room)
    assert len(pairs["should"]) > 10 and pairs["should"].any()
    assert (pairs["same_patch"] <= pairs["mask_jaccard"] + 1e-12).all()
    assert (pairs["mask_jaccard"] <= pairs["common_mask"] + 1e-12).all()
    assert not (pairs["should"] & pairs["group_mates"]).any() and (pairs["omega"] > 0).all()
    result = run_bench([room])
    assert result["pooled"] == result["rooms"]["room"]
    assert result["pooled"]["pairs"] == len(pairs["should"])


def test_merge_refuses_a_stale_trace(tiny_fitted, tmp_path):
    from trace3d.cli import main

    root = tiny_fitted
    assert main(["trace", "--scene", str(root / "scene"), "--poses", str(root / "poses"), "--gaussians",
                 str(root / "gaussians"), "--labels", str(root / "patches"), "--out", str(tmp_path / "trace")]) == 0
    stats = GITStats.load(tmp_path / "trace" / "git.npz")
    stats.num_labels[:] = 1
    stats.save(tmp_path / "trace" / "git.npz")
    assert main(["merge", "--scene", str(root / "scene"), "--git", str(tmp_path / "trace"), "--patches",
                 str(root / "patches"), "--out", str(tmp_path / "merge")]) == 2
    assert not (tmp_path / "merge").exists()
    assert main(["trace", "--scene", str(root / "scene"), "--gaussians", str(tmp_path / "nothing"),
                 "--labels", str(root / "patches"), "--out", str(tmp_path / "t2")]) == 2


@pytest.mark.parametrize("block", [1, 4, 1 << 26])
def test_all_source_histograms_equal_the_per_view_kernel(monkeypatch, block):
    import trace3d.tracing.merge as merge

    monkeypatch.setattr(merge, "HISTOGRAM_BLOCK", block * 4 * 6 * 4)  # `block` source views at a time
    rng = np.random.default_rng(5)
    labels = rng.integers(-1, 4, size=(60, 6)).astype(np.int32)
    visible = rng.random((60, 6)) > 0.3
    every = list(merge.all_source_histograms(labels, visible, 4, 4))
    assert len(every) == 6
    for v0 in range(6):
        np.testing.assert_array_equal(every[v0], source_histograms(labels, visible, v0, 4, 4))
