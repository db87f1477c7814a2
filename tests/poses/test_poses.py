"""The ``poses`` step (trace3d.poses): pycolmap SfM on a small rendered room, its failure modes,
the data set mode, and the CLI.

The test scene is a textured box room ``[-3, 3] x [-1.5, 1.5] x [-3, 3]`` (y down, OpenCV-like)
with a few boxes in it, rendered by an exact numpy ray caster (helpers below).  Every face carries
its own random texture (a coarse colour tint times a high-contrast two-scale grey noise), so SIFT
finds many distinctive, multi-view consistent features.  Cameras sit on a circle around the centre
and look inwards.  Images are rendered at 2x and box-filtered down.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from trace3d.cli import main as cli_main
from trace3d.errors import ConfigError, Trace3DError
from trace3d.pointcloud import read_points_ply, umeyama
from trace3d.scene import Camera, Scene, write_cameras, write_frame
from trace3d.poses.align import scene_has_reference_poses
from trace3d.poses.params import PosesParams, params_from
from trace3d.poses.step import run_poses

# ----------------------------------------------------------------------------------------------
# test scenes
# ----------------------------------------------------------------------------------------------

ROOM_MIN = np.array([-3.0, -1.5, -3.0])
ROOM_MAX = np.array([3.0, 1.5, 3.0])
BOXES = [  # (min corner, max corner)
    (np.array([-0.9, 0.5, -0.6]), np.array([-0.1, 1.5, 0.3])),
    (np.array([0.3, 0.9, -0.2]), np.array([1.1, 1.5, 0.7])),
    (np.array([-0.3, 1.1, 0.8]), np.array([0.4, 1.5, 1.4])),
]


def look_at(center: np.ndarray, target: np.ndarray, down: np.ndarray = np.array([0.0, 1.0, 0.0])) -> np.ndarray:
    """[4, 4] world_to_camera of a camera at ``center`` looking at ``target`` (OpenCV axes, y down)."""
    z = target - center
    z = z / np.linalg.norm(z)
    x = np.cross(down, z)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    rot = np.stack([x, y, z])  # rows: camera axes in world coordinates
    w2c = np.eye(4)
    w2c[:3, :3] = rot
    w2c[:3, 3] = -rot @ center
    return w2c


class _Textures:
    """One random texture per (surface, face); evaluated at face-local 2D coordinates in metres.

    A coarse random tint times a high-contrast grey pattern of two scales (SIFT sees grey levels).
    """

    def __init__(self, seed: int, num_surfaces: int, cell_tint: float = 0.6, cells_grey=(0.2, 0.08)):
        rng = np.random.default_rng(seed)
        self.cell_tint = cell_tint
        self.cells_grey = cells_grey
        extent = 6.5  # metres covered by each grid

        def grid(cell: float, channels: int) -> np.ndarray:
            n = int(np.ceil(extent / cell)) + 2
            return rng.uniform(0.0, 1.0, size=(n, n, channels))

        self.grids = {
            (surface, face): (grid(cell_tint, 3), [grid(c, 1) for c in cells_grey])
            for surface in range(num_surfaces)
            for face in range(6)
        }

    @staticmethod
    def _bilinear(grid: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        i0 = np.floor(u).astype(int)
        j0 = np.floor(v).astype(int)
        fu = (u - i0)[:, None]
        fv = (v - j0)[:, None]
        i0 = np.clip(i0, 0, grid.shape[0] - 2)
        j0 = np.clip(j0, 0, grid.shape[1] - 2)
        return (
            grid[i0, j0] * (1 - fu) * (1 - fv)
            + grid[i0 + 1, j0] * fu * (1 - fv)
            + grid[i0, j0 + 1] * (1 - fu) * fv
            + grid[i0 + 1, j0 + 1] * fu * fv
        )

    def colour(self, surface: int, face: int, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """[P, 3] colours in [0, 1] at face coordinates u, v [P] (metres, offset to be >= 0)."""
        tint_grid, grey_grids = self.grids[(surface, face)]
        tint = 0.35 + 0.65 * self._bilinear(tint_grid, u / self.cell_tint, v / self.cell_tint)
        grey = sum(self._bilinear(g, u / c, v / c) for g, c in zip(grey_grids, self.cells_grey)) / len(grey_grids)
        grey = np.clip((grey - 0.5) * 2.5 + 0.5, 0.0, 1.0)
        return tint * grey


def render(camera: Camera, textures: _Textures, supersample: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast the room: RGB [H, W, 3] uint8 and depth along the optical axis [H, W] float."""
    s = supersample
    W, H = camera.width * s, camera.height * s
    K = camera.K.copy()
    K[:2] *= s
    xs, ys = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    pix = np.stack([xs.ravel(), ys.ravel(), np.ones(W * H)], axis=1)
    dirs_cam = pix @ np.linalg.inv(K).T  # z = 1
    c2w = camera.camera_to_world
    dirs = dirs_cam @ c2w[:3, :3].T
    origin = c2w[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / dirs
    best_t = np.full(len(dirs), np.inf)
    best_surface = np.zeros(len(dirs), dtype=int)
    best_face = np.zeros(len(dirs), dtype=int)
    # room interior: exit point of the box
    far = np.where(dirs > 0, ROOM_MAX, ROOM_MIN)
    t_axis = (far - origin) * inv
    t_axis[~np.isfinite(t_axis)] = np.inf
    axis = np.argmin(t_axis, axis=1)
    best_t = t_axis[np.arange(len(dirs)), axis]
    best_face = axis * 2 + (dirs[np.arange(len(dirs)), axis] > 0)
    # boxes: slab test
    for k, (bmin, bmax) in enumerate(BOXES, start=1):
        t1 = (bmin - origin) * inv
        t2 = (bmax - origin) * inv
        tmin = np.minimum(t1, t2)
        tmax = np.maximum(t1, t2)
        t_near = tmin.max(axis=1)
        t_far = tmax.min(axis=1)
        hit = (t_near < t_far) & (t_near > 1e-6) & (t_near < best_t)
        near_axis = tmin.argmax(axis=1)
        best_t = np.where(hit, t_near, best_t)
        best_surface = np.where(hit, k, best_surface)
        best_face = np.where(hit, near_axis * 2 + (dirs[np.arange(len(dirs)), near_axis] > 0), best_face)
    points = origin + dirs * best_t[:, None]
    rgb = np.zeros((len(dirs), 3))
    for surface in range(len(BOXES) + 1):
        for face in range(6):
            sel = (best_surface == surface) & (best_face == face)
            if not sel.any():
                continue
            others = [a for a in range(3) if a != face // 2]
            u = points[sel, others[0]] + 3.2
            v = points[sel, others[1]] + 3.2
            rgb[sel] = textures.colour(surface, face, u, v)
    rgb = rgb.reshape(H, W, 3).reshape(camera.height, s, camera.width, s, 3).mean(axis=(1, 3))
    depth = (best_t * dirs_cam[:, 2]).reshape(H, W)[s // 2 :: s, s // 2 :: s]
    return (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8), depth


def make_room_scene(
    root: Path,
    num_views: int = 24,
    width: int = 160,
    height: int = 120,
    radius: float = 2.3,
    test_every: int = 6,
    seed: int = 0,
    with_depth: bool = False,
) -> Scene:
    """Write a canonical scene of the textured room with ``num_views`` cameras on a circle."""
    rng = np.random.default_rng(seed)
    textures = _Textures(seed, len(BOXES) + 1)
    focal = 0.9 * width
    K = np.array([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1.0]])
    cameras = []
    for i in range(num_views):
        angle = 2 * np.pi * i / num_views
        center = np.array([radius * np.cos(angle), -0.2 + 0.1 * rng.standard_normal(), radius * np.sin(angle)])
        target = np.array([0.0, 0.6, 0.0]) + 0.2 * rng.standard_normal(3)
        split = "test" if test_every and i % test_every == test_every - 1 else "train"
        cam = Camera(f"frame_{i:04d}", split, width, height, K, look_at(center, target))
        rgb, depth = render(cam, textures)
        write_frame(root, cam.name, rgb, depth=depth if with_depth else None)
        cameras.append(cam)
    write_cameras(root, cameras)
    return Scene.read(root)


def make_noise_scene(root: Path, num_views: int = 6, width: int = 96, height: int = 72, seed: int = 0) -> Scene:
    """Unrelated images (independent blurred noise and flat grey) with arbitrary poses: SfM must fail."""
    rng = np.random.default_rng(seed)
    K = np.array([[80.0, 0, width / 2], [0, 80.0, height / 2], [0, 0, 1.0]])
    cameras = []
    for i in range(num_views):
        if i % 2 == 0:
            rgb = np.full((height, width, 3), 128, dtype=np.uint8)
        else:
            rgb = rng.integers(0, 256, size=(height, width, 3), dtype=np.uint8)
        angle = 2 * np.pi * i / num_views
        center = np.array([np.cos(angle), 0.0, np.sin(angle)])
        cam = Camera(f"img_{i:02d}", "train" if i else "test", width, height, K, look_at(center, np.zeros(3)))
        write_frame(root, cam.name, rgb)
        cameras.append(cam)
    write_cameras(root, cameras)
    return Scene.read(root)


def subset_scene(source: Scene, root: Path, names: list[str], noise: tuple[str, ...] = (), seed: int = 1) -> Scene:
    """Copy the frames ``names`` of ``source`` into ``root``, replacing the images of ``noise`` by random noise."""
    rng = np.random.default_rng(seed)
    cameras = [source.camera(n) for n in names]
    for cam in cameras:
        rgb = source.image(cam.name)
        if cam.name in noise:
            rgb = rng.integers(0, 256, size=rgb.shape, dtype=np.uint8)
        write_frame(root, cam.name, rgb)
    write_cameras(root, cameras)
    return Scene.read(root)


def depth_consistency(cameras: list[Camera], scene: Scene, xyz: np.ndarray) -> float:
    """Median relative difference between the depth of points [P, 3] in each camera and the scene's depth map."""
    errors = []
    for cam in cameras:
        uv, z = cam.project(xyz)
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] < cam.height)
        reference = scene.depth(cam.name)[uv[inside, 1].astype(int), uv[inside, 0].astype(int)]
        errors.append(np.abs(reference - z[inside]) / reference)
    return float(np.median(np.concatenate(errors)))


def load_report(out: Path) -> dict:
    return json.loads((out / "sfm.json").read_text())


# ----------------------------------------------------------------------------------------------
# fixtures: one scene and one default reconstruction shared by the module
# ----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> Scene:
    return make_room_scene(tmp_path_factory.mktemp("room"), num_views=24, with_depth=True)


@pytest.fixture(scope="module")
def room_sfm(room, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("poses")
    run_poses(room, out, {"seed": 0})
    return out


# ----------------------------------------------------------------------------------------------
# colmap mode
# ----------------------------------------------------------------------------------------------


def test_registers_every_view_within_two_percent(room, room_sfm):
    report = load_report(room_sfm)
    assert report["images_registered"] == report["images_total"] == len(room.cameras)
    assert report["missing"] == [] and report["filled_from_scene"] == []
    alignment = report["alignment"]
    assert alignment["applied"]
    assert alignment["method"] == "poses" and alignment["suspect_frames"] == []
    assert alignment["center_error_rel_max"] < 0.02
    assert alignment["rotation_error_deg_max"] < 1.0
    assert alignment["centers_only"]["center_error_rel_max"] < 0.02  # plain Umeyama on the centres
    assert report["mean_reprojection_error_px"] < 1.0
    assert report["mean_track_length"] > 2.0
    assert report["num_points"] >= 300
    assert report["single_camera"] is True


def test_default_poses_are_reproducible_whatever_the_thread_budget(room, room_sfm, tmp_path):
    # COLMAP with several threads gave different cameras from run to run (2026-11-26): the default is
    # one thread, whatever `trace3d --threads` allows
    again = tmp_path / "again"
    assert cli_main(["--threads", "2", "poses", "--scene", str(room.root), "--out", str(again),
                     "--params", json.dumps({"seed": 0})]) == 0
    assert load_report(again)["params"]["num_threads"] == 1
    for name in ("cameras.json", "points3D.ply"):
        assert (again / name).read_bytes() == (room_sfm / name).read_bytes(), name


def test_outputs_live_in_the_scene_frame(room, room_sfm):
    poses = Scene.read(room_sfm, check_files=False)
    # every frame, same names and splits, in scene order; known intrinsics kept fixed
    assert [(c.name, c.split) for c in poses.cameras] == [(c.name, c.split) for c in room.cameras]
    for cam, ref in zip(poses.cameras, room.cameras):
        np.testing.assert_allclose(cam.K, ref.K, atol=1e-9)
        assert np.linalg.norm(cam.center - ref.center) < 0.02 * 3.0
    # the SfM points, seen through the output cameras, sit on the rendered surfaces
    xyz, rgb = read_points_ply(room_sfm / "points3D.ply")
    assert len(xyz) == load_report(room_sfm)["num_points"] and rgb.dtype == np.uint8
    assert depth_consistency(poses.cameras, room, xyz) < 0.02
    # the COLMAP model holds the same (aligned) poses
    rec = pycolmap.Reconstruction(str(room_sfm / "sparse" / "0"))
    assert rec.num_reg_images() == len(room.cameras) and rec.num_points3D() == len(xyz)
    for cam in poses.cameras:
        image = rec.find_image_with_name(f"{cam.name}.png")
        np.testing.assert_allclose(image.cam_from_world().matrix(), cam.world_to_camera[:3], atol=1e-9)


def test_sequential_matching_and_estimated_intrinsics(room, tmp_path):
    out = tmp_path / "poses"
    run_poses(room, out, {"matcher": "sequential", "sequential_overlap": 5, "known_intrinsics": False})
    report = load_report(out)
    assert report["images_registered"] == len(room.cameras)
    assert report["alignment"]["center_error_rel_max"] < 0.03
    assert report["intrinsics"]["focal_error_rel_max"] < 0.02
    poses = Scene.read(out, check_files=False)
    assert not np.allclose(poses.cameras[0].K, room.cameras[0].K)  # estimated, not copied


def test_without_reference_poses_keeps_colmap_frame(room, tmp_path):
    scene = subset_scene(room, tmp_path / "scene", [c.name for c in room.cameras[:12]])
    (scene.root / "meta.json").write_text(json.dumps({"poses": "unknown"}))
    scene = Scene.read(scene.root)
    assert not scene_has_reference_poses(scene)
    out = tmp_path / "poses"
    run_poses(scene, out, {})
    report = load_report(out)
    assert "alignment" not in report and report["frame"] == "colmap"
    poses = Scene.read(out, check_files=False)
    centres = np.stack([c.center for c in poses.cameras])
    reference = np.stack([c.center for c in scene.cameras])
    sim = umeyama(centres, reference)
    assert abs(sim.scale - 1.0) > 1e-3 or np.abs(sim.translation).max() > 1e-3  # really another frame
    residual = np.linalg.norm(sim.apply(centres) - reference, axis=1).max()
    assert residual < 0.02 * np.ptp(reference, axis=0).max()


def test_unregistered_frames_are_named(room, tmp_path):
    names = [c.name for c in room.cameras[:12]]
    bad = (names[3], names[8])
    scene = subset_scene(room, tmp_path / "scene", names, noise=bad)
    with pytest.raises(Trace3DError) as info:
        run_poses(scene, tmp_path / "poses", {})
    message = str(info.value)
    assert "only 10 of 12 frames registered" in message
    assert f"missing: {bad[0]}, {bad[1]}." in message
    assert str(scene.root) in message and "\n" not in message


def test_allowed_missing_frames_are_filled_and_listed(room, tmp_path):
    names = [c.name for c in room.cameras[:12]]
    bad = (names[3], names[8])
    scene = subset_scene(room, tmp_path / "scene", names, noise=bad)
    out = tmp_path / "poses"
    run_poses(scene, out, {"min_registered_fraction": 0.8})
    report = load_report(out)
    assert report["missing"] == list(bad) and report["filled_from_scene"] == list(bad)
    assert report["images_registered"] == 10
    poses = Scene.read(out, check_files=False)
    assert [c.name for c in poses.cameras] == names  # later steps get every frame, test views included
    for name in bad:
        np.testing.assert_allclose(poses.camera(name).world_to_camera, scene.camera(name).world_to_camera)


def test_unrelated_images_fail_with_all_frames_named(tmp_path):
    scene = make_noise_scene(tmp_path / "noise", num_views=6)
    with pytest.raises(Trace3DError) as info:
        run_poses(scene, tmp_path / "poses", {})
    message = str(info.value)
    assert "0 of 6 frames registered" in message
    assert "missing: " + ", ".join(c.name for c in scene.cameras) + "." in message


# ----------------------------------------------------------------------------------------------
# dataset mode, parameters, CLI
# ----------------------------------------------------------------------------------------------


def test_dataset_mode_points_from_depth(room, tmp_path):
    out = tmp_path / "poses"
    run_poses(room, out, {"mode": "dataset", "depth_points": 4800})
    poses = Scene.read(out, check_files=False)
    for cam, ref in zip(poses.cameras, room.cameras):
        assert cam.to_json() == ref.to_json()
    xyz, rgb = read_points_ply(out / "points3D.ply")
    assert 4000 <= len(xyz) <= 4800
    # back-projected points lie on the room's surfaces: inside the room, and on the depth maps
    assert (xyz.min(axis=0) > np.array([-3.02, -1.52, -3.02])).all()
    assert (xyz.max(axis=0) < np.array([3.02, 1.52, 3.02])).all()
    assert depth_consistency(room.cameras[:4], room, xyz) < 0.01
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert rec.num_reg_images() == len(room.cameras) and rec.num_points3D() == len(xyz)
    image = rec.find_image_with_name(f"{room.cameras[5].name}.png")
    np.testing.assert_allclose(image.cam_from_world().matrix(), room.cameras[5].world_to_camera[:3], atol=1e-12)
    report = load_report(out)
    assert report["mode"] == "dataset" and report["num_points"] == len(xyz)


def test_dataset_mode_triangulates_without_depth(room, tmp_path):
    names = [c.name for c in room.cameras[:8]]
    scene = subset_scene(room, tmp_path / "scene", names)  # no depth/ folder
    out = tmp_path / "poses"
    run_poses(scene, out, {"mode": "dataset"})
    report = load_report(out)
    assert report["points_source"] == "triangulate" and report["num_points"] >= 100
    assert report["mean_reprojection_error_px"] < 1.0
    xyz, _ = read_points_ply(out / "points3D.ply")
    assert len(xyz) == report["num_points"]
    assert depth_consistency([room.camera(n) for n in names], room, xyz) < 0.02
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert rec.num_points3D() == len(xyz) and rec.compute_mean_track_length() >= 2.0
    for image in rec.images.values():  # the scene's poses are kept, not refined
        np.testing.assert_allclose(image.cam_from_world().matrix(), scene.camera(image.name[:-4]).world_to_camera[:3],
                                   atol=1e-9)  # fmt: skip


def test_dataset_mode_without_points(room, tmp_path):
    scene = subset_scene(room, tmp_path / "scene", [c.name for c in room.cameras[:3]])
    out = tmp_path / "poses"
    run_poses(scene, out, {"mode": "dataset", "dataset_points": "none"})
    assert not (out / "points3D.ply").exists()
    report = load_report(out)
    assert report["num_points"] == 0 and "no points3D.ply was written" in report["note"]
    assert len(Scene.read(out, check_files=False).cameras) == 3
    with pytest.raises(ConfigError, match="no depth/ folder"):
        run_poses(scene, tmp_path / "poses2", {"mode": "dataset", "dataset_points": "depth"})


def test_params_are_checked(room, tmp_path):
    assert params_from(None) == PosesParams()
    with pytest.raises(ConfigError, match="unknown parameter"):
        params_from({"matcher_type": "exhaustive"})
    with pytest.raises(ConfigError, match="matcher"):
        params_from({"matcher": "vocab_tree"})
    with pytest.raises(ConfigError, match="min_registered_fraction"):
        params_from({"min_registered_fraction": 0.0})
    # one shared camera cannot hold two different K
    names = [c.name for c in room.cameras[:3]]
    scene = subset_scene(room, tmp_path / "scene", names)
    cameras = [Camera(c.name, c.split, c.width, c.height, c.K * [[1.0 + 0.1 * i], [1], [1]], c.world_to_camera)
               for i, c in enumerate(scene.cameras)]  # fmt: skip
    write_cameras(scene.root, cameras)
    with pytest.raises(ConfigError, match="K differ"):
        run_poses(Scene.read(scene.root), tmp_path / "poses", {"single_camera": True})


def test_reference_pose_detection(room, tmp_path):
    assert scene_has_reference_poses(room)
    names = [c.name for c in room.cameras[:3]]
    scene = subset_scene(room, tmp_path / "scene", names)
    write_cameras(scene.root, [Camera(c.name, c.split, c.width, c.height, c.K, np.eye(4)) for c in scene.cameras])
    assert not scene_has_reference_poses(Scene.read(scene.root))
    with pytest.raises(ConfigError, match="needs the scene's own poses"):
        run_poses(Scene.read(scene.root), tmp_path / "poses", {"mode": "dataset"})


def test_cli_poses_step(room, tmp_path, capsys):
    out = tmp_path / "poses"
    code = cli_main(["poses", "--scene", str(room.root), "--out", str(out), "--params", '{"mode": "dataset"}'])
    assert code == 0
    assert {p.name for p in out.iterdir()} >= {"cameras.json", "points3D.ply", "sfm.json", "sparse"}
    code = cli_main(["poses", "--scene", str(room.root), "--out", str(tmp_path / "x"), "--params", '{"moed": 1}'])
    assert code == 2 and "unknown parameter" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
