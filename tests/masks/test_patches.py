"""Primitive patches: overlap regions of a view's masks, tiny-patch absorption, hierarchy, the step."""

from __future__ import annotations

import json

import numpy as np
import pytest

from trace3d.errors import SceneFormatError
from trace3d.masks import run_masks
from trace3d.masks.patches import (
    PatchHierarchy,
    PatchParams,
    _masks_to_patches_reference,
    _nesting_depth_reference,
    coarser_patches,
    masks_to_patches,
    nesting_depth,
    read_patches,
    run_patches,
    select_masks,
)

from tests.masks.test_masks import H, W, make_scene


def _signatures(masks: np.ndarray) -> np.ndarray:
    """[H, W] int: bit-vector of covering masks (M <= 62)."""
    weights = (1 << np.arange(len(masks), dtype=np.int64))[:, None, None]
    return (masks.astype(np.int64) * weights).sum(axis=0)


def _random_masks(rng: np.random.Generator, M: int, h: int, w: int) -> np.ndarray:
    masks = np.zeros((M, h, w), bool)
    for m in masks:
        kind = rng.integers(3)
        if kind == 0:
            y, x = rng.integers(0, h - 2), rng.integers(0, w - 2)
            m[y:y + rng.integers(2, h), x:x + rng.integers(2, w)] = True
        elif kind == 1:
            yy, xx = np.mgrid[0:h, 0:w]
            cy, cx, r = rng.uniform(0, h), rng.uniform(0, w), rng.uniform(2, h / 2)
            m[(yy - cy) ** 2 + (xx - cx) ** 2 < r * r] = True
        else:
            m[rng.random((h, w)) < 0.08] = True  # speckle: many tiny pieces
    return masks


class TestMasksToPatches:
    def test_two_overlapping_masks_give_three_patches(self):
        masks = np.zeros((2, 10, 12), bool)
        masks[0, 1:8, 1:7] = True  # 42 px
        masks[1, 3:10, 4:11] = True  # 49 px
        patch_map, hier = masks_to_patches(masks, 0)
        assert patch_map.dtype == np.uint16 and patch_map.shape == (10, 12)
        assert hier.num_patches == 3
        assert set(np.unique(patch_map)) == {0, 1, 2, 3}
        only_a = masks[0] & ~masks[1]
        only_b = masks[1] & ~masks[0]
        both = masks[0] & masks[1]
        for region, containers in ((only_a, [0]), (only_b, [1]), (both, [1, 0])):
            ids = np.unique(patch_map[region])
            assert len(ids) == 1
            assert hier.containers(int(ids[0])) == containers  # coarse (larger mask 1) to fine
            assert hier.patch_areas[ids[0] - 1] == region.sum()
        assert np.all(patch_map[~masks.any(0)] == 0)
        np.testing.assert_array_equal(hier.mask_areas, [42, 49])

    def test_every_pixel_has_exactly_one_patch_of_its_signature(self):
        rng = np.random.default_rng(1)
        masks = _random_masks(rng, 12, 40, 50)
        masks = masks[[i for i in range(len(masks)) if masks[i].sum() > 40]]  # no speckle here
        patch_map, hier = masks_to_patches(masks, 0)
        np.testing.assert_array_equal(patch_map > 0, masks.any(0))
        sig = _signatures(masks)
        ids = np.unique(patch_map[patch_map > 0])
        np.testing.assert_array_equal(ids, np.arange(1, hier.num_patches + 1))
        for p in ids:
            s = np.unique(sig[patch_map == p])
            assert len(s) == 1  # one signature per patch ...
            assert sorted(hier.containers(int(p))) == [m for m in range(len(masks)) if s[0] >> m & 1]
        # ... and one patch per signature
        assert len(np.unique(sig[sig > 0])) == hier.num_patches
        assert hier.patch_areas.sum() == (patch_map > 0).sum()

    def test_tiny_patch_absorbed_into_largest_neighbour_inside_common_mask(self):
        masks = np.zeros((3, 12, 20), bool)
        masks[0, :, :8] = True  # left object (96 px)
        masks[1, :, 8:] = True  # right object (larger)
        masks[0, 4:7, 8:10] = True  # 6 px sliver of mask 0 bleeding into mask 1
        masks[2, :, :] = True  # the whole image (coarse mask)
        masks[2, 0:2, 18:20] = False  # 4 px corner covered by mask 1 only
        patch_map, hier = masks_to_patches(masks, 0)
        assert hier.num_patches == 4  # left, right, sliver, corner
        patch_map, hier = masks_to_patches(masks, min_patch_pixels=8)
        assert hier.num_patches == 2
        right = patch_map[0, 15]
        assert patch_map[5, 8] == right  # the sliver joins the (larger) right patch
        assert patch_map[0, 19] == right  # the corner joins the right patch (common mask 1)
        assert hier.containers(int(right)) == [2, 1]
        np.testing.assert_array_equal(patch_map > 0, masks.any(0))

    def test_tiny_patch_without_common_mask_neighbour_stays(self):
        masks = np.zeros((2, 10, 10), bool)
        masks[0, :, :5] = True
        masks[1, 4:6, 5:7] = True  # 4 px, touches mask 0 but shares no mask with it
        patch_map, hier = masks_to_patches(masks, min_patch_pixels=10)
        assert hier.num_patches == 2
        assert hier.containers(int(patch_map[4, 5])) == [1]

    def test_two_tiny_pieces_absorb_smaller_into_bigger(self):
        # pieces of 3 px and 2 px sharing a mask, nothing else around: no cycle, one patch
        masks = np.zeros((2, 6, 6), bool)
        masks[0, 2, 1:6] = True
        masks[1, 2, 4:6] = True
        patch_map, hier = masks_to_patches(masks, min_patch_pixels=10)
        assert hier.num_patches == 1 and hier.containers(1) == [0]
        np.testing.assert_array_equal(patch_map > 0, masks[0])

    def test_uncovered_pixels_never_absorbed(self):
        masks = np.zeros((1, 10, 10), bool)
        masks[0] = True
        masks[0, 5, 5] = False  # one uncovered pixel inside
        patch_map, hier = masks_to_patches(masks, min_patch_pixels=50)
        assert patch_map[5, 5] == 0 and hier.num_patches == 1

    def test_disconnected_overlap_region(self):
        masks = np.zeros((2, 8, 20), bool)
        masks[0, :, :] = True
        masks[1, :, 2:5] = True
        masks[1, :, 14:17] = True  # same signature {0, 1} in two places
        patch_map, hier = masks_to_patches(masks, 0)
        assert hier.num_patches == 2 and patch_map[0, 3] == patch_map[0, 15]
        patch_map, hier = masks_to_patches(masks, 0, split_disconnected=True)
        assert patch_map[0, 3] != patch_map[0, 15]
        assert hier.num_patches == 5  # background-of-mask-0 is cut into three by the two stripes
        assert hier.containers(int(patch_map[0, 15])) == [0, 1]

    def test_thin_ring_absorbed(self):
        # an object mask dilated by 1 px overlaps the floor in a 1-px ring of ~40 px
        masks = np.zeros((2, 20, 20), bool)
        masks[0] = True
        masks[0, 6:14, 6:14] = False  # the floor excludes the object ...
        masks[1, 5:15, 5:15] = True  # ... whose mask is 1 px too large
        _, hier = masks_to_patches(masks, 20)
        assert hier.num_patches == 3  # floor, object, ring (36 px, thin)
        patch_map, hier = masks_to_patches(masks, 20, min_patch_width=3)
        assert hier.num_patches == 2
        assert patch_map[5, 5] == patch_map[0, 0]  # ring joins the floor (largest, common mask 0)
        # a 3-px-wide band is not thin at width 3 but is at width 5
        masks = np.zeros((2, 12, 20), bool)
        masks[0] = True
        masks[1, 4:7, :] = True
        assert masks_to_patches(masks, 0, min_patch_width=3)[1].num_patches == 2  # above+below: one patch
        assert masks_to_patches(masks, 0, min_patch_width=5)[1].num_patches == 1

    @pytest.mark.parametrize("split", [False, True])
    @pytest.mark.parametrize("min_pixels,min_width", [(0, 0), (5, 3), (30, 0), (0, 5)])
    def test_matches_slow_reference(self, split, min_pixels, min_width):
        rng = np.random.default_rng(100 + min_pixels + min_width)
        for _trial in range(3):
            masks = _random_masks(rng, int(rng.integers(1, 9)), 18, 24)
            fast_map, hier = masks_to_patches(masks, min_pixels, split_disconnected=split, min_patch_width=min_width)
            ref_map, ref_containers = _masks_to_patches_reference(masks, min_pixels, split, min_width)
            np.testing.assert_array_equal(fast_map, ref_map)
            assert hier.patch_masks == ref_containers

    def test_no_masks(self):
        patch_map, hier = masks_to_patches(np.zeros((0, 5, 6), bool), 10)
        assert hier.num_patches == 0 and not patch_map.any()
        assert hier.candidate_pairs().shape == (0, 2)

    def test_more_than_64_masks(self):
        rng = np.random.default_rng(3)
        masks = _random_masks(rng, 80, 30, 30)
        masks = masks[[i for i in range(80) if masks[i].sum() > 30]]
        assert len(masks) > 64
        patch_map, hier = masks_to_patches(masks, 0)
        ref_map, ref_containers = _masks_to_patches_reference(masks, 0)
        np.testing.assert_array_equal(patch_map, ref_map)
        assert hier.patch_masks == ref_containers

    def test_rejects_non_bool(self):
        with pytest.raises(ValueError):
            masks_to_patches(np.zeros((2, 4, 4), np.uint8), 0)


class TestHierarchy:
    def _hier(self):
        masks = np.zeros((3, 10, 10), bool)
        masks[0, :, :] = True  # everything
        masks[1, :, :5] = True  # left half
        masks[2, :5, :5] = True  # top-left quarter
        return masks_to_patches(masks, 0, scores=np.array([0.5, 0.6, 0.7], np.float32), frame="v0")

    def test_containers_and_pairs(self):
        patch_map, hier = self._hier()
        tl, bl, right = int(patch_map[0, 0]), int(patch_map[9, 0]), int(patch_map[0, 9])
        assert hier.containers(tl) == [0, 1, 2]
        assert hier.containers(bl) == [0, 1]
        assert hier.containers(right) == [0]
        assert hier.patches_in_mask(1) == sorted([tl, bl])
        pairs = {tuple(p) for p in hier.candidate_pairs().tolist()}
        assert pairs == {tuple(sorted(p)) for p in [(tl, bl), (tl, right), (bl, right)]}
        member = hier.membership()
        assert member.shape == (4, 3) and not member[0].any() and member[tl].all()

    def test_json_round_trip_and_read(self, tmp_path):
        from trace3d.io import write_json
        from trace3d.scene import write_u16

        patch_map, hier = self._hier()
        data = json.loads(json.dumps(hier.to_json()))
        assert data["masks"][2] == {"index": 2, "area": 25, "score": pytest.approx(0.7)}
        back = PatchHierarchy.from_json(data, "x.json")
        assert back.patch_masks == hier.patch_masks and back.frame == "v0"
        np.testing.assert_array_equal(back.patch_areas, hier.patch_areas)
        write_u16(tmp_path / "v0.png", patch_map)
        write_json(tmp_path / "v0.json", data)
        got_map, got = read_patches(tmp_path, "v0")
        np.testing.assert_array_equal(got_map, patch_map)
        data["patches"][0]["masks"] = [7]
        write_json(tmp_path / "v0.json", data)
        with pytest.raises(SceneFormatError, match="v0.json: a patch names a mask index outside"):
            read_patches(tmp_path, "v0")


class TestNestingDepth:
    def test_a_known_tree(self):
        # a room (0) holding a table (1) holding a cup (2) and a plate (3); a picture (4) beside the table;
        # a copy of the cup (5): equal masks, the later one inside the earlier
        m = np.zeros((6, 8, 10), bool)
        m[0] = True
        m[1, 2:8, 0:6] = True
        m[2, 3:5, 1:3] = True
        m[3, 5:7, 3:5] = True
        m[4, 0:2, 7:10] = True
        m[5] = m[2]
        assert nesting_depth(m).tolist() == [0, 1, 2, 2, 1, 3]
        kept, scores = select_masks(m, np.arange(6, dtype=np.float32), PatchParams(max_depth=1))
        assert np.array_equal(kept, m[[0, 1, 4]]) and scores.tolist() == [0, 1, 4]
        assert select_masks(m, np.ones(6, np.float32), PatchParams())[0] is m  # None: every mask

    def test_matches_the_loop_twin_on_random_and_overlapping_masks(self):
        rng = np.random.default_rng(7)
        for M in (1, 3, 9, 17):
            masks = _random_masks(rng, M, 9, 11)
            masks[-1] = masks[0]  # an exact duplicate
            np.testing.assert_array_equal(nesting_depth(masks), _nesting_depth_reference(masks))

    def test_coarser_patches_from_the_hierarchy_are_the_coarse_masks_patches(self):
        """Regrouping the patches by the hierarchy's masks at most k deep gives the patches of those masks
        themselves (no absorption on either side), for nested trees with duplicates and uncovered pixels."""
        rng = np.random.default_rng(11)
        h, w = 12, 16

        def split(masks, y0, y1, x0, x1, depth):
            if depth > 3 or (y1 - y0) * (x1 - x0) < 4:
                return
            m = np.zeros((h, w), bool)
            m[y0:y1, x0:x1] = True
            masks.append(m)
            if rng.random() < 0.2:
                masks.append(m.copy())  # a duplicate mask
            if rng.random() < 0.7:
                if (y1 - y0) >= (x1 - x0):
                    cut = int(rng.integers(y0 + 1, y1))
                    split(masks, y0, cut, x0, x1, depth + 1)
                    split(masks, cut, y1, x0, x1, depth + 1)
                else:
                    cut = int(rng.integers(x0 + 1, x1))
                    split(masks, y0, y1, x0, cut, depth + 1)
                    split(masks, y0, y1, cut, x1, depth + 1)

        for _ in range(12):
            masks = []
            split(masks, 0, h, 0, w - 3, 0)  # the last three columns stay uncovered
            order = rng.permutation(len(masks))
            masks = np.stack(masks)[order]
            patch_map, hierarchy = masks_to_patches(masks, 0)
            for k in range(4):
                expected, _ = masks_to_patches(masks[nesting_depth(masks) <= k], 0)
                np.testing.assert_array_equal(coarser_patches(patch_map, hierarchy, k), expected.astype(np.int64))
        deep = coarser_patches(patch_map, hierarchy, 99)
        assert deep.max() == patch_map.max()

    def test_max_depth_is_checked(self):
        with pytest.raises(ValueError, match="max_depth"):
            PatchParams(max_depth=-1)


class TestRunPatches:
    def test_max_depth_patches_are_the_coarse_masks_overlap(self, tmp_path):
        scene = make_scene(tmp_path / "s", views=2)
        run_masks(scene, tmp_path / "masks", "simulated", {"inconsistency": 1.0, "seed": 2})
        run_patches(scene, tmp_path / "masks", tmp_path / "all", {"preview_views": 0})
        run_patches(scene, tmp_path / "masks", tmp_path / "top", {"preview_views": 0, "max_depth": 0})
        coarser = 0
        for cam in scene.cameras:
            masks = np.load(tmp_path / "masks" / f"{cam.name}.npz")["masks"]
            top = masks[nesting_depth(masks) == 0]
            expected, _ = masks_to_patches(top, PatchParams.min_patch_pixels, min_patch_width=3)
            got, hier = read_patches(tmp_path / "top", cam.name)
            np.testing.assert_array_equal(got, expected)
            assert hier.num_masks == len(top)
            coarser += int(got.max()) < int(read_patches(tmp_path / "all", cam.name)[0].max())
        assert coarser >= 1  # the simulated masks nest: dropping the inner ones leaves fewer patches

    def test_step_outputs(self, tmp_path):
        scene = make_scene(tmp_path / "s", views=4)
        run_masks(scene, tmp_path / "masks", "simulated", {"inconsistency": 1.0, "seed": 2})
        out = tmp_path / "patches"
        run_patches(scene, tmp_path / "masks", out, {"min_patch_pixels": 10, "preview_views": 2})
        summary = json.loads((out / "patches.json").read_text())
        assert summary["params"]["min_patch_pixels"] == 10
        assert set(summary["views"]) == {c.name for c in scene.cameras}
        assert (out / "preview.png").stat().st_size > 1000
        for cam in scene.cameras:
            masks = np.load(tmp_path / "masks" / f"{cam.name}.npz")["masks"]
            patch_map, hier = read_patches(out, cam.name)
            assert patch_map.shape == (H, W)
            assert hier.num_patches == summary["views"][cam.name]["patches"] == int(patch_map.max())
            np.testing.assert_array_equal(patch_map > 0, masks.any(0))
            # absorption leaves no piece under 10 px that has a neighbour in a common mask
            assert np.all(hier.patch_areas > 0)

    def test_missing_masks_refused(self, tmp_path):
        scene = make_scene(tmp_path / "s", views=2)
        run_masks(scene, tmp_path / "masks", "simulated", {})
        (tmp_path / "masks" / "frame_001.npz").unlink()
        with pytest.raises(SceneFormatError, match=r"frame_001\.npz: mask file is missing"):
            run_patches(scene, tmp_path / "masks", tmp_path / "p", {})
        with pytest.raises(SceneFormatError, match="masks folder does not exist"):
            run_patches(scene, tmp_path / "nope", tmp_path / "p", {})

    def test_unknown_param_refused(self, tmp_path):
        from trace3d.errors import ConfigError

        scene = make_scene(tmp_path / "s", views=1)
        with pytest.raises(ConfigError, match="min_patch_pixel"):
            run_patches(scene, tmp_path, tmp_path / "p", {"min_patch_pixel": 3})
