"""A tiny synthetic room ready to lift, without a fit: the evaluation's and the extraction's tests lift it
(by label assignment, or contrastively) and share this setup."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from trace3d.scene import Scene


def oracle_room(root: Path, synthetic: dict, init_views: str = "all") -> Scene:
    """Write under ``root``: ``scene/`` (a synthetic room with ``synthetic``'s parameters), ``gaussians/``
    (Gaussians on the ground-truth depth of every view, or of the training views with ``init_views``
    "train", with smaller disks for sharper object borders) and ``labels/`` (the training views'
    object-level ground-truth ids: an oracle for the instance maps). Returns the scene."""
    from trace3d.cli import main
    from trace3d.gaussians import init_from_depth
    from trace3d.scene import write_u16

    assert main(["scene", "synthetic", "--out", str(root / "scene"), "--params", json.dumps(synthetic)]) == 0
    scene = Scene.read(root / "scene")
    cameras = {"all": scene.cameras, "train": scene.train_cameras}[init_views]
    model = init_from_depth(scene, cameras=cameras, stride=1, max_points=None, sh_degree=0, opacity=0.95)
    model.log_scales = model.log_scales - 0.3  # smaller disks: sharper object borders
    (root / "gaussians").mkdir()
    model.write_ply(root / "gaussians" / "point_cloud.ply")
    lookup = scene.objects.lookup("object")
    for cam in scene.train_cameras:
        write_u16(root / "labels" / f"{cam.name}.png", lookup[scene.instances(cam.name)].astype(np.uint16))
    return scene
