"""Tests of trace3d.training.step: the `gaussians` pipeline step and its files."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from tests.plane_scene import STEP_PARAMS, plane_points, single_thread, write_plane_scene  # noqa: F401  (autouse fixture)
from trace3d.errors import ConfigError, Trace3DError
from trace3d.gaussians import GaussianModel
from trace3d.pointcloud import write_points_ply
from trace3d.scene import write_cameras
from trace3d.training import failed_dir_for, run_gaussians


def test_run_gaussians_writes_all_outputs(tmp_path):
    scene = write_plane_scene(tmp_path / "scene")
    poses = tmp_path / "poses"
    poses.mkdir()
    # poses: the scene's cameras (all views), and a point cloud on the plane
    write_cameras(poses, scene.cameras)
    write_points_ply(poses / "points3D.ply", plane_points(200).astype(np.float32), np.full((200, 3), 128, np.uint8))
    out = tmp_path / "gaussians"
    run_gaussians(scene, poses, out, dict(STEP_PARAMS))
    for name in ("point_cloud.ply", "train.csv", "metrics.json", "config.json", "cameras.json", "train_curve.png",
                 "renders.png"):
        assert (out / name).is_file(), name
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["init"] == "points" and metrics["num_test_views"] == 2 and metrics["num_train_views"] == 4
    assert len(metrics["test_views"]) == 2 and metrics["test_psnr"] > 12
    assert metrics["num_gaussians"] == len(GaussianModel.read_ply(out / "point_cloud.ply"))
    config = json.loads((out / "config.json").read_text())
    assert config["params"]["iterations"] == 60 and config["schedule"]["iterations"] == 60
    lines = (out / "train.csv").read_text().splitlines()
    assert lines[0].startswith("iteration,loss,l1,ssim,normal,distortion,psnr,gaussians")
    assert len(lines) == 1 + 6


def test_run_gaussians_random_init_and_bad_params(tmp_path):
    scene = write_plane_scene(tmp_path / "scene")
    with pytest.raises(ConfigError, match="unknown"):
        run_gaussians(scene, None, tmp_path / "x", {"bogus": 1})
    with pytest.raises(ConfigError, match="points"):
        run_gaussians(scene, None, tmp_path / "x", {"init": "points"})
    run_gaussians(scene, None, tmp_path / "out", dict(STEP_PARAMS, iterations=10, densify=False))
    assert json.loads((tmp_path / "out" / "metrics.json").read_text())["init"] == "random"


def test_run_gaussians_missing_test_pose(tmp_path):
    scene = write_plane_scene(tmp_path / "scene")
    poses = tmp_path / "poses"
    write_cameras(poses, [c for c in scene.cameras if c.split == "train"])
    with pytest.raises(Trace3DError, match="test views"):
        run_gaussians(scene, poses, tmp_path / "out", dict(STEP_PARAMS))


def test_run_gaussians_divergence_keeps_checkpoint_beside_output(tmp_path):
    scene = write_plane_scene(tmp_path / "scene")
    out = tmp_path / ".gaussians.tmp-123-abcdef12"  # the CLI's temporary name for results/.../gaussians
    params = dict(STEP_PARAMS, feature_lr=1e30, checkpoint_interval=1, densify=False)
    with pytest.raises(Trace3DError, match="checkpoint_last_good.ply") as info:
        run_gaussians(scene, None, out, params)
    failed = tmp_path / "gaussians.failed"
    assert failed_dir_for(out) == failed
    assert str(failed) in str(info.value)
    kept = GaussianModel.read_ply(failed / "checkpoint_last_good.ply")
    assert kept.is_finite() and len(kept) == 300
    assert json.loads((failed / "failure.json").read_text())["iteration"] >= 2


def test_gaussians_step_gives_the_same_files_at_one_and_two_threads(tmp_path):
    """The `gaussians` step at --threads 1 and 2 on a room like the SLURM test's writes the same point
    cloud. (The SLURM test's own room, its fit at 2 threads on the cluster, is what showed torch's Adam
    on 2 threads giving other bits; this room does not show it: GaussianOptimizer's ADAM_THREADS.)"""
    from trace3d.cli import main

    synthetic = json.dumps({"width": 48, "height": 36, "num_objects": 10, "num_views": 6, "test_every": 3,
                            "supersample": 1})
    train = json.dumps({"densify_from": 10, "densify_interval": 10, "densify_until": 30, "device": "cpu",
                        "iterations": 40, "normal_from": 20, "schedule_scale": 1.0, "sh_degree": 1,
                        "sh_degree_interval": 20})
    assert main(["scene", "synthetic", "--out", str(tmp_path / "scene"), "--params", synthetic]) == 0
    assert main(["poses", "--scene", str(tmp_path / "scene"), "--out", str(tmp_path / "poses"), "--params",
                 "{mode: dataset}"]) == 0
    clouds = []
    for threads in (1, 2):  # fresh processes, as the rules run them (torch's thread pool starts in the step)
        out = tmp_path / f"gaussians{threads}"
        ran = subprocess.run([sys.executable, "-m", "trace3d.cli", "--threads", str(threads), "gaussians", "--scene",
                              str(tmp_path / "scene"), "--poses", str(tmp_path / "poses"), "--out", str(out),
                              "--params", train], capture_output=True, text=True)
        assert ran.returncode == 0, ran.stderr[-3000:]
        clouds.append((out / "point_cloud.ply").read_bytes())
    assert clouds[0] == clouds[1]
