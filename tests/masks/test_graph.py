"""The ``graph`` mask source (nested multi-scale Felzenszwalb; no ground truth) and its prompt segmenter."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from trace3d.errors import ConfigError, Trace3DError
from trace3d.masks import parse_params, read_mask_npz, run_masks
from trace3d.masks.graph import (
    GraphParams,
    GraphPromptSegmenter,
    _nest_partitions_reference,
    graph_hierarchy,
    nest_partitions,
)
from trace3d.scene import Camera, Scene, write_cameras, write_frame


@pytest.fixture(scope="module")
def rooms(tmp_path_factory) -> tuple[Scene, Scene]:
    """A tiny synthetic room (with ground truth) and the same room as a user's photos (none)."""
    from trace3d.datasets.synthetic.params import SyntheticParams
    from trace3d.datasets.synthetic.writer import generate_scene

    root = tmp_path_factory.mktemp("graph")
    generate_scene(root / "room", SyntheticParams(seed=5, width=64, height=48, num_views=4, test_every=4))
    shutil.copytree(root / "room", root / "photos")
    for extra in ("instances", "depth"):
        shutil.rmtree(root / "photos" / extra, ignore_errors=True)
    (root / "photos" / "objects.json").unlink()
    return Scene.read(root / "room"), Scene.read(root / "photos")


def _pairwise_nested_or_disjoint(masks: np.ndarray) -> bool:
    flat = masks.reshape(len(masks), -1).astype(np.int64)
    inter = flat @ flat.T
    area = flat.sum(axis=1)
    nested = (inter == area[:, None]) | (inter == area[None, :])
    return bool(((inter == 0) | nested).all())


class TestNesting:
    def test_hand_built(self):
        # fine: four 2x2 quadrants of a 4x4 image; raw coarse: left column of 3 wide, right of 1 wide
        fine = np.array([[0, 0, 1, 1]] * 2 + [[2, 2, 3, 3]] * 2)
        coarse = np.array([[5, 5, 5, 7]] * 4)
        out = nest_partitions(np.stack([fine, coarse]))
        # quadrants 1 and 3 are mostly (2 of 4 pixels vs 2: tie -> lower label 5) in region 5: one region
        np.testing.assert_array_equal(out[1], np.zeros((4, 4)))
        coarse = np.array([[5, 5, 7, 7]] * 3 + [[5, 7, 7, 7]])
        out = nest_partitions(np.stack([fine, coarse]))
        np.testing.assert_array_equal(out[1], np.array([[0, 0, 1, 1]] * 4))

    def test_matches_loop_twin(self):
        rng = np.random.default_rng(0)
        for _ in range(5):
            levels = rng.integers(0, [[[40]], [[9]], [[3]]], size=(3, 20, 24))
            np.testing.assert_array_equal(nest_partitions(levels), _nest_partitions_reference(levels))

    def test_each_level_refines_the_next(self, rooms):
        scene = rooms[1]
        h = graph_hierarchy(scene.image(scene.cameras[0].name), GraphParams())
        assert h.shape[0] == 4
        for k in range(1, len(h)):
            pairs = np.unique(np.stack([h[k - 1].ravel(), h[k].ravel()]), axis=1)
            assert len(np.unique(pairs[0])) == pairs.shape[1]  # one parent per finer region
            assert len(np.unique(h[k])) < len(np.unique(h[k - 1]))  # coarser


def test_dissolve_thin_strips_but_not_small_blobs():
    from trace3d.masks.graph import dissolve_thin

    labels = np.zeros((12, 30), np.int64)
    labels[:, 15:] = 1
    labels[:, 14] = 2  # a 1-px strip of 12 px between the halves: below 2 * 3^2 = 18 px, kept
    labels[2:4, 2:4] = 3  # a 2x2 blob: small, kept
    np.testing.assert_array_equal(dissolve_thin(labels, 1), labels)
    long = np.zeros((30, 30), np.int64)
    long[:, 15:] = 1
    long[:, 14] = 2  # 30 px: thin, split between the neighbours (left: column 13 is nearest)
    long[2:4, 2:4] = 3
    out = dissolve_thin(long, 1)
    assert 2 not in out and (out == 3).sum() == 4
    np.testing.assert_array_equal(out[:, 15:], 1)
    np.testing.assert_array_equal(out[:, :14][long[:, :14] == 0], 0)
    np.testing.assert_array_equal(dissolve_thin(long, 0), long)


class TestSource:
    def test_runs_without_ground_truth_and_nests(self, rooms, tmp_path):
        from trace3d.cli import main

        photos = rooms[1]
        assert not photos.has_instances and photos.objects is None
        out = tmp_path / "masks"
        assert main(["masks", "--scene", str(photos.root), "--out", str(out), "--source", "graph"]) == 0
        summary = json.loads((out / "masks.json").read_text())
        assert summary["source"] == "graph" and "ground_truth_check" not in summary
        assert summary["params"]["scales"] == GraphParams().scales
        min_area = GraphParams().resolved(48, 64)["min_area"]
        for cam in photos.cameras:
            masks, scores = read_mask_npz(out / f"{cam.name}.npz", 48, 64)
            assert masks.shape[1:] == (48, 64) and len(masks) == summary["masks_per_view"][cam.name] >= 3
            np.testing.assert_array_equal(scores, 1.0)
            assert _pairwise_nested_or_disjoint(masks)
            assert masks.sum(axis=(1, 2)).min() >= min_area
            assert masks.any(axis=0).all()  # every pixel covered (finest regions are >= min_size)
            assert len({m.tobytes() for m in masks}) == len(masks)  # no mask twice
        # the masks flow through the patch step unchanged
        assert main(["patches", "--scene", str(photos.root), "--masks", str(out), "--out",
                     str(tmp_path / "patches")]) == 0

    def test_deterministic_and_ground_truth_check(self, rooms, tmp_path):
        room = rooms[0]
        run_masks(room, tmp_path / "a", "graph", {})
        run_masks(room, tmp_path / "b", "graph", {})
        for cam in room.cameras:
            a, _ = read_mask_npz(tmp_path / "a" / f"{cam.name}.npz", 48, 64)
            b, _ = read_mask_npz(tmp_path / "b" / f"{cam.name}.npz", 48, 64)
            np.testing.assert_array_equal(a, b)
        summary = json.loads((tmp_path / "a" / "masks.json").read_text())
        assert summary["ground_truth_check"]["objects"] > 0

    def test_scales_with_the_image(self):
        small, large = GraphParams().resolved(120, 160), GraphParams().resolved(240, 320)
        assert large["scales"] == pytest.approx([4 * s for s in small["scales"]])
        assert large["sigma"] == pytest.approx(2 * small["sigma"])
        assert abs(large["min_area"] - 4 * small["min_area"]) <= 4  # each rounded up to whole pixels
        assert small["thin_radius"] == 1 and large["thin_radius"] == 2

    @pytest.mark.parametrize("bad", [{"scales": [100, 400]}, {"scales": [400, 100, 1000]}, {"sigma": -1},
                                     {"min_area": 1.5}, {"max_area": 0.0}, {"scale": [1, 2, 3]}])
    def test_bad_parameters(self, bad, rooms, tmp_path, capsys):
        from trace3d.cli import main

        with pytest.raises(ConfigError):
            parse_params("graph", bad)
        out = tmp_path / "m"
        assert main(["masks", "--scene", str(rooms[1].root), "--out", str(out), "--source", "graph",
                     "--params", json.dumps(bad)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "graph" in err[0] and not out.exists()


# ----------------------------------------------------------------------------------------------
# Point prompts
# ----------------------------------------------------------------------------------------------


def _prompt_scene(root: Path) -> tuple[Scene, np.ndarray, np.ndarray]:
    """One 64x48 view, no ground truth: a red box holding a blue square on a noisy grey background.

    Returns the scene, the red box's pixels without the blue square, and the blue square's pixels."""
    rng = np.random.default_rng(1)
    H, W = 48, 64
    image = np.clip(128 + rng.normal(0, 3, size=(H, W, 3)), 0, 255)
    red = np.zeros((H, W), bool)
    red[8:40, 10:50] = True
    blue = np.zeros((H, W), bool)
    blue[18:30, 30:42] = True
    image[red] = (200, 30, 30)
    image[blue] = (30, 30, 200)
    write_frame(root, "view", image.astype(np.uint8))
    write_cameras(root, [Camera("view", "train", W, H, [[60.0, 0, W / 2], [0, 60.0, H / 2], [0, 0, 1]], np.eye(4))])
    return Scene.read(root), red & ~blue, blue


def _iou(a, b):
    return (a & b).sum() / (a | b).sum()


def _same_up_to_one_pixel(mask, truth):
    """``mask`` holds ``truth`` eroded by one pixel and lies inside ``truth`` dilated by one pixel
    (Felzenszwalb's smoothing may move a border by a pixel)."""
    import cv2

    k = np.ones((3, 3), np.uint8)
    inner = cv2.erode(truth.astype(np.uint8), k).astype(bool)
    outer = cv2.dilate(truth.astype(np.uint8), k).astype(bool)
    return bool((mask[inner]).all() and not mask[~outer].any())


class TestPromptSegmenter:
    @pytest.mark.parametrize("refine", ["none", "grabcut"])
    def test_known_answer(self, tmp_path, refine):
        scene, red, blue = _prompt_scene(tmp_path)
        # the mask source's hierarchy: at 64x48 the prompt source's finer default levels (minimum
        # region 4 px) glue a few noisy background pixels to the box
        seg = GraphPromptSegmenter(scene, {"graph": {}, "refine": refine})
        positive = np.array([[15.5, 12.5], [45.5, 35.5]])  # (x, y) on the red box
        negative = np.array([[35.5, 23.5]])  # on the blue square
        mask = seg.segment("view", positive, None, negatives=negative)
        assert mask[12, 15] and mask[35, 45] and not mask[23, 35]
        assert _same_up_to_one_pixel(mask, red)
        # both colours prompted, no negatives: the box with its square
        both = seg.segment("view", np.array([[15.5, 12.5], [35.5, 23.5]]), None)
        assert _same_up_to_one_pixel(both, red | blue)
        # one point on the square: the square
        assert _same_up_to_one_pixel(seg.segment("view", np.array([[35.5, 23.5]]), None), blue)

    def test_like_picks_the_closest_level(self, tmp_path):
        scene, red, blue = _prompt_scene(tmp_path)
        seg = GraphPromptSegmenter(scene, {"select": "points"})
        # the finest region under the point is the square; asked for something like the whole box,
        # the answer grows only if some level holds the square inside a larger region
        image, hierarchy = seg.view("view")
        mask = seg.segment("view", np.array([[35.5, 23.5]]), None, like=red | blue)
        ious = [_iou(np.isin(labels, [labels[23, 35]]), red | blue) for labels in hierarchy]
        assert _iou(mask, red | blue) == pytest.approx(max(ious))

    def test_negatives_and_levels_on_a_hand_built_hierarchy(self, tmp_path):
        scene, red, blue = _prompt_scene(tmp_path)
        seg = GraphPromptSegmenter(scene)
        image, _ = seg.view("view")
        # level 0: background 0, red 1, blue 2; level 1: the box (red + blue) 1; level 2: one region
        fine = np.where(blue, 2, np.where(red, 1, 0))
        hierarchy = np.stack([fine, np.minimum(fine, 1), np.zeros_like(fine)]).astype(np.int32)
        seg._cache["view"] = (image, hierarchy)
        on_red, on_blue, on_bg = np.array([[15.5, 12.5]]), np.array([[35.5, 23.5]]), np.array([[2.5, 2.5]])
        box = red | blue
        # red and blue prompted: the finest level holding both in one region is the box
        assert (seg.segment("view", np.concatenate([on_red, on_blue]), None) == box).all()
        # like the box: level 1, unless a negative on the square rules out every level above 0
        assert (seg.segment("view", on_red, None, like=box) == box).all()
        assert (seg.segment("view", on_red, None, like=box, negatives=on_blue) == red).all()
        # like the whole image with a negative on the background: the whole-image level holds it
        whole = np.ones_like(red)
        assert (seg.segment("view", on_red, None, like=whole) == whole).all()
        assert (seg.segment("view", on_red, None, like=whole, negatives=on_bg) == box).all()

    def test_fit_takes_the_regions_inside_the_rendered_region(self, tmp_path):
        scene, red, blue = _prompt_scene(tmp_path)
        seg = GraphPromptSegmenter(scene, {"select": "fit"})
        image, _ = seg.view("view")
        # level 0: background 0, box split into left 1 / right 2 halves; level 1: the box; level 2: one region
        fine = np.zeros(red.shape, np.int32)
        fine[8:40, 10:30], fine[8:40, 30:50] = 1, 2
        hierarchy = np.stack([fine, np.minimum(fine, 1), np.zeros_like(fine)])
        seg._cache["view"] = (image, hierarchy)
        box = fine > 0
        # a rendered region: the box shifted right by 2 px; one prompt on the left half
        rendered = np.roll(box, 2, axis=1)
        on_left = np.array([[15.5, 20.5]])
        assert (seg.segment("view", on_left, None, like=rendered) == box).all()
        # points only: the left half at level 0 scores below the box at level 1, so also the box
        points = GraphPromptSegmenter(scene, {"select": "points"})
        points._cache["view"] = (image, hierarchy)
        assert (points.segment("view", on_left, None, like=rendered) == box).all()
        # a negative on the right half: fit keeps the left half only
        assert (seg.segment("view", on_left, None, like=rendered, negatives=np.array([[40.5, 20.5]])) ==
                (fine == 1)).all()
        # rendered region = the right half only, prompt on its deepest pixel: fit gives the right half
        right = fine == 2
        assert (seg.segment("view", np.array([[40.5, 20.5]]), None, like=right) == right).all()

    def test_refuses_bad_prompts(self, tmp_path):
        scene, _, _ = _prompt_scene(tmp_path)
        seg = GraphPromptSegmenter(scene)
        with pytest.raises(Trace3DError, match="outside"):
            seg.segment("view", np.array([[70.0, 5.0]]), None)
        with pytest.raises(Trace3DError, match="no frame"):
            seg.segment("nope", np.array([[5.0, 5.0]]), None)
        with pytest.raises(ConfigError):
            GraphPromptSegmenter(scene, {"refine": "crf"})


def test_schema_matches_the_dataclasses():
    """The config schema's masks.graph and lift.graph sections name the dataclasses' fields and defaults."""
    import dataclasses

    import yaml

    from trace3d.masks.graph import GraphPromptParams
    from trace3d.lifting.self_prompt import SelfPromptParams

    # the step sections are generated from the dataclasses (python -m trace3d.tooling.schema, workflow/schemas/steps.schema.yaml)
    defs = yaml.safe_load((Path(__file__).resolve().parents[2] / "workflow/schemas/steps.schema.yaml").read_text())
    defs = defs["$defs"]
    section = defs["masks"]["properties"]["graph"]
    assert set(section["properties"]) == {f.name for f in dataclasses.fields(GraphParams)}
    assert set(f.name for f in dataclasses.fields(GraphPromptParams)) >= {"graph", "select", "refine"}
    assert "graph" in defs["masks"]["properties"]["source"]["enum"]
    assert set(defs["lift"]["properties"]["prompt_source"]["enum"]) == {"simulated", "sam", "graph"}
    assert SelfPromptParams(prompt_source="graph", graph={"refine": "grabcut"}).graph == {"refine": "grabcut"}
    with pytest.raises(ConfigError, match="scale"):
        SelfPromptParams(prompt_source="graph", graph={"graph": {"scale": [1, 2, 3]}})


def test_prompt_bench_scores_the_oracle_and_the_graph(rooms, tmp_path):
    from trace3d.cli import main
    from trace3d.bench.prompts import run_bench

    room, photos = rooms
    result = run_bench(room.root, views=2, min_pixels=30, sources={
        "oracle": ("simulated", {"inconsistency": 0.0}), "graph": ("graph", {})})
    assert result["object_views"] > 0
    # the oracle at inconsistency 0 answers with the ground-truth object itself
    assert result["iou"]["oracle"]["reference"]["mean"] == 1.0
    assert 0.0 < result["iou"]["graph"]["reference"]["mean"] < 1.0
    assert 0.0 < result["rendered_cue_iou"]["mean"] < 1.0
    # a scene without ground truth cannot be scored: one sentence, exit 2
    assert main(["bench", "prompts", "--room", str(photos.root), "--quick"]) == 2
