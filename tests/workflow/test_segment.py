"""A capture with no masks and no ground truth through the whole DAG: ``transforms.json`` (each
convention) -> graph masks -> fit -> trace, merge, refine -> contrastive lift -> ``segment`` (objects'
PLYs, turntables, contact sheet in the report)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import yaml

from tests.datasets.test_transforms import H, W, write_blender, write_instant_ngp, write_nerfstudio
from tests.workflow.test_workflow import SNAKEMAKE, run_snakemake
from trace3d.cli import main as cli_main
from trace3d.errors import ConfigError
from trace3d.gaussians import GaussianModel
from trace3d.scene import Scene
from trace3d.segment import SegmentParams, contact_sheet

WRITERS = {"blender": write_blender, "instant-ngp": write_instant_ngp, "nerfstudio": write_nerfstudio}

# tiny: a 40x30 room, 6 views; dataset poses (no COLMAP), a 40-iteration fit from random points
CAPTURE_DEFAULTS = {
    "poses": {"mode": "dataset", "dataset_points": "none"},
    "masks": {"source": "graph"},
    "gaussians": {"schedule_scale": 1.0, "iterations": 40, "densify_from": 10, "densify_until": 30,
                  "densify_interval": 10, "normal_from": 20, "sh_degree": 0, "device": "cpu", "init": "random",
                  "random_init_count": 1500},
    "refine": {"iterations": 20, "detect_at": [1, 10], "schedule_scale": 1.0, "highlight_views": 1},
    "lift": {"iterations": 60, "pixels": 256, "pool_pixels": 512, "pca_views": 1},
    "segment": {"samples": 2000, "min_share": 0.01, "min_gaussians": 5, "turntable_views": 3, "turntable_size": 24},
}


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    from trace3d.scene import Scene

    root = tmp_path_factory.mktemp("room")
    params = json.dumps({"seed": 2, "width": W, "height": H, "num_views": 6, "test_every": 3, "num_objects": 4,
                         "supersample": 1})
    assert cli_main(["scene", "synthetic", "--out", str(root / "scene"), "--params", params]) == 0
    return Scene.read(root / "scene")


@pytest.mark.slow
@pytest.mark.skipif(SNAKEMAKE is None, reason="snakemake is not installed")
@pytest.mark.xdist_group("whole_dag")  # whole-DAG runs take turns on one worker (tests/conftest.py)
def test_transforms_captures_run_the_whole_dag_to_object_plys(room, tmp_path):
    """An instant-ngp capture (the convention whose world is moved: scaled, rotated, offset) through the
    whole DAG: it ends in object PLYs that read back, the contact sheet goes into the report, and no
    evaluation runs (no ground truth). The other two conventions through the workflow's scene step only:
    after the import every step reads the same scene files whatever the convention (each convention's
    import is checked against the room in tests/datasets/test_transforms.py), and a whole DAG per capture cost
    ~11 more jobs each."""
    captures = tmp_path / "captures"
    names = {}  # convention -> {imported camera name: the room's}
    for name, writer in WRITERS.items():
        (captures / name).mkdir(parents=True)
        names[name] = writer(room, captures / name)
    config = {"data_root": str(captures), "defaults": CAPTURE_DEFAULTS,
              "scenes": {"instant-ngp": {"kind": "transforms", "source": "instant-ngp"}}}
    # a minute or two on an idle machine with numba's cache warm; the cold compile of the fit's, trace's and
    # lift's kernels on a loaded machine takes longer
    result = run_snakemake(tmp_path, "--cores", "2", "reproduce", config=config)
    assert result.returncode == 0, result.stderr[-4000:]
    for name in config["scenes"]:
        seg = tmp_path / "results" / name / "full" / "segment"
        info = json.loads((seg / "segment.json").read_text())
        assert info["objects"], (name, info)
        total = 0
        for obj in info["objects"]:
            model = GaussianModel.read_ply(seg / "objects" / f"{obj['id']}.ply")
            assert len(model) == obj["gaussians"] >= CAPTURE_DEFAULTS["segment"]["min_gaussians"]
            assert obj["pixels"] >= info["min_pixels"] and 1 <= obj["views"] <= info["training_views"]
            strip = cv2.imread(str(seg / "objects" / f"{obj['id']}.png"))
            assert strip.shape[:2] == (24, 3 * 24)
            total += obj["gaussians"]
        assert total + sum(d["gaussians"] for d in info["dropped"] + info["stuff"]) + info["unclustered_gaussians"] \
            == info["gaussians_total"]
        assert [o["pixels"] for o in info["objects"]] == sorted((o["pixels"] for o in info["objects"]), reverse=True)
        sheet = cv2.imread(str(tmp_path / "results" / "plots" / "segment" / f"{name}-full.png"))
        assert sheet.shape[0] >= 24 * len(info["objects"])
        assert not (tmp_path / "results" / name / "full" / "eval").exists()
        masks = json.loads((tmp_path / "results" / name / "masks" / "masks.json").read_text())
        assert masks["source"] == "graph"
    report = run_snakemake(tmp_path, "--cores", "1", "reproduce", "--report", str(tmp_path / "report.html"),
                           config=config)
    assert report.returncode == 0, report.stderr[-4000:]
    assert "Objects (no ground truth)" in (tmp_path / "report.html").read_text(errors="replace")
    # the other conventions: the workflow's scene step imports each (the same room, its own convention)
    others = [name for name in WRITERS if name not in config["scenes"]]
    every = {**config, "scenes": {name: {"kind": "transforms", "source": name} for name in WRITERS}}
    result = run_snakemake(tmp_path, "--cores", "2", *(f"results/{name}/scene" for name in others), config=every)
    assert result.returncode == 0, result.stderr[-4000:]
    for name in others:
        imported = Scene.read(tmp_path / "results" / name / "scene")
        assert imported.meta["convention"] == name and imported.meta["importer"] == "transforms"
        assert sorted(c.name for c in imported.cameras) == sorted(names[name])
        for cam in imported.cameras:
            np.testing.assert_array_equal(imported.image(cam.name), room.image(names[name][cam.name]))


@pytest.mark.skipif(SNAKEMAKE is None, reason="snakemake is not installed")
def test_reproduce_segments_only_scenes_without_ground_truth(room, tmp_path):
    """`reproduce` asks for `segment` on captures and canonical scenes without instances/, for contrastive
    variants only; a synthetic room is evaluated instead."""
    captures = tmp_path / "captures"
    write_blender(room, captures / "cap")
    (captures / "canon" / "images").mkdir(parents=True)
    (captures / "canon_gt" / "instances").mkdir(parents=True)
    config = {"data_root": str(captures), "defaults": {"masks": {"source": "graph"}},
              "variants": {"full": {}, "sp": {"lifting": "self_prompt"}},
              "scenes": {"cap": {"kind": "transforms", "source": "cap"},
                         "canon": {"kind": "canonical", "source": "canon"},
                         "canon_gt": {"kind": "canonical", "source": "canon_gt"},
                         "room": {"kind": "synthetic"}}}
    result = run_snakemake(tmp_path, "-n", "reproduce", config=config)
    assert result.returncode == 0, result.stderr[-4000:]
    out = result.stdout
    for scene in ("cap", "canon"):
        assert f"results/{scene}/full/segment" in out
        assert f"results/plots/segment/{scene}-full.png" in out
        assert f"results/{scene}/sp/segment" not in out
    assert "results/canon_gt/full/segment" not in out and "results/room/full/segment" not in out
    assert "results/room/full/eval" in out


def test_contact_sheet_stacks_the_strips_with_their_numbers():
    strips = [np.full((24, 72, 3), 200, np.uint8), np.full((24, 48, 3), 90, np.uint8)]
    sheet = contact_sheet(strips, ["1", "2"])
    assert sheet.shape == (24 + 2 + 24, 24 + 2 + 72, 3)
    assert (sheet[:24, 26:98] == 200).all() and (sheet[26:, 26:74] == 90).all() and (sheet[26:, 74:] == 0).all()
    assert (sheet[24:26] == 255).all()
    assert sheet[:24, :24].max() > 100 and sheet[26:, :24].max() > 100  # the numbers are drawn
    assert contact_sheet([], []).shape[0] > 0


@pytest.mark.parametrize("bad, message", [({"min_share": 1.5}, "min_share"), ({"samples": 1}, "samples"),
                                          ({"min_gaussians": 0}, "min_gaussians"), ({"colour": 1}, "colour")])
def test_bad_params_are_one_sentence(tmp_path, bad, message, capsys):
    from trace3d.params import from_mapping

    with pytest.raises(ConfigError, match=message):
        from_mapping(SegmentParams, bad, "segment params")
    assert cli_main(["segment", "--scene", str(tmp_path), "--gaussians", str(tmp_path), "--lift", str(tmp_path),
                     "--out", str(tmp_path / "out"), "--params", yaml.safe_dump(bad)]) == 2
    assert message in capsys.readouterr().err and not (tmp_path / "out").exists()
