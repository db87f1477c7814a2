"""``trace3d extract``: one object out by a click on a contrastively lifted tiny room (lifted from the
exact object masks), its PLY read back by the project's reader and by a generic PLY parse, its renders
against the object's ground truth, and bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from trace3d.cli import main as cli_main
from trace3d.evaluation.extraction import render_alone
from trace3d.extract import ExtractParams, grow_from_click
from trace3d.gaussians import GaussianModel
from trace3d.lifting.query import deepest_pixel, iou
from trace3d.scene import Scene

from tests.lifted_room import oracle_room

pytestmark = pytest.mark.usefixtures("single_numba_thread")


@pytest.fixture(scope="module")
def lifted_room(tmp_path_factory):
    """A tiny room, Gaussians on its ground-truth depth (no fit), features lifted contrastively from
    the exact object-level instance maps."""
    from trace3d.lifting.step import run_lift

    root = tmp_path_factory.mktemp("extract")
    scene = oracle_room(root, {"seed": 3, "width": 64, "height": 48, "num_views": 8, "test_every": 4, "num_objects": 14,
                               "supersample": 1}, init_views="train")
    (root / "lift").mkdir()
    run_lift(scene, None, root / "gaussians", root / "labels", root / "lift",
             {"method": "contrastive", "preset": "paper", "lr": 0.05, "iterations": 300, "pixels": 512, "pool_pixels": 1024,
              "pca_views": 1}, progress=False)
    return root


def _objects_in_view(scene, cam, min_pixels=200):
    """Object-level ids of furniture (not walls, floor or ceiling) with at least ``min_pixels`` pixels in
    ``cam``, largest first, and the view's object-level map."""
    objects = scene.objects.lookup("object")[scene.instances(cam.name)]
    out = []
    for oid in np.unique(objects[objects > 0]):
        if scene.objects.by_id[int(oid)].category in ("wall", "floor", "ceiling"):
            continue
        if (objects == oid).sum() >= min_pixels:
            out.append((int((objects == oid).sum()), int(oid)))
    return [oid for _, oid in sorted(out, reverse=True)], objects


def _render_iou(scene, model, object_id):
    """Mean over the views (training and test) where the object shows >= 30 pixels: IoU of the extracted
    Gaussians' render (alpha > 0.5) with the object's ground-truth mask."""
    lookup = scene.objects.lookup("object")
    ious, stray = [], 0
    for cam in scene.cameras:
        truth = lookup[scene.instances(cam.name)] == object_id
        _, alpha = render_alone(model, cam)
        if truth.sum() >= 30:
            ious.append(iou(alpha > 0.5, truth))
        stray += int(((alpha > 0.5) & ~truth).sum())
    return float(np.mean(ious)), len(ious), stray


PLY_NAMES_DC = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
PLY_NAMES_TAIL = ["opacity", "scale_0", "scale_1", "rot_0", "rot_1", "rot_2", "rot_3"]


def parse_ply_generic(path):
    """A plyfile-style parse written here: the header's element and typed properties, then the binary body."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    lines = data[:end].decode("ascii").splitlines()
    assert lines[0] == "ply" and lines[1] == "format binary_little_endian 1.0" and lines[-1] == "end_header"
    elements = [line.split() for line in lines if line.startswith("element")]
    assert len(elements) == 1 and elements[0][1] == "vertex"
    count = int(elements[0][2])
    props = [line.split() for line in lines if line.startswith("property")]
    types = {"float": "<f4", "float32": "<f4", "double": "<f8", "uchar": "u1", "int": "<i4"}
    dtype = np.dtype([(name, types[kind]) for _, kind, name in props])
    assert len(data) - end == count * dtype.itemsize
    return [name for _, _, name in props], np.frombuffer(data, dtype=dtype, count=count, offset=end)


def test_click_extracts_the_object(lifted_room, tmp_path):
    root = lifted_room
    scene = Scene.read(root / "scene")
    model = GaussianModel.read_ply(root / "gaussians" / "point_cloud.ply")
    cam = next(c for c in scene.train_cameras if len(_objects_in_view(scene, c)[0]) >= 2)
    candidates, objects = _objects_in_view(scene, cam)
    results = {}
    for oid in candidates[:2]:
        x, y = deepest_pixel(objects == oid)
        out = tmp_path / f"obj{oid}"
        assert cli_main(["extract", "--scene", str(root / "scene"), "--gaussians", str(root / "gaussians"), "--lift",
                         str(root / "lift"), "--view", cam.name, "--point", f"{x},{y}", "--out", str(out),
                         "--params", "{picture_views: 3, turntable_views: 2, turntable_size: 32}"]) == 0
        info = json.loads((out / "extract.json").read_text())
        assert info["view"] == cam.name and info["point"] == [x, y]
        # the project's reader and a generic parse give the same Gaussians, in the reference writers' order
        obj = GaussianModel.read_ply(out / "object.ply")
        assert len(obj) == info["gaussians"] > 0
        names, body = parse_ply_generic(out / "object.ply")
        rest = [n for n in names if n.startswith("f_rest_")]
        assert names[: len(PLY_NAMES_DC)] == PLY_NAMES_DC
        assert names[len(PLY_NAMES_DC): len(PLY_NAMES_DC) + len(rest)] == [f"f_rest_{i}" for i in range(len(rest))]
        assert names[len(PLY_NAMES_DC) + len(rest): len(PLY_NAMES_DC) + len(rest) + 7] == PLY_NAMES_TAIL
        np.testing.assert_array_equal(np.stack([body["x"], body["y"], body["z"]], 1), obj.means.numpy())
        np.testing.assert_array_equal(body["opacity"], obj.opacity_logits.numpy())
        np.testing.assert_array_equal(np.stack([body[f"rot_{i}"] for i in range(4)], 1), obj.quats.numpy())
        # every Gaussian of the PLY is one of the scene's
        full = {tuple(row) for row in model.means.numpy().tolist()}
        assert all(tuple(row) in full for row in obj.means.numpy().tolist())
        for picture in ("object.png", "turntable.png"):
            assert (out / picture).stat().st_size > 200
        score, views, stray = _render_iou(scene, obj, oid)
        other = [o for o in candidates[:2] if o != oid][0]
        results[oid] = (score, views, _render_iou(scene, obj, other)[0], stray, info)
    for score, views, other_score, stray, _info in results.values():
        # measured 2026-11-27 (room seed 3, view_000): sideboard 0.88 over its 3 views, TV 0.92 over its 1 view
        assert views >= 1 and score > 0.8, results
        assert other_score < 0.1, results  # the other object's ground truth is not what came out
        assert stray < 150, results  # rendered pixels off the object over all 8 views: 61 and 9 measured


def test_grown_region_is_the_objects_plateau():
    """On a hand-made feature map (two flat objects and a background, blurred borders), the click grows
    into exactly its object, whichever object it is on."""
    h, w = 40, 60
    fmap = np.zeros((h, w, 3), np.float32)
    truth = np.zeros((h, w), np.int64)
    truth[5:20, 5:25] = 1
    truth[22:35, 30:55] = 2
    fmap[truth == 1] = [3.0, 0.0, 0.0]
    fmap[truth == 2] = [0.0, 2.0, 1.0]
    rng = np.random.default_rng(0)
    fmap += rng.normal(0, 0.05, fmap.shape).astype(np.float32)
    import cv2

    fmap = cv2.GaussianBlur(fmap, (3, 3), 0.7)
    for oid, (x, y) in ((1, (10, 10)), (2, (40, 30))):
        region = grow_from_click(np.ascontiguousarray(fmap), x, y)
        assert iou(region.mask, truth == oid) > 0.9
        assert region.areas[-1] == h * w  # the largest threshold swallows the view, and was not chosen
    with pytest.raises(Exception, match="outside"):
        grow_from_click(fmap, 60, 0)
    with pytest.raises(Exception, match="threshold_steps"):
        ExtractParams(threshold_steps=2)


def test_extract_bad_input(lifted_room, tmp_path, capsys):
    root = lifted_room
    scene = Scene.read(root / "scene")
    base = ["extract", "--scene", str(root / "scene"), "--gaussians", str(root / "gaussians"), "--lift",
            str(root / "lift")]
    train, test = scene.train_cameras[0].name, scene.test_cameras[0].name
    cases = [
        (["--view", test, "--point", "3,3"], "not a training view"),
        (["--view", train, "--point", "3"], "two numbers"),
        (["--view", train, "--point", "500,3"], "outside"),
        (["--point", "3,3"], "name the clicked training view"),
        (["--view", train, "--point", "3,3", "--params", "{treshold_steps: 3}"], "unknown parameter"),
    ]
    for k, (extra, message) in enumerate(cases):
        out = tmp_path / f"o{k}"
        assert cli_main(base + extra + ["--out", str(out)]) == 2
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1, err
        assert not out.exists()
    # a lift that is not contrastive (no features to click on)
    (tmp_path / "labels_lift").mkdir()
    (tmp_path / "labels_lift" / "lift.json").write_text(json.dumps({"method": "self_prompt", "params": {}}))
    assert cli_main(base[:-1] + [str(tmp_path / "labels_lift"), "--view", train, "--point", "3,3", "--out",
                                 str(tmp_path / "x")]) == 2
    assert "contrastive" in capsys.readouterr().err


def test_connected_to_seeds_drops_far_pieces():
    """Two point clusters 5 spacings apart: the seeds' cluster is kept whole, the other dropped; a chain
    of links joins pieces that are each within reach."""
    from trace3d.extract import connected_to_seeds

    grid = np.stack(np.meshgrid(np.arange(6.0), np.arange(6.0), [0.0]), -1).reshape(-1, 3)
    far = grid + [10.0, 0.0, 0.0]
    means = np.concatenate([grid, far])
    seeds = np.zeros(len(means), bool)
    seeds[3] = True
    kept = connected_to_seeds(means, seeds, link_scale=3.0)  # links < 3: the 5-unit gap is not crossed
    np.testing.assert_array_equal(kept, np.arange(len(means)) < len(grid))
    assert connected_to_seeds(means, seeds, link_scale=6.0).all()  # a reach of 6 crosses the gap
    assert not connected_to_seeds(means, np.zeros(len(means), bool), 3.0).any()


def test_other_selections_and_the_segment_step(lifted_room, tmp_path):
    """The same click with ``selection: segment`` and ``region`` (the 2D region growing of before), and
    ``trace3d segment`` on the room: its objects, stuff (walls, floor) and dropped segments account for
    every Gaussian, and the clicked object's segment is what ``selection: segment`` returns."""
    root = lifted_room
    scene = Scene.read(root / "scene")
    cam = next(c for c in scene.train_cameras if len(_objects_in_view(scene, c)[0]) >= 2)
    candidates, objects = _objects_in_view(scene, cam)
    x, y = deepest_pixel(objects == candidates[0])
    base = ["extract", "--scene", str(root / "scene"), "--gaussians", str(root / "gaussians"), "--lift",
            str(root / "lift"), "--view", cam.name, "--point", f"{x},{y}"]
    got = {}
    for selection in ("segment", "region"):
        out = tmp_path / selection
        assert cli_main(base + ["--out", str(out), "--params",
                                f"{{selection: {selection}, picture_views: 1, turntable_views: 0}}"]) == 0
        info = json.loads((out / "extract.json").read_text())
        assert info["selection"] == selection and info["gaussians"] > 0
        got[selection] = GaussianModel.read_ply(out / "object.ply")
        score, views, _ = _render_iou(scene, got[selection], candidates[0])
        assert views >= 1 and score > 0.6, (selection, score)
    seg_out = tmp_path / "segmented"  # not the extract output of the same name above
    assert cli_main(["segment", "--scene", str(root / "scene"), "--gaussians", str(root / "gaussians"), "--lift",
                     str(root / "lift"), "--out", str(seg_out), "--params",
                     "{turntable_views: 2, turntable_size: 24}"]) == 0
    info = json.loads((seg_out / "segment.json").read_text())
    assert info["params"]["method"] == "graph" and info["threshold"] > 0
    assert len(info["objects"]) >= 2 and len(info["stuff"]) >= 1  # furniture, and walls / floor as stuff
    total = sum(e["gaussians"] for e in info["objects"] + info["stuff"] + info["dropped"])
    assert total + info["unclustered_gaussians"] == info["gaussians_total"]
    for entry in info["objects"]:
        assert len(GaussianModel.read_ply(seg_out / "objects" / f"{entry['id']}.ply")) == entry["gaussians"]
    for entry in info["stuff"]:
        assert len(GaussianModel.read_ply(seg_out / "stuff" / f"{entry['id']}.ply")) == entry["gaussians"]
    # the segment the click selected is one of the step's objects, Gaussian for Gaussian
    sizes = {e["gaussians"] for e in info["objects"] + info["stuff"]}
    assert len(got["segment"]) in sizes
