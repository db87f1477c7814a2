"""Mask sources: simulated (from ground truth), files, sam; run_masks output format."""

from __future__ import annotations

import json
import sys
import types
from pathlib import Path

import cv2
import numpy as np
import pytest

from trace3d.errors import ConfigError, SceneFormatError, Trace3DError
from trace3d.masks import (
    SimulatedPromptSegmenter,
    SimulateParams,
    cross_view_disagreement,
    frame_rng,
    object_status,
    parse_params,
    read_mask_npz,
    run_masks,
    simulate_view_masks,
)
from trace3d.masks.sam import (
    SamParams,
    _nest_covered_masks_reference,
    check_available,
    filter_small,
    filter_stability,
    nest_covered_masks,
    postprocess,
)
from trace3d.scene import Camera, ObjectTable, Scene, SceneObject, write_cameras, write_frame
from trace3d.io import write_json

H, W = 72, 96

# id: (name, level, parent, category, box (y0, y1, x0, x1) inclusive-exclusive, moves with the view)
_LAYOUT = {
    1: ("wall", "object", None, "wall", (0, 30, 0, W), False),
    2: ("floor", "object", None, "floor", (30, H, 0, W), False),
    11: ("table/top", "part", 10, "table", (36, 42, 20, 60), True),
    12: ("table/leg_l", "part", 10, "table", (42, 62, 22, 28), True),
    13: ("table/leg_r", "part", 10, "table", (42, 62, 52, 58), True),
    20: ("cup", "object", 100, "cup", (28, 36, 30, 38), True),
    21: ("book", "object", 100, "book", (32, 36, 44, 52), True),
    31: ("chair/seat", "part", 30, "chair", (44, 50, 64, 84), True),
    32: ("chair/back", "part", 30, "chair", (26, 44, 78, 84), True),
    40: ("box", "object", None, "box", (52, 66, 4, 16), True),
    41: ("lamp", "object", None, "lamp", (40, 52, 6, 14), True),
    50: ("pen", "object", None, "pen", (64, 66, 34, 50), True),
}
_PARENTS = {
    10: SceneObject(10, "table", "object", 100, "table", True),
    30: SceneObject(30, "chair", "object", None, "chair", True),
    100: SceneObject(100, "table_set", "group", None, "group", True),
}


def tiny_objects(replica_like: bool = False) -> ObjectTable:
    """The hierarchy of the tiny test scene (replica_like: every leaf a parentless object)."""
    objs = []
    for i, (name, level, parent, cat, _, _) in _LAYOUT.items():
        if replica_like:
            objs.append(SceneObject(i, name, "object", None, cat, True))
        else:
            objs.append(SceneObject(i, name, level, parent, cat, True))
    if not replica_like:
        objs.extend(_PARENTS.values())
    return ObjectTable(objs)


def tiny_instance_map(view: int) -> np.ndarray:
    """[H, W] uint16 leaf ids of view ``view``: objects shift right by 2 px per view."""
    out = np.zeros((H, W), dtype=np.uint16)
    for i, (_, _, _, _, (y0, y1, x0, x1), moves) in _LAYOUT.items():
        dx = 2 * view if moves else 0
        out[y0:y1, max(x0 + dx, 0):min(x1 + dx, W)] = i
    return out


def make_scene(root: Path, views: int = 6, replica_like: bool = False, instances: bool = True) -> Scene:
    """Write a tiny canonical scene (rectangles with a part/object/group hierarchy) and read it."""
    rng = np.random.default_rng(0)
    palette = rng.integers(0, 256, size=(65536, 3), dtype=np.uint8)
    cams = []
    for v in range(views):
        name = f"frame_{v:03d}"
        ids = tiny_instance_map(v)
        write_frame(root, name, palette[ids], ids if instances else None)
        w2c = np.eye(4)
        w2c[0, 3] = 0.1 * v
        K = [[80.0, 0, W / 2], [0, 80.0, H / 2], [0, 0, 1]]
        cams.append(Camera(name, "test" if v % 3 == 2 else "train", W, H, K, w2c))
    write_cameras(root, cams)
    write_json(root / "objects.json", tiny_objects(replica_like).to_json())
    return Scene.read(root)


def _object_masks(instance_map: np.ndarray, objects: ObjectTable | None, min_pixels: int) -> set[bytes]:
    lut = objects.lookup("object") if objects is not None else np.arange(instance_map.max() + 1)
    obj = lut[instance_map]
    obj[instance_map == 0] = 0
    out = set()
    for o in np.unique(obj):
        if o and (obj == o).sum() >= min_pixels:
            out.add((obj == o).tobytes())
    return out


# ----------------------------------------------------------------------------------------------
# simulated
# ----------------------------------------------------------------------------------------------


class TestSimulated:
    @pytest.mark.parametrize("replica_like", [False, True])
    def test_inconsistency_zero_gives_ground_truth_objects(self, replica_like):
        objects = tiny_objects(replica_like)
        params = SimulateParams(inconsistency=0.0, seed=3)
        for v in range(6):
            ids = tiny_instance_map(v)
            masks, scores = simulate_view_masks(ids, objects, frame_rng(3, v), params)
            assert masks.dtype == bool and masks.shape[1:] == (H, W)
            got = {m.tobytes() for m in masks}
            assert len(got) == len(masks)
            assert got == _object_masks(ids, objects, params.min_mask_pixels)
            np.testing.assert_array_equal(scores, 1.0)

    def test_without_object_table(self):
        # no objects.json at all: every id is a stand-alone object; groups come from adjacency
        ids = tiny_instance_map(0)
        masks, _ = simulate_view_masks(ids, None, frame_rng(0, 0), SimulateParams(inconsistency=0.0))
        assert {m.tobytes() for m in masks} == _object_masks(ids, None, 16)
        statuses = [
            object_status(simulate_view_masks(tiny_instance_map(v), None, frame_rng(0, v),
                                              SimulateParams(inconsistency=1.0))[0], tiny_instance_map(v), None)
            for v in range(6)
        ]
        assert cross_view_disagreement(statuses)["inconsistent_fraction"] >= 0.5

    def test_ground_truth_objects_are_the_object_level(self):
        # the table's three parts are one mask at inconsistency 0, and the group is not merged
        ids = tiny_instance_map(0)
        masks, _ = simulate_view_masks(ids, tiny_objects(), frame_rng(0, 0), SimulateParams(inconsistency=0.0))
        table = np.isin(ids, [11, 12, 13])
        assert any(np.array_equal(m, table) for m in masks)
        assert not any(np.array_equal(m, ids == 11) for m in masks)
        assert len(masks) == 9

    @pytest.mark.parametrize("replica_like", [False, True])
    def test_inconsistency_one_disagrees_across_views(self, replica_like):
        objects = tiny_objects(replica_like)
        params = SimulateParams(inconsistency=1.0, seed=0)
        statuses = []
        for v in range(8):
            ids = tiny_instance_map(v)
            masks, scores = simulate_view_masks(ids, objects, frame_rng(0, v), params)
            assert np.all((scores > 0.8) & (scores <= 1.0))
            statuses.append(object_status(masks, ids, objects))
        summary = cross_view_disagreement(statuses)
        assert summary["objects"] == (12 if replica_like else 9)
        # measured with seed 0: 0.89 (hierarchical) and 0.75 (replica-like) of objects disagree
        assert summary["inconsistent_fraction"] >= 0.6, summary
        counts = summary["status_counts"]
        assert counts.get("merged", 0) > 0, counts
        assert counts.get("missed", 0) > 0, counts
        if not replica_like:
            assert counts.get("split", 0) > 0, counts

    def test_knob_scales_disagreement(self):
        objects = tiny_objects()
        not_whole = {}
        for inc in (0.0, 0.3, 1.0):
            counts = cross_view_disagreement([
                object_status(simulate_view_masks(tiny_instance_map(v), objects, frame_rng(s, v),
                                                  SimulateParams(inconsistency=inc, seed=s))[0],
                              tiny_instance_map(v), objects)
                for s in range(3) for v in range(6)
            ])["status_counts"]
            not_whole[inc] = 1 - counts.get("whole", 0) / sum(counts.values())
        assert not_whole[0.0] == 0.0 < not_whole[0.3] < not_whole[1.0], not_whole

    def test_zero_inconsistency_statuses_all_whole(self):
        objects = tiny_objects()
        statuses = []
        for v in range(4):
            ids = tiny_instance_map(v)
            masks, _ = simulate_view_masks(ids, objects, frame_rng(0, v), SimulateParams(inconsistency=0.0))
            statuses.append(object_status(masks, ids, objects))
        summary = cross_view_disagreement(statuses)
        assert summary["inconsistent_fraction"] == 0.0
        assert set(summary["status_counts"]) == {"whole"}

    def test_overlapping_granularities_appear(self):
        # at inconsistency 1 some view holds a mask strictly containing another (whole + parts)
        objects = tiny_objects()
        params = SimulateParams(inconsistency=1.0, multi_rate=1.0, seed=1)
        nested = 0
        for v in range(4):
            masks, _ = simulate_view_masks(tiny_instance_map(v), objects, frame_rng(1, v), params)
            flat = masks.reshape(len(masks), -1).astype(np.int32)
            inter = flat @ flat.T
            area = flat.sum(1)
            contained = (inter >= 0.9 * area[:, None]) & (area[:, None] < area[None, :])
            nested += int(contained.sum())
        assert nested > 0

    def test_flat_split_and_boundary_jitter(self):
        objects = tiny_objects()
        ids = tiny_instance_map(0)
        params = SimulateParams(inconsistency=1.0, split_rate=1.0, group_rate=0.0, part_rate=0.0,
                                multi_rate=0.0, miss_rate=0.0, seed=5)
        masks, _ = simulate_view_masks(ids, objects, frame_rng(5, 0), params)
        wall = ids == 1
        pieces = [m for m in masks if (m & wall).sum() >= 0.8 * m.sum()]
        assert len(pieces) == 2  # the wall comes as two pieces
        # jitter: no mask equals its ground-truth object exactly, but all stay close (IoU > 0.5)
        gt = _object_masks(ids, objects, 1)
        assert not ({m.tobytes() for m in masks} & gt)

    def test_determinism(self):
        objects = tiny_objects()
        params = SimulateParams(inconsistency=0.8, seed=7)
        a = simulate_view_masks(tiny_instance_map(2), objects, frame_rng(7, 2), params)
        b = simulate_view_masks(tiny_instance_map(2), objects, frame_rng(7, 2), params)
        c = simulate_view_masks(tiny_instance_map(2), objects, frame_rng(8, 2), params)
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_array_equal(a[1], b[1])
        assert a[0].shape != c[0].shape or not np.array_equal(a[0], c[0])

    def test_params_validation(self):
        with pytest.raises(ValueError):
            SimulateParams(inconsistency=1.5)
        with pytest.raises(ConfigError, match="unknown parameter"):
            parse_params("simulated", {"inconsistensy": 0.3})


class TestPromptSegmenter:
    def test_mask_contains_point_and_varies(self, tmp_path):
        scene = make_scene(tmp_path / "s", views=2)
        seg = SimulatedPromptSegmenter(scene, {"inconsistency": 1.0})
        rng = np.random.default_rng(0)
        ids = tiny_instance_map(0)
        seen = set()
        for _ in range(30):
            point = (24.5, 38.5)  # on the table top (leaf 11)
            mask = seg.segment("frame_000", point, rng)
            assert mask.shape == (H, W) and mask.dtype == bool
            assert mask[38, 24]
            seen.add(mask.tobytes())
        assert len(seen) >= 3  # several granularities / boundaries
        cands = seg.candidates("frame_000", (24.5, 38.5))
        np.testing.assert_array_equal(cands["part"], ids == 11)
        np.testing.assert_array_equal(cands["object"], np.isin(ids, [11, 12, 13]))
        np.testing.assert_array_equal(cands["group"], np.isin(ids, [11, 12, 13, 20, 21]))

    def test_zero_inconsistency_returns_object(self, tmp_path):
        scene = make_scene(tmp_path / "s", views=2)
        seg = SimulatedPromptSegmenter(scene, SimulateParams(inconsistency=0.0))
        ids = tiny_instance_map(1)
        mask = seg.segment("frame_001", (70.0, 46.0), np.random.default_rng(1))  # chair seat
        np.testing.assert_array_equal(mask, np.isin(ids, [31, 32]))

    def test_adjacency_group_without_hierarchy(self, tmp_path):
        scene = make_scene(tmp_path / "s", views=1, replica_like=True)
        seg = SimulatedPromptSegmenter(scene, {"inconsistency": 1.0})
        cands = seg.candidates("frame_000", (10.0, 45.0))  # the lamp, touching the box
        ids = tiny_instance_map(0)
        np.testing.assert_array_equal(cands["object"], ids == 41)
        np.testing.assert_array_equal(cands["group"], np.isin(ids, [40, 41]))
        assert "part" not in cands

    def test_bad_point_and_frame(self, tmp_path):
        scene = make_scene(tmp_path / "s", views=1)
        seg = SimulatedPromptSegmenter(scene)
        with pytest.raises(Trace3DError, match="outside"):
            seg.segment("frame_000", (500.0, 3.0), np.random.default_rng(0))
        with pytest.raises(Trace3DError, match="no frame named"):
            seg.segment("nope", (5.0, 3.0), np.random.default_rng(0))


# ----------------------------------------------------------------------------------------------
# run_masks: simulated end to end, files, sam
# ----------------------------------------------------------------------------------------------


def test_run_masks_simulated_writes_every_frame(tmp_path):
    scene = make_scene(tmp_path / "s", views=4)
    out = tmp_path / "masks"
    run_masks(scene, out, "simulated", {"inconsistency": 0.0, "seed": 1})
    summary = json.loads((out / "masks.json").read_text())
    assert summary["source"] == "simulated"
    assert summary["params"]["inconsistency"] == 0.0
    assert set(summary["masks_per_view"]) == {c.name for c in scene.cameras}  # train and test
    assert summary["ground_truth_check"]["inconsistent_fraction"] == 0.0
    for cam in scene.cameras:
        masks, scores = read_mask_npz(out / f"{cam.name}.npz", H, W)
        assert masks.shape[0] == summary["masks_per_view"][cam.name] == 9
        assert scores.dtype == np.float32


def test_run_masks_is_deterministic(tmp_path):
    scene = make_scene(tmp_path / "s", views=3)
    for d in ("a", "b"):
        run_masks(scene, tmp_path / d, "simulated", {"inconsistency": 0.7, "seed": 4})
    for cam in scene.cameras:
        a = np.load(tmp_path / "a" / f"{cam.name}.npz")
        b = np.load(tmp_path / "b" / f"{cam.name}.npz")
        np.testing.assert_array_equal(a["masks"], b["masks"])
        np.testing.assert_array_equal(a["scores"], b["scores"])


def test_simulated_needs_instances(tmp_path):
    scene = make_scene(tmp_path / "s", views=1, instances=False)
    with pytest.raises(Trace3DError, match="needs ground-truth instance maps"):
        run_masks(scene, tmp_path / "m", "simulated", {})


def test_unknown_source(tmp_path):
    scene = make_scene(tmp_path / "s", views=1)
    with pytest.raises(Trace3DError, match="unknown mask source"):
        run_masks(scene, tmp_path / "m", "magic", {})


class TestFiles:
    def test_npz_and_png_round_trip(self, tmp_path):
        scene = make_scene(tmp_path / "s", views=2)
        ids0, ids1 = tiny_instance_map(0), tiny_instance_map(1)
        stack0 = np.stack([ids0 == 1, ids0 == 2, np.isin(ids0, [11, 12, 13])])
        (scene.root / "masks").mkdir()
        np.savez(scene.root / "masks" / "frame_000.npz", masks=stack0.astype(np.uint8),
                 scores=np.array([0.9, 0.8, 0.7]))
        png_dir = scene.root / "masks" / "frame_001"
        png_dir.mkdir()
        for k, i in enumerate([40, 41]):
            cv2.imwrite(str(png_dir / f"{k}.png"), (ids1 == i).astype(np.uint8) * 255)
        out = tmp_path / "m"
        run_masks(scene, out, "files", {"default_score": 0.5})
        m0, s0 = read_mask_npz(out / "frame_000.npz", H, W)
        np.testing.assert_array_equal(m0, stack0)
        np.testing.assert_allclose(s0, [0.9, 0.8, 0.7], rtol=1e-6)
        m1, s1 = read_mask_npz(out / "frame_001.npz", H, W)
        np.testing.assert_array_equal(m1, np.stack([ids1 == 40, ids1 == 41]))
        np.testing.assert_array_equal(s1, [0.5, 0.5])

    def test_other_folder_and_default_scores(self, tmp_path):
        scene = make_scene(tmp_path / "s", views=1)
        folder = tmp_path / "elsewhere"
        folder.mkdir()
        ids = tiny_instance_map(0)
        np.savez_compressed(folder / "frame_000.npz", masks=np.stack([ids == 1, ids == 2]))
        run_masks(scene, tmp_path / "m", "files", {"folder": str(folder), "default_score": 0.25})
        masks, scores = read_mask_npz(tmp_path / "m" / "frame_000.npz", H, W)
        assert len(masks) == 2
        np.testing.assert_array_equal(scores, [0.25, 0.25])
        summary = json.loads((tmp_path / "m" / "masks.json").read_text())
        assert summary["source"] == "files" and summary["masks_per_view"] == {"frame_000": 2}

    def test_size_mismatch_refused(self, tmp_path):
        scene = make_scene(tmp_path / "s", views=1)
        (scene.root / "masks").mkdir()
        path = scene.root / "masks" / "frame_000.npz"
        np.savez(path, masks=np.zeros((2, 80, 100), dtype=bool))
        with pytest.raises(SceneFormatError) as err:
            run_masks(scene, tmp_path / "m", "files", {})
        assert str(err.value) == f"{path}: mask stack is 100x80 but the image is {W}x{H}."

    def test_png_size_mismatch_and_bad_names(self, tmp_path):
        scene = make_scene(tmp_path / "s", views=1)
        folder = scene.root / "masks" / "frame_000"
        folder.mkdir(parents=True)
        cv2.imwrite(str(folder / "0.png"), np.zeros((10, 12), np.uint8))
        with pytest.raises(SceneFormatError, match=r"0\.png: mask is 12x10 but the image is 96x72\."):
            run_masks(scene, tmp_path / "m", "files", {})
        (folder / "0.png").unlink()
        cv2.imwrite(str(folder / "first.png"), np.zeros((H, W), np.uint8))
        with pytest.raises(SceneFormatError, match="must be named <k>.png"):
            run_masks(scene, tmp_path / "m", "files", {})

    def test_missing_and_malformed(self, tmp_path):
        scene = make_scene(tmp_path / "s", views=1)
        with pytest.raises(SceneFormatError, match="mask folder does not exist"):
            run_masks(scene, tmp_path / "m", "files", {})
        (scene.root / "masks").mkdir()
        with pytest.raises(SceneFormatError, match="mask file is missing for frame 'frame_000'"):
            run_masks(scene, tmp_path / "m", "files", {})
        path = scene.root / "masks" / "frame_000.npz"
        np.savez(path, masks=np.full((1, H, W), 3, np.uint8))
        with pytest.raises(SceneFormatError, match="values other than 0 and 1"):
            run_masks(scene, tmp_path / "m", "files", {})
        np.savez(path, masks=np.zeros((2, H, W), bool), scores=np.ones(3))
        with pytest.raises(SceneFormatError, match="'scores' must be 2 numbers"):
            run_masks(scene, tmp_path / "m", "files", {})
        np.savez(path, other=np.zeros(3))
        with pytest.raises(SceneFormatError, match="no 'masks' array"):
            run_masks(scene, tmp_path / "m", "files", {})
        path.write_bytes(b"not a zip")
        with pytest.raises(SceneFormatError, match="corrupt"):
            run_masks(scene, tmp_path / "m", "files", {})


class TestSam:
    def test_missing_package_and_checkpoint_named(self, tmp_path, monkeypatch):
        monkeypatch.setitem(sys.modules, "segment_anything", None)  # import fails
        with pytest.raises(Trace3DError) as err:
            check_available(SamParams())
        msg = str(err.value)
        assert "segment_anything" in msg and "no SAM checkpoint" in msg
        assert "`simulated`" in msg and "`files`" in msg
        with pytest.raises(Trace3DError, match=r"sam_vit_h\.pth does not exist"):
            check_available(SamParams(checkpoint=str(tmp_path / "sam_vit_h.pth")))

    def test_run_masks_sam_errors_clearly(self, tmp_path, monkeypatch):
        monkeypatch.setitem(sys.modules, "segment_anything", None)
        scene = make_scene(tmp_path / "s", views=1)
        with pytest.raises(Trace3DError, match="the `sam` mask source cannot run"):
            run_masks(scene, tmp_path / "m", "sam", {"model_type": "vit_b"})
        with pytest.raises(ConfigError, match="model_type"):
            run_masks(scene, tmp_path / "m", "sam", {"model_type": "vit_x"})

    def test_only_checkpoint_missing(self, tmp_path, monkeypatch):
        monkeypatch.setitem(sys.modules, "segment_anything", types.ModuleType("segment_anything"))
        with pytest.raises(Trace3DError) as err:
            check_available(SamParams())
        assert "package" not in str(err.value) and "no SAM checkpoint" in str(err.value)

    def test_filters(self):
        masks = np.zeros((3, 20, 20), bool)
        masks[0, :10, :10] = True  # 100 px
        masks[1, :8, :12] = True  # 96 px: dropped (<= 96)
        masks[2] = True
        np.testing.assert_array_equal(filter_small(masks, 96), [True, False, True])
        np.testing.assert_array_equal(filter_stability(np.array([0.95, 0.9, 0.85]), 0.9), [True, True, False])

    def test_nesting_merges_nearly_covered_masks(self):
        masks = np.zeros((3, 20, 20), bool)
        masks[0, 2:12, 2:12] = True  # 100 px, 92 px of it inside mask 1
        masks[1, 0:18, 2:20] = True  # 324 px before the notch
        masks[2, 0:5, 0:5] = True  # 25 px, 13 px inside mask 1: stays separate
        masks[1, 2:4, 4:8] = False  # a notch: 8 px of mask 0 outside mask 1 -> 92 % covered
        nested, order = nest_covered_masks(masks, 0.9)
        np.testing.assert_array_equal(order, [2, 0, 1])
        np.testing.assert_array_equal(nested[0], masks[2])
        np.testing.assert_array_equal(nested[1], masks[0])
        assert np.all(nested[2][masks[0]])  # the big mask now contains mask 0 completely
        assert not np.all(nested[2][masks[2]])
        np.testing.assert_array_equal(nested[2], masks[1] | masks[0])

    def test_nesting_matches_reference(self):
        rng = np.random.default_rng(0)
        for _ in range(5):
            masks = np.zeros((12, 24, 24), bool)
            for m in masks:
                y, x = rng.integers(0, 18, 2)
                h, w = rng.integers(3, 24, 2)
                m[y:y + h, x:x + w] = True
                if rng.random() < 0.5:
                    m[rng.integers(0, 24), :] = False
            fast, _ = nest_covered_masks(masks, 0.9)
            np.testing.assert_array_equal(fast, _nest_covered_masks_reference(masks, 0.9))

    def test_postprocess_and_run_with_a_stand_in_generator(self, tmp_path, monkeypatch):
        """The whole `sam` path with a stand-in `segment_anything` module that returns GT masks."""
        scene = make_scene(tmp_path / "s", views=2)
        calls = {}

        class FakeModel:
            def to(self, device):
                calls["device"] = device
                return self

        class FakeGenerator:
            def __init__(self, model, **kwargs):
                calls["kwargs"] = kwargs
                self.view = 0

            def generate(self, image):
                assert image.shape == (H, W, 3)
                ids = tiny_instance_map(self.view)
                self.view += 1
                records = []
                for i, stab in ((1, 0.97), (2, 0.95), (40, 0.99), (50, 0.5), (11, 0.93)):
                    seg = ids == i
                    records.append({"segmentation": seg, "area": int(seg.sum()),
                                    "predicted_iou": 0.9, "stability_score": stab})
                return records

        fake = types.ModuleType("segment_anything")
        fake.SamAutomaticMaskGenerator = FakeGenerator
        fake.sam_model_registry = {"vit_b": lambda checkpoint: FakeModel()}
        monkeypatch.setitem(sys.modules, "segment_anything", fake)
        ckpt = tmp_path / "sam_vit_b.pth"
        ckpt.write_bytes(b"x")
        out = tmp_path / "m"
        run_masks(scene, out, "sam", {"checkpoint": str(ckpt), "model_type": "vit_b"})
        assert calls["kwargs"]["stability_score_thresh"] == 0.9
        assert calls["device"] == "cpu"
        masks, scores = read_mask_npz(out / "frame_000.npz", H, W)
        ids = tiny_instance_map(0)
        # pen: stability 0.5 -> dropped; table top: 240 px kept; ascending area order
        areas = masks.reshape(len(masks), -1).sum(1)
        assert len(masks) == 4 and np.all(np.diff(areas) >= 0)
        assert not any(np.array_equal(m, ids == 50) for m in masks)
        np.testing.assert_allclose(scores, 0.9)

    def test_postprocess_pure(self):
        masks = np.zeros((3, 20, 20), bool)
        masks[0, :10, :10] = True
        masks[1, :5, :5] = True  # 25 px: too small
        masks[2, :, :] = True
        out, scores = postprocess(masks, np.array([0.8, 0.9, 0.7], np.float32),
                                  np.array([0.95, 0.99, 0.92], np.float32), SamParams())
        assert len(out) == 2
        np.testing.assert_allclose(scores, [0.8, 0.7])
        empty, empty_scores = postprocess(masks[:0], np.zeros(0, np.float32), np.zeros(0, np.float32), SamParams())
        assert empty.shape == (0, 20, 20) and empty_scores.shape == (0,)


def test_cli_masks_and_patches(tmp_path, monkeypatch, capsys):
    from trace3d.cli import main

    scene = make_scene(tmp_path / "s", views=2)
    assert main(["masks", "--scene", str(scene.root), "--out", str(tmp_path / "m"),
                 "--params", "{inconsistency: 0.4, seed: 2}"]) == 0
    assert main(["patches", "--scene", str(scene.root), "--masks", str(tmp_path / "m"),
                 "--out", str(tmp_path / "p"), "--params", "{preview_views: 1}"]) == 0
    assert (tmp_path / "p" / "frame_001.png").is_file() and (tmp_path / "p" / "preview.png").is_file()
    monkeypatch.setitem(sys.modules, "segment_anything", None)
    assert main(["masks", "--scene", str(scene.root), "--out", str(tmp_path / "m2"), "--source", "sam"]) == 2
    err = capsys.readouterr().err
    assert "segment_anything" in err and "`simulated`" in err
    assert not (tmp_path / "m2").exists()  # nothing half-written


# --- overlay (one label per pixel, the baselines' input) ---------------------------------------


def test_overlay_smallest_covering_mask_wins():
    from trace3d.masks.overlay import overlay_masks

    masks = np.zeros((3, 4, 5), dtype=bool)
    masks[0] = True  # the whole view (largest)
    masks[1, :2, :3] = True  # 6 px, on top of mask 0
    masks[2, 1, 1:4] = True  # 3 px, overlaps mask 1 and mask 0
    labels = overlay_masks(masks)
    expected = np.full((4, 5), 1, dtype=np.uint16)
    expected[:2, :3] = 2
    expected[1, 1:4] = 3
    np.testing.assert_array_equal(labels, expected)
    # The stack order does not matter, only the areas: reversing the stack keeps the same masks on top.
    reversed_labels = overlay_masks(masks[::-1])
    np.testing.assert_array_equal(reversed_labels, 4 - expected)


def test_overlay_uncovered_pixels_are_zero_and_ties_take_the_later_mask():
    from trace3d.masks.overlay import overlay_masks

    masks = np.zeros((2, 3, 3), dtype=bool)
    masks[0, 0, :2] = True
    masks[1, 0, 1:] = True  # same area: painted after mask 0
    labels = overlay_masks(masks)
    np.testing.assert_array_equal(labels[0], [1, 2, 2])
    assert (labels[1:] == 0).all()
    with pytest.raises(ValueError):
        overlay_masks(np.zeros((3, 3), dtype=bool))


def test_run_overlay_writes_train_views(tmp_path):
    from trace3d.masks.overlay import overlay_masks, run_overlay
    from trace3d.scene import read_u16

    scene = make_scene(tmp_path / "scene")
    run_masks(scene, tmp_path / "masks", "simulated", {})
    report = run_overlay(scene, tmp_path / "masks", tmp_path / "overlay")
    assert report["views"] == len(scene.train_cameras) > 0
    for cam in scene.train_cameras:
        masks, _ = read_mask_npz(tmp_path / "masks" / f"{cam.name}.npz", cam.height, cam.width)
        np.testing.assert_array_equal(read_u16(tmp_path / "overlay" / f"{cam.name}.png"), overlay_masks(masks))
    for cam in scene.test_cameras:
        assert not (tmp_path / "overlay" / f"{cam.name}.png").exists()
    with pytest.raises(SceneFormatError, match="masks folder does not exist"):
        run_overlay(scene, tmp_path / "nowhere", tmp_path / "overlay2")
