"""The robustness table and plot (trace3d.report.robustness) from hand-made evaluate outputs."""

from __future__ import annotations

import json
import re

import pandas as pd
import pytest

from trace3d.errors import Trace3DError
from trace3d.report.robustness import write_robustness


def _metrics(folder, obj, nvs, psnr=20.0):
    folder.mkdir(parents=True)
    (folder / "metrics.json").write_text(json.dumps({
        "protocol": "standard", "extraction": {"mIoU": obj, "PSNR": psnr}, "nvs": {"mIoU": nvs, "mAcc": 0.9}}))
    return str(folder)


def _merge(folder, ari_before, ari_after):
    folder.mkdir(parents=True)
    (folder / "merge.json").write_text(json.dumps({"ground_truth": {
        "before": {"ari": ari_before, "straddling": 0.1}, "after": {"ari": ari_after, "straddling": 0.2}}}))
    return str(folder)


@pytest.fixture
def spec(tmp_path):
    runs, merges = [], []
    values = {("r1", 0.0, "full"): (0.6, 0.9), ("r1", 1.0, "full"): (0.4, 0.7),
              ("r2", 0.0, "full"): (0.8, 0.8), ("r2", 1.0, "full"): (0.2, 0.5),
              ("r1", 0.0, "base"): (0.5, 0.9), ("r1", 1.0, "base"): (0.5, 0.6),
              ("r2", 0.0, "base"): (0.5, 0.7), ("r2", 1.0, "base"): (0.3, 0.6)}
    for (scene, level, variant), (obj, nvs) in values.items():
        runs.append({"scene": scene, "level": level, "variant": variant,
                     "eval": _metrics(tmp_path / f"{scene}@{level}" / variant / "eval", obj, nvs)})
    for scene in ("r1", "r2"):
        for level, (b, a) in ((0.0, (0.9, 0.95)), (1.0, (0.5, 0.7))):
            merges.append({"scene": scene, "level": level, "merge": _merge(tmp_path / f"{scene}@{level}" / "m", b, a)})
    return {"runs": runs, "merges": merges}


def test_table_is_the_mean_over_rooms_per_level_and_variant(tmp_path, spec):
    summary = write_robustness(spec, tmp_path / "out" / "robustness.md", tmp_path / "out" / "robustness.png")
    got = {(r.level, r.variant): (r["object mIoU"], r["object mIoU std"], r["NVS mIoU"]) for _, r in summary.iterrows()}
    assert got[(0.0, "full")] == pytest.approx((70.0, 10.0, 85.0))
    assert got[(1.0, "full")] == pytest.approx((30.0, 10.0, 60.0))
    assert got[(1.0, "base")] == pytest.approx((40.0, 10.0, 60.0))
    text = (tmp_path / "out" / "robustness.md").read_text()
    assert "| full" not in text.split("## Object mIoU")[0]  # variants are columns of the level rows
    assert "70.0" in text and "40.0" in text and "r1, r2" in text
    assert re.search(r"\|\s+1\s+\|\s+30\.0", text)  # levels printed as given (1, not 1.0), then full
    assert "0.700" in text  # ARI of the merged maps at level 1, mean over the rooms
    csv = pd.read_csv(tmp_path / "out" / "robustness.csv")
    assert len(csv) == 8 and set(csv["variant"]) == {"full", "base"}
    assert (tmp_path / "out" / "robustness.png").stat().st_size > 1000


def test_same_inputs_same_table(tmp_path, spec):
    write_robustness(spec, tmp_path / "a.md")
    write_robustness(spec, tmp_path / "b.md")
    assert (tmp_path / "a.md").read_text() == (tmp_path / "b.md").read_text()
    assert (tmp_path / "a.csv").read_text() == (tmp_path / "b.csv").read_text()


def test_missing_evaluation_is_named(tmp_path, spec):
    spec["runs"][3]["eval"] = str(tmp_path / "nowhere")
    with pytest.raises(Trace3DError, match="nowhere/metrics.json: result file is missing"):
        write_robustness(spec, tmp_path / "t.md")
    assert not (tmp_path / "t.md").exists()


def test_bad_spec_is_refused(tmp_path):
    with pytest.raises(Trace3DError, match="'runs' must be a non-empty list"):
        write_robustness({"runs": []}, tmp_path / "t.md")
    with pytest.raises(Trace3DError, match="lacks eval"):
        write_robustness({"runs": [{"scene": "a", "level": 0, "variant": "v"}]}, tmp_path / "t.md")


def test_paired_effects_per_level(tmp_path):
    # two rooms, three variants, two levels: full - no_merge is +10 and +20 points at level 0.5 (mean 15),
    # -5 and -5 at level 1 (no spread: interval 0); PQ is read where present
    runs = []
    values = {("r1", 0.5): {"full": 0.6, "no_merge": 0.5, "both_off": 0.4},
              ("r2", 0.5): {"full": 0.7, "no_merge": 0.5, "both_off": 0.5},
              ("r1", 1.0): {"full": 0.4, "no_merge": 0.45, "both_off": 0.3},
              ("r2", 1.0): {"full": 0.3, "no_merge": 0.35, "both_off": 0.3}}
    for (scene, level), by_variant in values.items():
        for variant, obj in by_variant.items():
            folder = tmp_path / f"{scene}@{level}" / variant / "eval"
            folder.mkdir(parents=True)
            (folder / "metrics.json").write_text(json.dumps({
                "protocol": "standard", "extraction": {"mIoU": obj, "PSNR": 20.0}, "nvs": {"mIoU": obj},
                "panoptic": {"PQ": obj / 2}, "single_point": {"nvs": {"mIoU": obj}}}))
            runs.append({"scene": scene, "level": level, "variant": variant, "eval": str(folder)})
    write_robustness({"runs": runs}, tmp_path / "t.md", tmp_path / "t.png")
    text = (tmp_path / "t.md").read_text()
    merge = text.split("### merge: full - no_merge")[1].split("###")[0]
    # level 0.5: differences 10 and 20 -> mean 15, t(0.975, 1) * std(ddof=1) / sqrt 2 = 12.706 * 7.071 / 1.414
    assert re.search(r"\|\s+0\.5\s+\|\s+\+15\.0 ± 63\.5 \(2/2\)", merge)
    assert re.search(r"\|\s+1\s+\|\s+-5\.0 ± 0\.0 \(0/2\)", merge)
    assert "+7.5 ± 31.8 (2/2)" in merge  # PQ = half of the object mIoU here
    assert "### density control: no_merge - both_off" in text and "## PQ^scene" in text
    csv = pd.read_csv(tmp_path / "t.csv")
    assert csv["PQ scene"].notna().all() and csv["NVS mIoU 1pt"].notna().all()
    assert (tmp_path / "t.png").stat().st_size > 1000
