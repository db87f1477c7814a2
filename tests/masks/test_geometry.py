"""The ``geometry`` mask source: nested masks from the fitted scene's depth and normals with colour
(reads no ground truth); its cues and merging against loop twins, a toy scene whose answer is known,
and the masks step on a tiny scene without ground truth."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from trace3d.cli import main as cli_main
from trace3d.masks import FITTED_SOURCES, parse_params, read_mask_npz
from trace3d.masks.geometry import (
    GeometryParams,
    _agglomerate_reference,
    _pixel_pairs_reference,
    agglomerate,
    back_project,
    dominant_planes,
    geometry_hierarchy,
    geometry_view_masks,
    pixel_pairs,
    superpixels,
)
from trace3d.scene import Scene

pytestmark = pytest.mark.usefixtures("single_numba_thread")

W, H = 80, 64
K = np.array([[60.0, 0.0, W / 2], [0.0, 60.0, 16.0], [0.0, 0.0, 1.0]])  # looking slightly down
BOX = {"x": (-0.6, 0.6), "front": 3.0, "back": 4.5, "top": 0.5}  # a box standing on the floor
FLOOR_Y, WALL_Z = 1.5, 20.0  # camera-space y grows downwards: the floor lies 1.5 below the camera


def toy_view():
    """A box on a floor before a wall, ray-cast from a camera at the origin (looking along +z): depth [H, W],
    unit normals facing the camera [H, W, 3], and the part each pixel sees [H, W] (0 floor, 1 wall,
    2 box front, 3 box top). Everything has one grey colour, so only the geometry can separate it."""
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=2)
    best = np.full((H, W), np.inf)
    part = np.full((H, W), -1)
    normals = {0: (0, -1, 0), 1: (0, 0, -1), 2: (0, 0, -1), 3: (0, -1, 0)}

    def hit(t, ok, label):
        closer = ok & (t > 0) & (t < best)
        best[closer] = t[closer]
        part[closer] = label

    with np.errstate(divide="ignore", invalid="ignore"):
        t = FLOOR_Y / rays[..., 1]
        hit(t, rays[..., 1] > 0, 0)
        hit(np.full((H, W), WALL_Z), np.ones((H, W), bool), 1)
        x, y = rays[..., 0] * BOX["front"], rays[..., 1] * BOX["front"]
        hit(np.full((H, W), BOX["front"]), (x >= BOX["x"][0]) & (x <= BOX["x"][1]) & (y >= BOX["top"]) & (y <= FLOOR_Y), 2)
        t = BOX["top"] / rays[..., 1]
        x, z = rays[..., 0] * t, t
        hit(t, (rays[..., 1] > 0) & (x >= BOX["x"][0]) & (x <= BOX["x"][1]) & (z >= BOX["front"]) & (z <= BOX["back"]), 3)
    depth = best  # the rays have z = 1, so t is the depth
    normal = np.array([normals[p] for p in part.ravel()], np.float64).reshape(H, W, 3)
    return depth, normal, part


def _nested_or_disjoint(masks: np.ndarray) -> bool:
    flat = masks.reshape(len(masks), -1)
    for i in range(len(flat)):
        for j in range(i + 1, len(flat)):
            inter = (flat[i] & flat[j]).sum()
            if inter and inter not in (flat[i].sum(), flat[j].sum()):
                return False
    return True


def test_toy_scene_box_floor_and_wall_come_apart_by_geometry_alone():
    depth, normal, part = toy_view()
    assert set(np.unique(part)) == {0, 1, 2, 3}
    image = np.full((H, W, 3), 128, np.uint8)
    alpha = np.ones((H, W))
    params = GeometryParams()
    masks, scores = geometry_view_masks(image, depth, normal, alpha, K, params)
    assert masks.dtype == bool and masks.shape[1:] == (H, W) and np.all(scores == 1.0)
    assert _nested_or_disjoint(masks)

    def best_iou(region):
        inter = (masks & region).sum(axis=(1, 2))
        return float((inter / (masks.sum(axis=(1, 2)) + region.sum() - inter)).max())

    box = (part == 2) | (part == 3)
    # the box (front and top joined across their convex edge) is one mask, and so are the floor and the wall
    assert best_iou(box) > 0.9  # 0.95 measured: the borders move by a pixel where strips dissolve
    assert best_iou(part == 0) > 0.95 and best_iou(part == 1) > 0.95
    # below the coarsest level, the box's region holds none of the floor (a concave contact) or the wall (a
    # depth edge) but for a pixel's width along its outline
    hierarchy, _ = geometry_hierarchy(image, depth, normal, alpha, K, params)
    for labels in hierarchy[:-1]:
        box_label = np.bincount(labels[box]).argmax()
        for region in (part == 0, part == 1):
            assert (labels[region] == box_label).sum() < 0.1 * box.sum()
    # the colour alone (every pixel grey) separates nothing: the graph source has no edge to follow
    from trace3d.masks.graph import GraphParams, graph_view_masks

    assert len(graph_view_masks(image, GraphParams())[0]) == 0


def test_finest_level_leaves_the_finest_regions_out():
    """finest_level 1: the masks are the coarser levels' regions only, each one of the full set's masks."""
    depth, normal, part = toy_view()
    rng = np.random.default_rng(0)
    image = np.clip(128 + rng.normal(0, 25, (H, W, 1)) * np.ones((1, 1, 3)), 0, 255).astype(np.uint8)  # speckle
    alpha = np.ones((H, W))
    full, _ = geometry_view_masks(image, depth, normal, alpha, K, GeometryParams())
    coarse, _ = geometry_view_masks(image, depth, normal, alpha, K, GeometryParams(finest_level=1))
    hierarchy, _ = geometry_hierarchy(image, depth, normal, alpha, K, GeometryParams())
    assert 0 < len(coarse) < len(full)
    flat = full.reshape(len(full), -1)
    for mask in coarse:  # every coarse mask is one of the full set's
        assert (flat == mask.ravel()).all(axis=1).any()
    # the finest level's own regions (those equal to no coarser level's region) are gone
    finest_only = [r for r in np.unique(hierarchy[0])
                   if not any(((hierarchy[k] == np.bincount(hierarchy[k][hierarchy[0] == r]).argmax())
                               == (hierarchy[0] == r)).all() for k in range(1, len(hierarchy)))]
    assert finest_only
    for r in finest_only:
        assert not (coarse.reshape(len(coarse), -1) == (hierarchy[0] == r).ravel()).all(axis=1).any()
    with pytest.raises(ValueError, match="finest_level"):
        GeometryParams(finest_level=3)


def test_pixel_cues_match_the_loop_twin_and_read_planes_steps_and_creases():
    depth, normal, part = toy_view()
    rng = np.random.default_rng(0)
    lab = rng.normal(50, 10, (H, W, 3))
    alpha = np.ones((H, W))
    alpha[0, :3] = 0.2  # a few empty pixels
    params = GeometryParams(normal_smooth=0)
    fast, slow = pixel_pairs(lab, depth, normal, alpha, K, params), _pixel_pairs_reference(lab, depth, normal, alpha, K, params)
    for name in ("a", "b", "depth_edge", "concave"):
        np.testing.assert_array_equal(getattr(fast, name), getattr(slow, name), err_msg=name)
    for name in ("crease", "crease_near", "colour"):
        np.testing.assert_allclose(getattr(fast, name), getattr(slow, name), rtol=1e-9, atol=1e-9, err_msg=name)
    labelled = np.where(alpha < params.min_alpha, -1, part).ravel()  # empty pixels: a part of their own
    pa, pb = labelled[fast.a], labelled[fast.b]
    empty = (alpha < params.min_alpha).ravel()
    solid = ~empty[fast.a] & ~empty[fast.b]
    # within one plane (the slanted floor included): no depth edge, no crease
    same = (pa == pb) & solid
    far = same.copy()  # depth edges and creases show only within a few pixels of another part
    far_from_edge = np.ones(H * W, bool)
    for idx in np.nonzero(pa != pb)[0]:
        for p in (fast.a[idx], fast.b[idx]):
            y, x = divmod(int(p), W)
            far_from_edge.reshape(H, W)[max(y - 2, 0):y + 3, max(x - 2, 0):x + 3] = False
    far &= far_from_edge[fast.a] & far_from_edge[fast.b]
    assert far.sum() > 500 and fast.crease[far].max() < 1e-9 and not fast.depth_edge[far].any()
    # the box's top above the wall and its front before the wall: depth edges; empty pixels: depth edges
    assert fast.depth_edge[((pa == 1) & (pb >= 2)) | ((pa >= 2) & (pb == 1))].all()
    assert fast.depth_edge[~solid].all()
    # the box front meeting the floor: a concave 90-degree crease, not a depth edge; front to top: convex
    # (beside the box the floor lies farther back: those horizontal pairs are depth edges)
    vertical = fast.b - fast.a == W
    contact = vertical & (pa == 2) & (pb == 0)
    beside = ~vertical & (((pa == 2) & (pb == 0)) | ((pa == 0) & (pb == 2)))
    flat_depth = depth.ravel()
    gap = 1 - np.minimum(flat_depth[fast.a], flat_depth[fast.b]) / np.maximum(flat_depth[fast.a], flat_depth[fast.b])
    assert (beside & (gap > 0.6)).sum() >= 4 and (beside & (gap < 0.4)).sum() >= 4
    assert fast.depth_edge[beside & (gap > 0.6)].all() and not fast.depth_edge[beside & (gap < 0.4)].any()
    assert contact.sum() >= 10 and not fast.depth_edge[contact].any()
    assert fast.concave[contact].all() and np.allclose(fast.crease[contact], np.pi / 2)
    edge = vertical & (pa == 3) & (pb == 2)
    assert edge.sum() >= 10 and not fast.concave[edge].any() and np.allclose(fast.crease[edge], np.pi / 2)


def test_agglomeration_matches_the_brute_force_twin():
    rng = np.random.default_rng(1)
    depth, normal, part = toy_view()
    crop = (slice(16, 48), slice(20, 60))  # the box and some floor and wall, 32 x 40 (the brute force is slow)
    depth, normal, part = depth[crop], normal[crop], part[crop]
    Kc = K.copy()
    Kc[0, 2] -= 20
    Kc[1, 2] -= 16
    h, w = depth.shape
    # blocks of distinct colours (no two regions tie exactly in cost) that split the parts
    image = np.repeat(np.repeat(rng.integers(60, 200, (h // 8 + 1, w // 8 + 1, 3)), 8, 0), 8, 1)[:h, :w].astype(np.uint8)
    noise = rng.normal(0.0, 0.5, (h, w, 3))  # on the colours the merge reads: no two pieces of a block alike
    alpha = np.ones((h, w))
    alpha[:2, :4] = 0.0
    from skimage.color import rgb2lab

    # (thresholds away from the costs the toy's exact right angles give, 1.0 for a convex edge: there the two
    # twins' sums in another order may fall either side)
    for params in (GeometryParams(thresholds=[1.1, 2.3, 4.7, 9.1]),
                   GeometryParams(thresholds=[0.2, 0.6, 3.1], colour_weight=2.0, small_area=0.01, max_planes=3)):
        lab = rgb2lab(image) + noise
        pairs = pixel_pairs(lab, depth, normal, alpha, Kc, params)
        empty = alpha < params.min_alpha
        labels = superpixels(image, pairs, empty, params)
        assert 5 <= labels.max() + 1 <= 120  # a small problem for the brute force
        planes = None
        if params.max_planes:
            planes = dominant_planes(back_project(depth, Kc), ~empty, params, np.random.default_rng(0))
            assert planes.max() >= 1  # floor and wall at least
            assert (planes[part == 0] == planes[part == 0][0]).mean() > 0.95  # the floor is one plane
        fast = agglomerate(labels, lab, pairs, empty, params, planes)
        slow = _agglomerate_reference(labels, lab, pairs, empty, params, planes)
        np.testing.assert_array_equal(fast, slow)
        for k in range(1, len(fast)):  # nested: every finer region inside one coarser region
            pairs_k = np.unique(fast[k - 1].astype(np.int64) * (fast.max() + 1) + fast[k])
            assert len(pairs_k) == len(np.unique(fast[k - 1]))


def test_params_are_checked():
    assert isinstance(parse_params("geometry", None), GeometryParams)
    for bad in ({"thresholds": [1.0, 2.0]}, {"thresholds": [2.0, 1.0, 3.0]}, {"depth_edge": 0}, {"max_area": 0.001},
                {"min_alpha": 1.5}):
        with pytest.raises(ValueError):
            GeometryParams(**bad)
    assert FITTED_SOURCES == ("geometry",)
    from trace3d import steps

    assert steps.FITTED_MASK_SOURCES == FITTED_SOURCES


@pytest.fixture(scope="module")
def photos_and_fit(tmp_path_factory):
    """A tiny room as a user's capture (no instances, depth or objects) and Gaussians on its depth taken before
    that depth was removed (standing in for a 2DGS fit)."""
    from trace3d.datasets.synthetic.params import SyntheticParams
    from trace3d.datasets.synthetic.writer import generate_scene
    from trace3d.gaussians import init_from_depth

    root = tmp_path_factory.mktemp("geometry")
    generate_scene(root / "room", SyntheticParams(seed=5, width=64, height=48, num_views=4, test_every=4, supersample=1))
    room = Scene.read(root / "room")
    model = init_from_depth(room, cameras=room.cameras, stride=1, max_points=None, sh_degree=0, opacity=0.95)
    model.log_scales = model.log_scales - 0.3
    (root / "gaussians").mkdir()
    model.write_ply(root / "gaussians" / "point_cloud.ply")
    shutil.copytree(root / "room", root / "photos")
    for extra in ("instances", "depth"):
        shutil.rmtree(root / "photos" / extra, ignore_errors=True)
    (root / "photos" / "objects.json").unlink()
    return root, room


def test_masks_step_on_a_scene_without_ground_truth(photos_and_fit):
    root, room = photos_and_fit
    photos = Scene.read(root / "photos")
    assert not photos.has_instances
    args = ["masks", "--scene", str(root / "photos"), "--source", "geometry", "--gaussians", str(root / "gaussians")]
    assert cli_main(args + ["--out", str(root / "m1")]) == 0
    summary = json.loads((root / "m1" / "masks.json").read_text())
    assert summary["source"] == "geometry" and "ground_truth_check" not in summary
    assert summary["params"]["thresholds"] == GeometryParams().thresholds
    for cam in photos.cameras:
        masks, scores = read_mask_npz(root / "m1" / f"{cam.name}.npz", cam.height, cam.width)
        assert masks.dtype == bool and len(masks) >= 3 and scores.shape == (len(masks),)
        assert _nested_or_disjoint(masks)
    # same inputs, same bytes
    assert cli_main(args + ["--out", str(root / "m2")]) == 0
    for cam in photos.cameras:
        assert (root / "m1" / f"{cam.name}.npz").read_bytes() == (root / "m2" / f"{cam.name}.npz").read_bytes()
    # what it found, against the room's ground truth (which the source never saw): most objects have a mask
    from trace3d.masks.simulate import cross_view_disagreement, object_status

    statuses = [object_status(read_mask_npz(root / "m1" / f"{c.name}.npz", c.height, c.width)[0],
                              room.instances(c.name), room.objects) for c in room.cameras]
    counts = cross_view_disagreement(statuses)["status_counts"]
    assert counts.get("whole", 0) >= 0.6 * sum(counts.values()), counts


def test_bad_input_is_one_sentence(photos_and_fit, tmp_path, capsys):
    root, _ = photos_and_fit
    for args, needle in (
        (["--source", "geometry"], "--gaussians"),
        (["--source", "graph", "--gaussians", str(root / "gaussians")], "reads the images only"),
        (["--source", "geometry", "--gaussians", str(tmp_path)], "point_cloud.ply"),
    ):
        out = tmp_path / "out"
        assert cli_main(["masks", "--scene", str(root / "photos"), "--out", str(out)] + args) == 2
        err = capsys.readouterr().err
        errors = [line for line in err.splitlines() if "error" in line.lower()]
        assert errors and needle in errors[0] and "Traceback" not in err, err
        assert not out.exists()
