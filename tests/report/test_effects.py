"""The study table (trace3d/report/effects.py): intervals, paired effects and gap shares on hand-made
metrics.json files whose answers are computed by hand."""

import json
import math
import re

import numpy as np
import pytest

from trace3d.errors import Trace3DError
from trace3d.report import effects


def _metrics(folder, object_miou, nvs_miou, pq=None):
    folder.mkdir(parents=True)
    data = {"extraction": {"mIoU": object_miou, "PSNR": 20.0}, "nvs": {"mIoU": nvs_miou, "mAcc": 0.9}}
    if pq is not None:
        data["panoptic"] = {"PQ": pq}
    (folder / "metrics.json").write_text(json.dumps(data))
    return str(folder)


def test_t_interval_matches_the_textbook_formula():
    mean, half, n = effects.t_interval([1.0, 2.0, 3.0, 4.0, float("nan")])
    assert n == 4 and mean == pytest.approx(2.5)
    # t_{0.975, 3} = 3.182446; sample std = 1.290994
    assert half == pytest.approx(3.182446 * 1.290994 / 2.0, rel=1e-5)
    assert math.isnan(effects.t_interval([5.0])[1])
    assert effects.t_interval([])[2] == 0


@pytest.fixture
def spec(tmp_path):
    # two rooms x two seeds; raw = both_off, oracle = both_off on exact masks
    values = {  # (masks, variant) -> object mIoU per (room, seed)
        ("default", "both_off"): [0.40, 0.42, 0.50, 0.52],
        ("default", "no_merge"): [0.42, 0.44, 0.52, 0.54],
        ("default", "full"): [0.50, 0.52, 0.60, 0.61],
        ("oracle", "both_off"): [0.60, 0.62, 0.70, 0.72],
    }
    runs = []
    for (masks, variant), vals in values.items():
        for k, (room, seed) in enumerate([("a", 0), ("a", 1), ("b", 0), ("b", 1)]):
            folder = tmp_path / masks / variant / f"{room}{seed}"
            runs.append({"room": room, "masks": masks, "variant": variant, "seed": seed,
                         "eval": _metrics(folder, vals[k], 0.8, pq=0.5 if variant == "full" else None)})
    return {"runs": runs, "oracle": ["both_off"], "raw": "both_off"}


def test_gap_share_and_paired_effects(spec):
    frame = effects.collect(spec)
    summary, paired = effects.summarize(frame, spec["oracle"], spec["raw"])
    full = summary[(summary.masks == "default") & (summary.variant == "full")].iloc[0]
    # mean(full - raw) = (10 + 10 + 10 + 9) / 4 = 9.75 points; mean(oracle - raw) = 20 points
    assert full["object mIoU gap share"] == pytest.approx(9.75 / 20.0)
    raw = summary[(summary.masks == "default") & (summary.variant == "both_off")].iloc[0]
    assert raw["object mIoU gap share"] == pytest.approx(0.0)
    assert full["object mIoU mean"] == pytest.approx(55.75)
    # the merge effect with refinement on: full - no_merge = 8, 8, 8, 7 points, all four wins
    row = paired[(paired.effect.str.startswith("merge (refine on)")) & (paired.metric == "object mIoU")].iloc[0]
    assert row["mean"] == pytest.approx(7.75) and row["wins"] == 4 and row["n"] == 4
    diffs = np.array([8.0, 8.0, 8.0, 7.0])
    assert row["ci95"] == pytest.approx(3.182446 * diffs.std(ddof=1) / 2.0, rel=1e-5)
    # over rooms alone: room a 8.0, room b 7.5 -> t_{0.975,1} = 12.706205
    assert row["rooms ci95"] == pytest.approx(12.706205 * np.std([8.0, 7.5], ddof=1) / math.sqrt(2), rel=1e-5)
    # a metric no run has stays out; one only some runs have is there, NaN elsewhere
    assert "object mIoU 1pt mean" not in summary
    assert full["PQ scene mean"] == pytest.approx(50.0)
    assert math.isnan(raw["PQ scene mean"])


def test_segment_and_click_are_read_per_mask_model(tmp_path):
    # the metrics without ground truth (the segment step's PQ^scene, one click's IoU) under two mask models
    runs = []
    for masks, seg, click in (("geometry", [0.30, 0.34], [0.60, 0.64]), ("oracle", [0.70, 0.74], [0.80, 0.90])):
        for k, room in enumerate(("a", "b")):
            folder = tmp_path / masks / room
            folder.mkdir(parents=True)
            data = {"extraction": {"mIoU": 0.5}, "nvs": {"mIoU": 0.8}, "segment": {"PQ": seg[k], "SQ": 0.9},
                    "click": {"mIoU": click[k], "objects": 3}}
            (folder / "metrics.json").write_text(json.dumps(data))
            runs.append({"room": room, "masks": masks, "variant": "both_off", "seed": 0, "eval": str(folder)})
    frame = effects.collect({"runs": runs})
    summary, _ = effects.summarize(frame, ["both_off"], "both_off")
    geo = summary[summary.masks == "geometry"].iloc[0]
    assert geo["PQ segment mean"] == pytest.approx(32.0) and geo["click IoU mean"] == pytest.approx(62.0)
    # the gap to exact masks: segment 40 points, click 23 points; the raw patches close none of it
    assert geo["PQ segment gap share"] == pytest.approx(0.0) and geo["click IoU gap share"] == pytest.approx(0.0)
    assert summary[summary.masks == "oracle"].iloc[0]["click IoU mean"] == pytest.approx(85.0)


def test_writes_table_csv_and_plot(spec, tmp_path):
    out = tmp_path / "tables" / "effects.md"
    effects.write_effects(spec, out, tmp_path / "plots" / "effects.png")
    text = out.read_text()
    assert "*Masks: default*" in text and "*Masks: oracle*" in text
    assert re.search(r"\| 49( ± \d+)? % \|", text)  # full's gap share on object mIoU, 9.75 / 20
    assert (tmp_path / "tables" / "effects.csv").read_text().startswith("masks,variant")
    assert (tmp_path / "tables" / "effects_runs.csv").is_file()
    # the raw variant under each mask model, beside the effects plot
    from PIL import Image

    masks_png = tmp_path / "plots" / "effects_masks.png"
    assert masks_png == effects.masks_plot_path(tmp_path / "plots" / "effects.png")
    assert Image.open(masks_png).size[0] > 300
    assert (tmp_path / "plots" / "effects.png").read_bytes()[:4] == b"\x89PNG"


def test_bad_spec_is_one_sentence(tmp_path):
    with pytest.raises(Trace3DError, match="'runs' must be a non-empty list"):
        effects.collect({"runs": []})
    with pytest.raises(Trace3DError, match="lacks seed"):
        effects.collect({"runs": [{"room": "a", "masks": "default", "variant": "full", "eval": str(tmp_path)}]})


def test_no_gap_share_where_exact_masks_do_not_help(spec):
    """NVS mIoU is 0.8 for every run here: exact masks gain nothing, so no variant has a share of it."""
    frame = effects.collect(spec)
    summary, _ = effects.summarize(frame, spec["oracle"], spec["raw"])
    full = summary[(summary.masks == "default") & (summary.variant == "full")].iloc[0]
    assert math.isnan(full["NVS mIoU gap share"]) and not math.isnan(full["object mIoU gap share"])


def test_gap_share_uses_every_seed_when_the_oracle_has_fewer(spec):
    """The oracle run on seed 0 only: its gap per room comes from seed 0, the variant's gain from both seeds."""
    spec = dict(spec, runs=[r for r in spec["runs"] if not (r["masks"] == "oracle" and r["seed"] == 1)])
    frame = effects.collect(spec)
    summary, _ = effects.summarize(frame, spec["oracle"], spec["raw"])
    full = summary[(summary.masks == "default") & (summary.variant == "full")].iloc[0]
    # gains: room a (10 + 10) / 2 = 10, room b (10 + 9) / 2 = 9.5; oracle gaps on seed 0: a 20, b 20
    assert full["object mIoU gap share"] == pytest.approx(9.75 / 20.0)
    # a seed-1 value of full that changes moves the share: the seed-1 runs are not dropped
    frame.loc[(frame.masks == "default") & (frame.variant == "full") & (frame.seed == 1), "object mIoU"] += 4.0
    summary, _ = effects.summarize(frame, spec["oracle"], spec["raw"])
    full = summary[(summary.masks == "default") & (summary.variant == "full")].iloc[0]
    assert full["object mIoU gap share"] == pytest.approx(11.75 / 20.0)
