"""Mapping a reconstruction into the scene's frame: the Sim(3) that aligns its cameras with the
scene's reference poses, and the camera-centre and rotation errors it leaves (:mod:`trace3d.poses`)."""

from __future__ import annotations

import logging

import numpy as np

from ..errors import Trace3DError
from ..pointcloud import align_cameras, rotation_angle_deg
from ..scene import Scene

log = logging.getLogger(__name__)


# after alignment, frames off the reference by more than this are listed as suspect (a warning, not a failure)
SUSPECT_CENTER_REL = 0.05  # of the camera diameter
SUSPECT_ROTATION_DEG = 2.0


def scene_has_reference_poses(scene: Scene) -> bool:
    """Whether the scene's cameras.json poses are real (ground truth or the data set's own).

    An importer that does not know the poses writes identity poses and/or ``"poses": "unknown"``
    in meta.json; both are recognised.  Poses whose centres all coincide cannot anchor a Sim(3).
    """
    if str(scene.meta.get("poses", "")).lower() in ("unknown", "none", "identity"):
        return False
    centres = np.stack([c.center for c in scene.cameras])
    return len(centres) >= 3 and float(np.ptp(centres, axis=0).max()) > 1e-9


def camera_diameter(centres: np.ndarray) -> float:
    """Largest pairwise distance between camera centres [L, 3] (the scene extent used for errors)."""
    diff = centres[:, None, :] - centres[None, :, :]
    return float(np.sqrt((diff**2).sum(-1)).max())


def _name_list(names: list[str], limit: int = 30) -> str:
    if len(names) <= limit:
        return ", ".join(names)
    return ", ".join(names[:limit]) + f" and {len(names) - limit} more"


def _align_to_scene(rec, scene: Scene, registered: dict, method: str) -> dict:
    """Map ``rec`` (in place) by the Sim(3) aligning its cameras to the scene's; return the errors.

    ``method`` is :func:`trace3d.pointcloud.align_cameras`'s.  The errors after the alignment that
    uses the camera centres alone (Umeyama) are reported too, under ``centers_only``.
    """
    import pycolmap

    names = [c.name for c in scene.cameras if c.name in registered]
    if len(names) < 3:
        raise Trace3DError(
            f"{scene.root}: only {len(names)} frames registered, too few to align the reconstruction "
            "to the scene's poses (need 3)."
        )

    def sfm_poses() -> np.ndarray:
        out = np.tile(np.eye(4), (len(names), 1, 1))
        out[:, :3, :4] = [registered[n].cam_from_world().matrix() for n in names]
        return out

    reference = np.stack([scene.camera(n).world_to_camera for n in names])
    reference_centres = np.stack([scene.camera(n).center for n in names])
    diameter = camera_diameter(np.stack([c.center for c in scene.cameras]))

    def errors(poses: np.ndarray) -> dict:
        centres = -np.einsum("lji,lj->li", poses[:, :3, :3], poses[:, :3, 3])
        dist = np.linalg.norm(centres - reference_centres, axis=1)
        angles = np.array([rotation_angle_deg(a[:3, :3], b[:3, :3]) for a, b in zip(poses, reference)])
        suspect = [n for n, d, a in zip(names, dist, angles)
                   if d > SUSPECT_CENTER_REL * diameter or a > SUSPECT_ROTATION_DEG]
        return {
            "suspect_frames": suspect,
            "center_error_mean": float(dist.mean()),
            "center_error_max": float(dist.max()),
            "center_error_rel_mean": float(dist.mean() / diameter),
            "center_error_rel_max": float(dist.max() / diameter),
            "center_error_worst_frame": names[int(np.argmax(dist))],
            "rotation_error_deg_mean": float(angles.mean()),
            "rotation_error_deg_max": float(angles.max()),
        }

    before = sfm_poses()
    by_centres = align_cameras(before, reference, "centers")
    centres_only = errors(np.stack([by_centres.transform_world_to_camera(w) for w in before]))
    sim = align_cameras(before, reference, method)
    rec.transform(pycolmap.Sim3d(sim.scale, pycolmap.Rotation3d(sim.rotation), sim.translation))
    after = errors(sfm_poses())
    if after["suspect_frames"]:
        log.warning(
            "poses (colmap): %d frame(s) are off the scene's poses by more than %.0f %% of the camera diameter "
            "or %.0f degrees after alignment: %s", len(after["suspect_frames"]), 100 * SUSPECT_CENTER_REL,
            SUSPECT_ROTATION_DEG, _name_list(after["suspect_frames"]),
        )  # fmt: skip
    return {
        "applied": True,
        "method": method,
        "sim3_scene_from_colmap": sim.to_json(),
        "extent": "diameter of the scene's camera centres (largest pairwise distance)",
        "extent_value": diameter,
        **after,
        "centers_only": centres_only,
    }
