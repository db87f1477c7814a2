"""Paper-layout tables from hand-written metrics.json files: values, layout, determinism."""

from __future__ import annotations

import csv
import json

import pytest

from trace3d.errors import SceneFormatError, Trace3DError
from trace3d.report.tables import build_tables, write_tables


def metrics(obj_miou, psnr, nvs_miou, nvs_macc, variant, protocol="standard", method="labels"):
    return {"variant": variant, "protocol": protocol, "lift": {"method": method},
            "extraction": {"mIoU": obj_miou, "PSNR": psnr}, "nvs": {"mIoU": nvs_miou, "mAcc": nvs_macc}}


FULL = {"variant": "full", "preset": "paper", "consistent_masks": True, "density_control": True}
NO_REFINE = {"variant": "no_refine", "preset": "paper", "consistent_masks": True, "density_control": False}
BOTH_OFF = {"variant": "both_off", "preset": "paper", "consistent_masks": False, "density_control": False}
OFFICIAL = {"variant": "official", "preset": "official", "consistent_masks": True, "density_control": True}


def write_results(root):
    values = {
        ("room0", "full"): metrics(0.80, 22.0, 0.90, 0.98, FULL),
        ("room1", "full"): metrics(0.70, 20.0, 0.80, 0.96, FULL),
        ("room0", "no_refine"): metrics(0.60, 19.0, 0.85, 0.97, NO_REFINE),
        ("room1", "no_refine"): metrics(0.50, 18.0, 0.75, 0.95, NO_REFINE),
        ("room0", "both_off"): metrics(0.40, 17.0, 0.70, None, BOTH_OFF),
        ("room0", "official"): metrics(0.75, 21.0, 0.88, 0.90, OFFICIAL, protocol="official"),
        ("room1", "official"): metrics(0.65, 19.0, 0.78, 0.92, OFFICIAL, protocol="official"),
    }
    for (scene, variant), data in values.items():
        path = root / scene / variant / "eval" / "metrics.json"
        path.parent.mkdir(parents=True)
        path.write_text(json.dumps(data))
    (root / "room0" / "scene").mkdir()  # other folders are ignored
    return values


def test_table_values_and_layout(tmp_path):
    write_results(tmp_path / "results")
    t2, t2p, t3, t5 = build_tables(tmp_path / "results")
    assert t2.header == ["Method", "room0", "room1", "mIoU", "PSNR"]
    rows = {r[0]: r for r in t2.rows}
    assert list(rows) == ["both_off", "full", "no_refine", "official"]  # variants as rows, sorted
    assert rows["full"] == ["full", "80.0", "70.0", "75.0 ± 5.0", "21.0 ± 1.0"]
    assert rows["both_off"] == ["both_off", "40.0", "–", "40.0 ± 0.0", "17.0 ± 0.0"]  # missing scene
    assert {r[0]: r for r in t2p.rows}["no_refine"] == ["no_refine", "19.0", "18.0", "18.5 ± 0.5"]
    t3_rows = {r[0]: r for r in t3.rows}
    assert t3.header == ["Method", "room0", "room1", "mIoU", "mAcc"]
    assert t3_rows["full"] == ["full", "90.0", "80.0", "85.0 ± 5.0", "97.0 ± 1.0"]
    assert t3_rows["both_off"][-1] == "–"  # no mAcc at all
    # Table 5: the grid of the `full` group (preset paper); the official preset is not a grid row;
    # the paper's row order; the (False, True) combination is missing and left out
    assert [r[0] for r in t5.rows] == ["both_off", "no_refine", "full"]
    assert t5.rows[2] == ["full", "labels", "✓", "✓", "85.0 ± 5.0", "75.0 ± 5.0", "21.0 ± 1.0"]
    assert t5.rows[0][2:4] == ["×", "×"]
    assert "official" in t2.notes[0] and "standard" in t2.notes[0]


def test_files_csv_latex_and_determinism(tmp_path):
    write_results(tmp_path / "results")
    written = write_tables(tmp_path / "results", tmp_path / "tables")
    names = sorted(p.name for p in written)
    assert names == sorted(f"{t}.{e}" for t in ("table2", "table2_psnr", "table3", "table5")
                           for e in ("md", "csv", "tex"))
    first = {p.name: p.read_bytes() for p in written}
    write_tables(tmp_path / "results", tmp_path / "tables")
    assert {p.name: p.read_bytes() for p in written} == first
    rows = list(csv.DictReader((tmp_path / "tables" / "table2.csv").open()))
    full = next(r for r in rows if r["method"] == "full")
    assert float(full["room0"]) == pytest.approx(80.0) and float(full["object_miou_mean"]) == pytest.approx(75.0)
    assert float(full["object_miou_std"]) == pytest.approx(5.0) and float(full["psnr_mean"]) == pytest.approx(21.0)
    assert next(r for r in rows if r["method"] == "both_off")["room1"] == ""
    tex = (tmp_path / "tables" / "table5.tex").read_text()
    assert "\\begin{tabular}{lcccccc}" in tex and "$\\checkmark$" in tex and "no\\_refine" in tex
    assert "75.0 $\\pm$ 5.0" in tex
    md = (tmp_path / "tables" / "table3.md").read_text()
    assert "| full | 90.0 | 80.0 | 85.0 ± 5.0 | 97.0 ± 1.0 |" in md


def test_bad_inputs(tmp_path):
    with pytest.raises(Trace3DError, match="does not exist"):
        build_tables(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(Trace3DError, match="no \\*/\\*/eval/metrics.json"):
        build_tables(tmp_path / "empty")
    bad = tmp_path / "bad" / "room0" / "full" / "eval" / "metrics.json"
    bad.parent.mkdir(parents=True)
    bad.write_text("{not json")
    with pytest.raises(SceneFormatError, match="not valid JSON"):
        build_tables(tmp_path / "bad")
    bad.write_text(json.dumps({"nvs": {}}))
    with pytest.raises(SceneFormatError, match="'extraction' section is missing"):
        build_tables(tmp_path / "bad")


def test_cli_tables(tmp_path):
    from trace3d.cli import main

    write_results(tmp_path / "results")
    assert main(["tables", "--results", str(tmp_path / "results"), "--out", str(tmp_path / "results" / "tables")]) == 0
    assert (tmp_path / "results" / "tables" / "table5.md").is_file()
    assert main(["tables", "--results", str(tmp_path / "none"), "--out", str(tmp_path / "t")]) == 2
    # only the listed evaluate folders
    only = [str(tmp_path / "results" / s / "full" / "eval") for s in ("room0", "room1")]
    assert main(["tables", "--results", str(tmp_path / "results"), "--out", str(tmp_path / "only"),
                 "--evals", *only]) == 0
    text = (tmp_path / "only" / "table2.md").read_text()
    assert "| full |" in text and "no_refine" not in text
    assert main(["tables", "--results", str(tmp_path / "results"), "--out", str(tmp_path / "x"), "--evals",
                 str(tmp_path / "results" / "room1" / "both_off" / "eval")]) == 2


def test_grid_groups_settings_written_before_a_key_existed(tmp_path):
    """A variant evaluated before `overlay`/`lifting` joined the settings groups with one that spells the
    defaults out; a real difference (overlay on) still leaves the grid."""
    root = tmp_path / "results"
    values = {
        "full": metrics(0.8, 22.0, 0.9, 0.98, FULL),
        "no_refine": metrics(0.6, 19.0, 0.85, 0.97, {**NO_REFINE, "overlay": False, "lifting": "contrastive"}),
        "egolifter": metrics(0.5, 18.0, 0.8, 0.97, {**BOTH_OFF, "variant": "egolifter", "overlay": True}),
    }
    for variant, data in values.items():
        path = root / "room0" / variant / "eval" / "metrics.json"
        path.parent.mkdir(parents=True)
        path.write_text(json.dumps(data))
    t5 = build_tables(root)[3]
    assert [r[0] for r in t5.rows] == ["no_refine", "full"]


def test_grid_takes_the_self_prompting_row_above_its_contrastive_twin(tmp_path):
    """As the paper's Table 5 has an "SP." row: a self-prompting variant of the full settings joins the grid
    above `full`; a closed-form (labels) variant of the same switches does not."""
    root = tmp_path / "results"
    values = {
        "full": metrics(0.8, 22.0, 0.9, 0.98, {**FULL, "lifting": "contrastive"}, method="contrastive"),
        "no_refine": metrics(0.6, 19.0, 0.85, 0.97, {**NO_REFINE, "lifting": "contrastive"}, method="contrastive"),
        "self_prompt": metrics(0.7, 20.0, 0.6, 0.9, {**FULL, "variant": "self_prompt", "lifting": "self_prompt"},
                               method="self_prompt"),
        "flashsplat": metrics(0.5, 18.0, 0.8, 0.97, {**NO_REFINE, "variant": "flashsplat", "lifting": "labels"},
                              method="labels"),
    }
    for variant, data in values.items():
        path = root / "room0" / variant / "eval" / "metrics.json"
        path.parent.mkdir(parents=True)
        path.write_text(json.dumps(data))
    t5 = build_tables(root)[3]
    assert [r[0] for r in t5.rows] == ["no_refine", "self_prompt", "full"]
    assert t5.rows[1] == ["self_prompt", "self_prompt", "✓", "✓", "60.0 ± 0.0", "70.0 ± 0.0", "20.0 ± 0.0"]
    assert "flashsplat" in {r[0] for r in build_tables(root)[0].rows}  # still a row of Table 2
