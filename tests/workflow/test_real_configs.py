"""The real benchmarks' configs (config/replica.yaml, config/nvos.yaml) through the workflow on tiny
fixtures written in the data sets' own layouts: a layout or config mistake fails here, not on a
user's GPU machine. The configs are used as shipped (defaults, scene entries, importer parameters);
the test only points ``data_root`` at the fixture, keeps the scenes the fixture has, and makes the
training tiny."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from tests.datasets.test_llff import FERN_NAMES, write_llff_scene, write_nvos_labels
from tests.datasets.test_llff import render as render_llff
from tests.datasets.test_replica import write_replica_sequence
from trace3d.scene import Scene
from tests.workflow.test_workflow import REPO, SNAKEMAKE, TINY_TRAINING, run_snakemake

pytestmark = pytest.mark.skipif(SNAKEMAKE is None, reason="snakemake is not installed")

TINY_STAGES = {
    "gaussians": TINY_TRAINING,
    "refine": {"iterations": 20, "detect_at": [1, 10], "schedule_scale": 1.0, "highlight_views": 1},
    "lift": {"iterations": 30, "pixels": 256, "pool_pixels": 512, "pca_views": 1},
    "evaluate": {"min_pixels": 20, "turntable_views": 3, "turntable_size": 32},
}


def derived_config(name: str, data_root: Path, scenes: list[str], **defaults) -> dict:
    """The shipped config ``config/<name>.yaml`` with data_root, the fixture's scenes and tiny stages."""
    config = yaml.safe_load((REPO / "config" / f"{name}.yaml").read_text())
    config["data_root"] = str(data_root)
    config["results"] = "results"
    config["scenes"] = {s: config["scenes"][s] for s in scenes}
    for step, values in {**TINY_STAGES, **defaults}.items():
        config.setdefault("defaults", {})[step] = {**config["defaults"].get(step, {}), **values}
    return config


@pytest.mark.slow
@pytest.mark.xdist_group("whole_dag")  # whole-DAG runs take turns on one worker (tests/conftest.py)
def test_replica_config_runs_the_whole_dag(tmp_path):
    data = tmp_path / "Replica"
    write_replica_sequence(data / "room_0" / "Sequence_1", num_frames=12)
    config = derived_config("replica", data, ["room0"])
    result = run_snakemake(tmp_path, "--cores", "2", "reproduce", config=config)
    assert result.returncode == 0, result.stderr[-4000:]
    root = tmp_path / "results" / "room0"
    scene = Scene.read(root / "scene")
    assert len(scene.cameras) == 12 and len(scene.test_cameras) == 3  # every 4th frame is a test view
    assert scene.objects.evaluated_ids()  # the paper's room_0 list meets the fixture's ids
    for step in ("poses", "masks", "patches", "gaussians", "trace-paper", "merge-paper", "refine-paper-merged"):
        assert (root / step).is_dir(), step
    metrics = json.loads((root / "full" / "eval" / "metrics.json").read_text())
    assert metrics["extraction"]["objects"] >= 1 and metrics["nvs"]["objects"] >= 1
    assert json.loads((root / "full" / "eval-official" / "metrics.json").read_text())["protocol"] == "official"
    tables = tmp_path / "results" / "tables"
    for table in ("table2", "table3"):
        frame = pd.read_csv(tables / f"{table}.csv")
        assert "room0" in " ".join(frame.columns), frame.columns
        assert (tables / "official" / f"{table}.md").is_file()


@pytest.mark.parametrize("name", ["replica", "nvos"])
def test_missing_data_root_is_one_sentence_before_any_job(tmp_path, name):
    config = yaml.safe_load((REPO / "config" / f"{name}.yaml").read_text())
    config["data_root"] = str(tmp_path / "nowhere")
    result = run_snakemake(tmp_path, "-n", "reproduce", config=config)
    assert result.returncode != 0
    out = result.stdout + result.stderr
    assert f"config data_root: {tmp_path / 'nowhere'} does not exist" in out, out[-2000:]
    assert "Job stats" not in out


def test_missing_scene_folder_is_named(tmp_path):
    data = tmp_path / "Replica"
    data.mkdir()
    config = yaml.safe_load((REPO / "config" / "replica.yaml").read_text())
    config["data_root"] = str(data)
    config["scenes"]["room0"]["source"] = "room_0"
    result = run_snakemake(tmp_path, "-n", "reproduce", config=config)
    assert result.returncode != 0
    assert f"config scenes.room0.source: {data / 'room_0'} does not exist" in result.stdout + result.stderr


@pytest.mark.slow
@pytest.mark.xdist_group("whole_dag")  # whole-DAG runs take turns on one worker (tests/conftest.py)
def test_nvos_config_runs_the_whole_dag(tmp_path):
    """NVOS as shipped asks SAM for masks; here the fixture's masks come as files (the sphere and the
    wall per view), the rest of the config unchanged: import, poses from poses_bounds.npy, fit, trace,
    merge, refine, lift, the NVOS evaluation (scribbles -> target-view mask) and Table 4."""
    data = tmp_path / "nvos"
    poses = write_llff_scene(data / "fern", FERN_NAMES)
    write_nvos_labels(data / "labels" / "llff", "fern", poses[0], poses[-1])
    masks = tmp_path / "fern_masks"
    masks.mkdir()
    for name, c2w in zip(FERN_NAMES, poses):
        sphere = render_llff(c2w)[1]
        np.savez(masks / f"{name}.npz", masks=np.stack([sphere, ~sphere]), scores=np.array([0.9, 0.8]))
    config = derived_config("nvos", data, ["fern"], masks={"source": "files", "files": {"folder": str(masks)}})
    result = run_snakemake(tmp_path, "--cores", "2", "reproduce", config=config)
    assert result.returncode == 0, result.stderr[-4000:]
    root = tmp_path / "results" / "fern"
    scene = Scene.read(root / "scene")
    assert scene.meta["nvos"]["target_frame"] == "IMG_4027" and [c.name for c in scene.test_cameras] == ["IMG_4027"]
    for step in ("poses", "masks", "patches", "gaussians", "trace-paper", "merge-paper", "refine-paper-merged"):
        assert (root / step).is_dir(), step
    assert (root / "full" / "lift" / "features.npy").is_file()
    metrics = json.loads((root / "full" / "eval-nvos" / "metrics.json").read_text())
    assert metrics["protocol"] == "nvos" and metrics["target"] == "IMG_4027" and metrics["reference"] == "IMG_4038"
    assert metrics["reference_instances"]  # the positive scribbles select the sphere's instance
    assert 0.0 <= metrics["nvs"]["mIoU"] <= 1.0 and metrics["nvs"]["mAcc"] > 0.5
    table = pd.read_csv(tmp_path / "results" / "tables" / "table4.csv")
    assert list(table["method"]) == ["full"] and "fern" in " ".join(table.columns)
    assert not (tmp_path / "results" / "tables" / "table2.md").exists()
