"""The nested (SAM-automatic-generator-like) simulated masks and the mask-set statistics."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.masks.test_masks import _object_masks, make_scene, tiny_instance_map, tiny_objects
from trace3d.errors import ConfigError
from trace3d.masks import NestedParams, SimulateParams, frame_rng, nested_view_masks, parse_params, run_masks
from trace3d.masks.nested import cut_region, duplicate_nms, edge_pieces, pairwise_intersections
from trace3d.masks.patches import PatchParams
from trace3d.masks.stats import CALIBRATION_TARGETS, check_targets, scene_statistics, view_statistics
from trace3d.scene import Scene

H, W = 72, 96


def tiny_image(view: int) -> np.ndarray:
    """[H, W, 3] uint8 image of the tiny scene: each leaf a flat grey, the table top two-toned."""
    ids = tiny_instance_map(view).astype(np.int64)
    grey = (40 + (ids * 37) % 180).astype(np.uint8)
    img = np.repeat(grey[..., None], 3, axis=2)
    top = ids == 11
    left = np.zeros_like(top)
    left[:, : 40 + 2 * view] = True
    img[top & left] = 230  # a texture edge inside the table top
    return img


def _masks(view: int, params: NestedParams, objects=None):
    return nested_view_masks(tiny_instance_map(view), tiny_image(view), objects or tiny_objects(),
                             frame_rng(params.seed, view), params)


class TestNestedModel:
    def test_deterministic_from_seed(self):
        p = NestedParams(seed=4, inconsistency=0.8)
        a, sa = _masks(1, p)
        b, sb = _masks(1, p)
        assert np.array_equal(a, b) and np.array_equal(sa, sb)
        differs = False
        for seed in (5, 6, 7):
            c, _ = _masks(1, NestedParams(seed=seed, inconsistency=0.8))
            differs |= c.shape != a.shape or not np.array_equal(c, a)
        assert differs

    @pytest.mark.parametrize("replica_like", [False, True])
    def test_inconsistency_zero_gives_exact_object_masks(self, replica_like):
        objects = tiny_objects(replica_like)
        for v in range(3):
            masks, scores = _masks(v, NestedParams(inconsistency=0.0, seed=v), objects)
            got = {m.tobytes() for m in masks}
            assert got == _object_masks(tiny_instance_map(v), objects, NestedParams().min_mask_pixels)
            assert np.all(scores == 1.0)

    @staticmethod
    def _enclosed_share(params: NestedParams) -> tuple[int, float]:
        """(count, share) of the masks inside one object and smaller than it (parts, subparts) that
        lie >= 90 % inside a larger mask, over 6 views."""
        lut = tiny_objects().lookup("object")
        enclosed = total = 0
        for v in range(6):
            masks, _ = _masks(v, params)
            obj = lut[tiny_instance_map(v)]
            areas = masks.sum(axis=(1, 2))
            inter = pairwise_intersections(masks)
            for m in range(len(masks)):
                owners, counts = np.unique(obj[masks[m]], return_counts=True)
                owner = owners[np.argmax(counts)]
                if owner == 0 or counts.max() < 0.8 * areas[m] or areas[m] >= 0.85 * (obj == owner).sum():
                    continue  # not inside one object, or the whole object itself
                total += 1
                enclosed += bool(np.any((inter[m] >= 0.9 * areas[m]) & (areas > areas[m])))
        return total, enclosed / max(total, 1)

    def test_masks_are_nested(self):
        """Nearly every part / subpart mask has an enclosing mask when borders are exact (the rest: a
        part that is most of its object suppresses the whole as a duplicate, as SAM's NMS does), and
        most do with the default ragged borders (a part dilated where its whole is eroded sticks out)."""
        forced = dict(part_rate=1.0, subpart_rate=1.0, whole_drop_rate=0.0, stuff_whole_drop_rate=0.0)
        total, share = self._enclosed_share(NestedParams(jitter_pixels=0, warp_pixels=0.0, **forced))
        assert total >= 12 and share >= 0.9
        total, share = self._enclosed_share(NestedParams(jitter_pixels=0, warp_pixels=0.0, nms_iou=1.0, **forced))
        assert total >= 12 and share == 1.0
        total, share = self._enclosed_share(NestedParams(**forced))
        assert total >= 12 and share >= 0.7
        # dropping the whole (rate 1) leaves parts without their enclosing mask: the measure sees it
        total, share = self._enclosed_share(NestedParams(jitter_pixels=0, warp_pixels=0.0, group_rate=0.0,
                                                         part_rate=1.0, subpart_rate=1.0, whole_drop_rate=1.0, stuff_whole_drop_rate=1.0,
                                                         drop_cover=0.0))
        assert total >= 12 and share < 0.7

    def test_subparts_and_levels_vary_across_views(self):
        """At the default level the set of levels changes from view to view (the point of the model)."""
        p = NestedParams()
        counts = {len(_masks(v, p)[0]) for v in range(6)}
        assert len(counts) >= 2

    def test_rate_mapping(self):
        p = NestedParams(part_rate=0.4)
        assert p.rate("part") == pytest.approx(0.4)
        assert NestedParams(part_rate=0.4, inconsistency=0.0).rate("part") == 0.0
        assert NestedParams(part_rate=0.4, inconsistency=1.0).rate("part") == pytest.approx(1 - 0.6 ** 2)
        assert NestedParams(part_rate=0.4, inconsistency=0.25).rate("part") < 0.4

    def test_default_inconsistency_matches_the_workflow(self):
        # rules/common.smk's robustness levels assume the simulated source's default level is 0.5
        assert NestedParams().inconsistency == SimulateParams().inconsistency == 0.5


class TestCuts:
    def test_edge_pieces_follow_the_luminance_edge(self):
        region = np.zeros((20, 30), bool)
        region[2:18, 3:27] = True
        lum = np.full((20, 30), 0.2, np.float32)
        lum[:, 15:] = 0.8
        pieces = edge_pieces(region, lum, 4, 3)
        assert len(pieces) == 2
        halves = {(region & (np.arange(30) < 15)).tobytes(), (region & (np.arange(30) >= 15)).tobytes()}
        assert {p.tobytes() for p in pieces} == halves

    def test_flat_region_gets_a_smooth_cut(self):
        region = np.zeros((40, 50), bool)
        region[5:35, 5:45] = True
        lum = np.full((40, 50), 0.5, np.float32)
        pieces = cut_region(region, lum, 2, NestedParams(), np.random.default_rng(0))
        assert len(pieces) == 2
        assert not (pieces[0] & pieces[1]).any()
        assert np.array_equal(pieces[0] | pieces[1], region)
        assert min(p.sum() for p in pieces) > 0.2 * region.sum()  # a median cut: halves of similar size

    def test_pairwise_intersections_match_brute_force(self):
        rng = np.random.default_rng(1)
        for M in (1, 9, 70):
            masks = rng.random((M, 12, 17)) > 0.6
            flat = masks.reshape(M, -1).astype(np.int64)
            assert np.array_equal(pairwise_intersections(masks), flat @ flat.T)

    def test_duplicate_nms_keeps_the_higher_score(self):
        a = np.zeros((3, 10, 10), bool)
        a[0, :5] = True
        a[1, :5, :9] = True  # IoU 0.9 with mask 0
        a[2, 5:] = True
        keep = duplicate_nms(a, np.array([0.9, 0.95, 0.5]), 0.7)
        assert keep.tolist() == [False, True, True]


class TestParams:
    @pytest.mark.parametrize("params, words", [
        ({"model": "nested", "part_rate": 1.5}, "part_rate"),
        ({"model": "nested", "multi_rate": 0.3}, "multi_rate"),   # a one_level key
        ({"model": "nested", "max_subparts": 1}, "max_subparts"),
        ({"model": "nestd"}, "one_level"),
        ({"model": "one_level", "subpart_rate": 0.3}, "subpart_rate"),
    ])
    def test_wrong_parameters_refused_in_one_sentence(self, params, words):
        with pytest.raises(ConfigError) as err:
            parse_params("simulated", params)
        message = str(err.value)
        assert words in message and message.count("\n") == 0

    def test_model_selects_the_parameter_set(self):
        assert isinstance(parse_params("simulated", {"model": "nested"}), NestedParams)
        assert isinstance(parse_params("simulated", {}), SimulateParams)
        assert isinstance(parse_params("simulated", None), SimulateParams)


def test_run_masks_writes_the_nested_model(tmp_path):
    scene = make_scene(tmp_path / "scene", views=3)
    run_masks(scene, tmp_path / "masks", "simulated", {"model": "nested", "seed": 2})
    summary = json.loads((tmp_path / "masks" / "masks.json").read_text())
    assert summary["params"]["model"] == "nested" and summary["params"]["seed"] == 2
    stats = scene_statistics(scene, tmp_path / "masks")
    assert stats["views"] == 3
    assert stats["statistics"]["masks"]["mean"] == pytest.approx(np.mean(list(summary["masks_per_view"].values())))


class TestStatistics:
    def test_view_statistics_by_hand(self):
        masks = np.zeros((3, 4, 6), bool)
        masks[0, :, :4] = True      # whole object (16 px)
        masks[1, :, :2] = True      # its left part (8 px), nested
        masks[2, :2, 5] = True      # a mask on the other object
        inst = np.ones((4, 6), np.uint16)
        inst[:, 4:] = 2
        s = view_statistics(masks, inst, None, min_object_pixels=1)
        assert s["masks"] == 3
        assert s["multi_covered"] == pytest.approx(8 / 24)
        assert s["uncovered"] == pytest.approx(6 / 24)
        assert s["nested"] == pytest.approx(1 / 3)
        assert s["objects"] == 2 and s["masks_per_object"] == 1.5
        assert s["whole_fraction"] == 0.5  # object 2 (8 px) against mask 2 (2 px): IoU 0.25, not matched
        # patches: left part, the rest of the whole, the small mask (8, 8, 2 px) without absorption;
        # with the patch step's defaults (pieces under 20 px absorbed inside a common coarser mask) the
        # two halves of the whole become one, and the 2 px mask, inside no coarser mask, stays
        exact = view_statistics(masks, inst, None, PatchParams(min_patch_pixels=0, min_patch_width=0), 1)
        assert exact["patches"] == 3 and s["patches"] == 2
        assert exact["patches_per_object"] == pytest.approx((2 + 1) / 2)

    def test_whole_fraction_counts_iou(self):
        masks = np.zeros((1, 4, 6), bool)
        masks[0, :, :4] = True
        inst = np.ones((4, 6), np.uint16)
        inst[:, 4:] = 2
        s = view_statistics(masks, inst, None, min_object_pixels=1)
        assert s["whole_fraction"] == 0.5
        assert s["patches_per_object"] == pytest.approx(0.5)  # one patch, owned by object 1


@pytest.fixture(scope="module")
def small_room(tmp_path_factory) -> Scene:
    from trace3d.datasets.synthetic import SyntheticParams, generate_scene

    root = tmp_path_factory.mktemp("room") / "scene"
    generate_scene(root, SyntheticParams(seed=0, num_views=8, supersample=1))
    return Scene.read(root)


def _tolerant_check(stats: dict) -> dict[str, bool]:
    """Targets hit within the accepted range widened by two standard errors of the view mean."""
    views = 8
    out = {}
    for name, (_, low, high) in CALIBRATION_TARGETS.items():
        mean, std = stats[name]["mean"], stats[name]["std"]
        slack = 2.0 * std / np.sqrt(views)
        out[name] = low - slack <= mean <= high + slack
    return out


def test_calibrated_model_hits_its_targets_on_a_small_room(small_room, tmp_path):
    """The calibrated defaults meet every target (ranges of docs/masks_calibration.md widened by two
    standard errors, since 8 views are a small sample); the one_level model, as a control, does not."""
    run_masks(small_room, tmp_path / "nested", "simulated", {"model": "nested"})
    nested = scene_statistics(small_room, tmp_path / "nested")["statistics"]
    assert all(_tolerant_check(nested).values()), check_targets(nested)
    run_masks(small_room, tmp_path / "one", "simulated", {})
    one = scene_statistics(small_room, tmp_path / "one")["statistics"]
    assert sum(_tolerant_check(one).values()) <= 2


def test_config_schema_knows_the_model_key():
    """A config selects the model with masks.simulated.model; a misspelled model is refused before anything runs."""
    import jsonschema
    import yaml

    repo = Path(__file__).resolve().parents[2]
    # the config's masks section is the generated steps schema's (python -m trace3d.tooling.schema)
    schema = yaml.safe_load((repo / "workflow" / "schemas" / "steps.schema.yaml").read_text())["$defs"]["masks"]
    masks = {"source": "simulated", "simulated": {"model": "nested", "seed": 1}}
    jsonschema.validate(masks, schema)
    masks["simulated"]["model"] = "nestd"
    with pytest.raises(jsonschema.ValidationError, match="is not one of"):
        jsonschema.validate(masks, schema)
