"""The ``poses`` step (:mod:`trace3d.poses`): :func:`run_poses` runs the colmap mode
(:mod:`.colmap`) or the dataset mode (here: the scene's own cameras, with points from its depth maps
or triangulated with its poses) and writes sfm.json."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..errors import ConfigError
from ..geometry import backproject_pixels
from ..io import write_json
from ..params import to_dict
from ..pointcloud import write_points_ply
from ..scene import Scene, write_cameras
from .align import scene_has_reference_poses
from .colmap import _check_pinhole, _run_colmap, _triangulate_known_poses, write_colmap_model
from .params import PosesParams, params_from

log = logging.getLogger(__name__)


def run_poses(scene: Scene, out_dir: Path, params: dict) -> None:
    """The ``poses`` step: write sparse/0, cameras.json, points3D.ply and sfm.json into ``out_dir``."""
    from ..threads import resolve_threads

    p = params_from(params)
    p = dataclasses.replace(p, num_threads=resolve_threads(p.num_threads))  # -1 = all of `trace3d --threads`
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if p.mode == "dataset":
        report = _run_dataset(scene, out_dir, p)
    else:
        report = _run_colmap(scene, out_dir, p)
    report["params"] = to_dict(p)
    write_json(out_dir / "sfm.json", report)
    log.info("poses: wrote %s", out_dir)


def _run_dataset(scene: Scene, out_dir: Path, p: PosesParams) -> dict:
    if not scene_has_reference_poses(scene):
        raise ConfigError(
            f"{scene.root / 'cameras.json'}: poses mode 'dataset' needs the scene's own poses, but they are "
            "unknown (identity poses or meta.json 'poses': 'unknown', as for `trace3d scene images`); "
            "use mode 'colmap'."
        )
    cameras = [dataclasses.replace(c) for c in scene.cameras]
    for cam in cameras:
        _check_pinhole(cam, str(scene.root / "cameras.json"))
    write_cameras(out_dir, cameras)
    source = p.dataset_points
    if source == "auto":
        source = "depth" if scene.has_depth else "triangulate"
    xyz, rgb = np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint8)
    report: dict = {"mode": "dataset", "images_registered": len(cameras), "images_total": len(scene.cameras),
                    "missing": [], "frame": "scene", "points_source": source}  # fmt: skip
    if source == "depth":
        if not scene.has_depth:
            raise ConfigError(f"{scene.root}: dataset_points is 'depth' but the scene has no depth/ folder.")
        if p.depth_points > 0:
            xyz, rgb = points_from_depth(scene, p.depth_points, p.seed)
        write_colmap_model(out_dir / "sparse" / "0", cameras, xyz, rgb)
        reason = "the depth maps have no valid pixel" if p.depth_points else "depth_points is 0"
        note = f"{len(xyz)} points back-projected from the scene's depth maps" if len(xyz) else reason
    elif source == "triangulate":
        rec, stats = _triangulate_known_poses(scene, p)
        report.update(stats)
        point_ids = sorted(rec.points3D)
        xyz = np.array([rec.points3D[i].xyz for i in point_ids], dtype=np.float64).reshape(-1, 3)
        rgb = np.array([rec.points3D[i].color for i in point_ids], dtype=np.uint8).reshape(-1, 3)
        (out_dir / "sparse" / "0").mkdir(parents=True, exist_ok=True)
        rec.write_binary(str(out_dir / "sparse" / "0"))
        note = (f"{len(xyz)} points triangulated from SIFT matches with the scene's poses" if len(xyz)
                else "triangulation with the scene's poses found no points (too few verified matches)")
    else:
        write_colmap_model(out_dir / "sparse" / "0", cameras, xyz, rgb)
        note = "dataset_points is 'none'"
    if len(xyz):
        write_points_ply(out_dir / "points3D.ply", xyz, rgb)
    else:
        note = (f"no points3D.ply was written: {note}; the trainer must initialise the Gaussians another way "
                "(depth or random in the scene bounds)")
        log.warning("poses (dataset): %s", note)
    log.info("poses (dataset): %d cameras copied; %s", len(cameras), note)
    report.update({"num_points": int(len(xyz)), "points_file": "points3D.ply" if len(xyz) else None, "note": note})
    return report


def points_from_depth(scene: Scene, total: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Back-project a random subsample of valid depth pixels of every frame.

    Returns xyz [P, 3] in the scene frame and rgb [P, 3] uint8, P <= total (about total / L per frame).
    """
    rng = np.random.default_rng(seed)
    per_frame = max(1, total // len(scene.cameras))
    all_xyz, all_rgb = [], []
    for cam in tqdm(scene.cameras, desc="depth points", unit="frame", leave=False):
        depth = scene.depth(cam.name)
        valid = np.flatnonzero(depth.ravel() > 0)
        if len(valid) == 0:
            continue
        pick = rng.choice(valid, size=min(per_frame, len(valid)), replace=False)
        v, u = np.divmod(pick, cam.width)
        all_xyz.append(backproject_pixels(cam, v, u, depth.ravel()[pick]))
        all_rgb.append(scene.image(cam.name).reshape(-1, 3)[pick])
    if not all_xyz:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint8)
    return np.concatenate(all_xyz), np.concatenate(all_rgb)
