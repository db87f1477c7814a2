"""Replica importer: tiny fixtures in the exact Semantic-NeRF layout, imported and checked.

The fixture is a ray-cast box room (six walls and a box on the floor) seen by cameras on a circle;
rgb, z-depth (mm), instance ids and an OpenCV camera-to-world trajectory are written exactly as the
Semantic-NeRF Replica release lays them out.  Because the depth is rendered from the same poses,
back-projecting it through the imported cameras must land on the room's surfaces: a wrong pose
convention (OpenGL vs OpenCV, c2w vs w2c) or wrong intrinsics would not.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from trace3d.datasets import replica
from trace3d.datasets.depth_init import _backproject_depth_reference, backproject_depth, depth_points
from trace3d.errors import ConfigError, Trace3DError
from trace3d.scene import Scene

W, H = 32, 24
ROOM = np.array([2.0, 2.0, 1.5])  # half extents of the room (walls at +-x, +-y, +-z)
BOX_LO, BOX_HI = np.array([-0.5, -0.4, -1.5]), np.array([0.3, 0.5, -0.8])
BOX_ID = 6  # Replica ids: walls 0..5 (id 0 is a real object in Replica), box 6


def look_at_c2w(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """[4, 4] OpenCV camera-to-world (x right, y down, z forward), world z up."""
    forward = (target - position) / np.linalg.norm(target - position)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([right, down, forward], axis=1)
    c2w[:3, 3] = position
    return c2w


def render(c2w: np.ndarray, width: int = W, height: int = H) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """rgb [H, W, 3] uint8, z-depth [H, W] metres, Replica instance ids [H, W] of the box room."""
    f = width / 2.0  # 90 degree HFOV
    cols, rows = np.meshgrid(np.arange(width), np.arange(height))
    dirs_cam = np.stack([(cols + 0.5 - width / 2) / f, (rows + 0.5 - height / 2) / f, np.ones_like(cols, float)], -1)
    dirs = dirs_cam @ c2w[:3, :3].T  # [H, W, 3]; the ray parameter t equals z-depth
    origin = c2w[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_walls = np.where(dirs > 0, (ROOM - origin) / dirs, (-ROOM - origin) / dirs)  # [H, W, 3]
        t_walls[~np.isfinite(t_walls)] = np.inf
        axis = np.argmin(t_walls, axis=-1)
        t = np.take_along_axis(t_walls, axis[..., None], -1)[..., 0]
        positive = np.take_along_axis(dirs, axis[..., None], -1)[..., 0] > 0
        ids = axis * 2 + positive.astype(int)  # 0..5
        t1, t2 = (BOX_LO - origin) / dirs, (BOX_HI - origin) / dirs
        t_near = np.nanmax(np.minimum(t1, t2), axis=-1)
        t_far = np.nanmin(np.maximum(t1, t2), axis=-1)
    hit_box = (t_near <= t_far) & (t_near > 0) & (t_near < t)
    t = np.where(hit_box, t_near, t)
    ids = np.where(hit_box, BOX_ID, ids)
    points = origin + dirs * t[..., None]
    checker = ((np.floor(points * 4).astype(int).sum(-1)) % 2).astype(np.uint8)
    palette = np.array([[200, 60, 60], [60, 200, 60], [60, 60, 200], [200, 200, 60], [60, 200, 200],
                        [200, 60, 200], [240, 240, 240]], dtype=np.uint8)
    rgb = (palette[ids] * (0.6 + 0.4 * checker[..., None])).astype(np.uint8)
    return rgb, t, ids


def camera_path(num_frames: int) -> list[np.ndarray]:
    poses = []
    for k in range(num_frames):
        angle = 2 * math.pi * k / max(num_frames, 1)
        position = np.array([1.2 * math.cos(angle), 1.2 * math.sin(angle), 0.3])
        target = np.array([-0.6 * math.cos(angle + 0.7), -0.6 * math.sin(angle + 0.7), -0.9])
        poses.append(look_at_c2w(position, target))
    return poses


def write_replica_sequence(
    seq: Path,
    num_frames: int = 12,
    written: list[int] | None = None,
    instance: bool = True,
    semantic_class: bool = True,
) -> list[np.ndarray]:
    """Write a Semantic-NeRF-layout sequence; returns the camera-to-world poses (all frames)."""
    poses = camera_path(num_frames)
    for sub in ("rgb", "depth", "semantic_class", "semantic_instance"):
        if sub == "semantic_instance" and not instance or sub == "semantic_class" and not semantic_class:
            continue
        (seq / sub).mkdir(parents=True, exist_ok=True)
    (seq / "traj_w_c.txt").write_text("".join(" ".join(f"{v:.9f}" for v in p.ravel()) + "\n" for p in poses))
    for i in written if written is not None else range(num_frames):
        rgb, depth, ids = render(poses[i])
        cv2.imwrite(str(seq / "rgb" / f"rgb_{i}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(seq / "depth" / f"depth_{i}.png"), np.round(depth * 1000).astype(np.uint16))
        if instance:
            cv2.imwrite(str(seq / "semantic_instance" / f"semantic_instance_{i}.png"), ids.astype(np.uint16))
        if semantic_class:
            cv2.imwrite(str(seq / "semantic_class" / f"semantic_class_{i}.png"), (ids // 2 + 10).astype(np.uint8))
    return poses


def on_room_surface(points: np.ndarray, tol: float = 0.02) -> np.ndarray:
    """[P] bool: the point lies on a wall of the room or on the box surface."""
    on_wall = np.abs(np.abs(points) - ROOM).min(axis=1) < tol
    inside_box = np.all((points > BOX_LO - tol) & (points < BOX_HI + tol), axis=1)
    near_box_face = np.minimum(np.abs(points - BOX_LO), np.abs(points - BOX_HI)).min(axis=1) < tol
    return on_wall | (inside_box & near_box_face)


@pytest.fixture
def room0(tmp_path: Path) -> tuple[Path, list[np.ndarray]]:
    root = tmp_path / "Replica"
    poses = write_replica_sequence(root / "room_0" / "Sequence_1")
    return root, poses


def do_import(source: Path, out: Path, **params) -> Scene:
    replica.import_replica(source, out, replica.params_from(params))
    return Scene.read(out)


# ----------------------------------------------------------------------------------------------


def test_round_trip(room0, tmp_path):
    root, poses = room0
    scene = do_import(root, tmp_path / "out", scene="room0")
    names = [c.name for c in scene.cameras]
    assert names == [f"rgb_{i:04d}" for i in range(12)]
    assert [c.name for c in scene.test_cameras] == ["rgb_0000", "rgb_0004", "rgb_0008"]
    for i, cam in enumerate(scene.cameras):
        assert (cam.width, cam.height) == (W, H)
        np.testing.assert_allclose(cam.K, [[16, 0, 16], [0, 16, 12], [0, 0, 1]])
        np.testing.assert_allclose(cam.camera_to_world, poses[i], atol=1e-7)
        rgb, depth, ids = render(poses[i])
        np.testing.assert_array_equal(scene.image(cam.name), rgb)
        np.testing.assert_allclose(scene.depth(cam.name), np.round(depth * 1000) / 1000, atol=1e-6)
        np.testing.assert_array_equal(scene.instances(cam.name), ids + 1)  # Replica id + 1
    seen = sorted(set().union(*(np.unique(render(p)[2]).tolist() for p in poses)))
    objects = {o.id: o for o in scene.objects}
    assert sorted(objects) == [i + 1 for i in seen] and 0 in seen and BOX_ID in seen
    assert objects[1].name == "replica_0" and objects[7].name == "replica_6"
    room0_list = set(replica.EVALUATED_IDS["room_0"])
    for o in scene.objects:
        assert o.level == "object" and o.parent is None
        assert o.evaluated == ((o.id - 1) in room0_list)
    assert objects[7].category == f"class_{6 // 2 + 10}"
    meta = scene.meta
    assert meta["scene"] == "room_0" and meta["init"] == "depth" and meta["instance_id_offset"] == 1
    assert meta["frame_index"]["rgb_0011"] == 11


def test_paper_lists():
    # The supplementary's table, office3's duplicated 86 dropped.
    assert len(replica.EVALUATED_IDS["office_0"]) == 29
    assert len(replica.EVALUATED_IDS["office_2"]) == 41 and replica.EVALUATED_IDS["office_2"][0] == 0
    assert len(replica.EVALUATED_IDS["office_3"]) == 31
    assert len(replica.EVALUATED_IDS["room_0"]) == 52
    for ids in replica.EVALUATED_IDS.values():
        assert len(set(ids)) == len(ids) and ids == sorted(ids)


def test_source_forms_and_scene_inference(room0, tmp_path):
    root, _ = room0
    for k, source in enumerate([root / "room_0", root / "room_0" / "Sequence_1"]):
        scene = do_import(source, tmp_path / f"out{k}")  # scene inferred from the folder name
        assert scene.meta["scene"] == "room_0" and len(scene.cameras) == 12


def test_depth_backprojects_onto_room_surfaces(room0, tmp_path):
    root, _ = room0
    scene = do_import(root, tmp_path / "out", scene="room0")
    xyz, rgb = depth_points(scene, stride=1, split=None)
    assert xyz.shape == (12 * W * H, 3) and rgb.shape == xyz.shape and rgb.dtype == np.uint8
    # mm quantisation of depth moves points by < 1 mm * |ray| / z
    assert on_room_surface(xyz.astype(np.float64)).mean() > 0.995
    # and each point seen from another camera has that camera's rendered depth there
    cam_a, cam_b = scene.cameras[1], scene.cameras[2]
    pts, _ = backproject_depth(cam_a, scene.depth(cam_a.name))
    uv, z = cam_b.project(pts)
    inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    cols, rows = np.floor(uv[inside]).astype(int).T
    visible = np.abs(scene.depth(cam_b.name)[rows, cols] - z[inside]) < 0.05
    assert inside.sum() > 50 and visible.mean() > 0.6


def test_backproject_matches_reference_loop(room0, tmp_path):
    root, _ = room0
    scene = do_import(root, tmp_path / "out", scene="room0", downscale=2)
    cam = scene.cameras[3]
    depth = scene.depth(cam.name)
    depth[0, 0] = 0.0  # an invalid pixel is skipped by both
    fast, _ = backproject_depth(cam, depth, stride=1)
    slow = _backproject_depth_reference(cam, depth, stride=1)
    np.testing.assert_allclose(fast, slow, atol=1e-9)
    # points project back to their pixel centres at their depth
    uv, z = cam.project(fast)
    rows, cols = np.nonzero(depth > 0)
    np.testing.assert_allclose(uv, np.stack([cols + 0.5, rows + 0.5], 1), atol=1e-9)
    np.testing.assert_allclose(z, depth[rows, cols], atol=1e-6)


def test_depth_points_split_stride_and_cap(room0, tmp_path):
    root, _ = room0
    scene = do_import(root, tmp_path / "out", scene="room0")
    xyz, _ = depth_points(scene, stride=4)  # train views only by default
    assert xyz.shape[0] == 9 * (W // 4) * (H // 4)
    capped, _ = depth_points(scene, stride=4, max_points=50, seed=3)
    again, _ = depth_points(scene, stride=4, max_points=50, seed=3)
    assert capped.shape == (50, 3)
    np.testing.assert_array_equal(capped, again)


def test_downscale(room0, tmp_path):
    root, poses = room0
    scene = do_import(root, tmp_path / "out", scene="room0", downscale=2)
    cam = scene.cameras[0]
    assert (cam.width, cam.height) == (16, 12)
    np.testing.assert_allclose(cam.K, [[8, 0, 8], [0, 8, 6], [0, 0, 1]])
    _, depth, ids = render(poses[0])
    ids_small = scene.instances(cam.name).astype(int) - 1
    for r in range(12):  # the block's most frequent id, ties to the first in row-major order
        for c in range(16):
            block = ids[2 * r : 2 * r + 2, 2 * c : 2 * c + 2].ravel().tolist()
            assert ids_small[r, c] == max(block, key=lambda v: (block.count(v), -block.index(v)))
    small = scene.depth(cam.name)
    assert (small > 0).mean() > 0.8  # blocks across a depth edge are invalidated, the rest kept
    # harmonic block means are exact on planes: blocks inside one surface back-project onto it
    # (to mm rounding); blocks straddling a crease land near it
    for cam, pose in zip(scene.cameras, poses):
        _, _, full_ids = render(pose)
        blocks = full_ids.reshape(12, 2, 16, 2).transpose(0, 2, 1, 3).reshape(12, 16, 4)
        same = (blocks == full_ids[::2, ::2, None]).all(-1)
        same &= full_ids[::2, ::2] != BOX_ID  # the box's faces share one id; walls are one plane per id
        xyz, pix = backproject_depth(cam, scene.depth(cam.name))
        flat = same[pix[:, 0], pix[:, 1]]
        assert flat.mean() > 0.5
        assert on_room_surface(xyz[flat], tol=0.005).all()
        assert on_room_surface(xyz, tol=0.1).all()


def test_split_and_rejected_frames_full_length():
    frames = replica.select_frames(900, "office_4", replica.params_from({}))
    test = [i for i, s in frames if s == "test"]
    assert test == [i for i in range(0, 900, 4) if not 618 <= i <= 733]
    assert not any(618 <= i <= 733 for i, _ in frames)
    assert len(frames) == 900 - (733 - 618 + 1)
    frames = replica.select_frames(900, "room_0", replica.params_from({}))
    assert len(frames) == 900 and sum(s == "test" for _, s in frames) == 225


def test_office1_rejection_with_stride(tmp_path):
    root = tmp_path / "Replica"
    stride_frames = list(range(0, 520, 10))
    write_replica_sequence(root / "office_1" / "Sequence_1", num_frames=520, written=stride_frames)
    scene = do_import(root, tmp_path / "out", scene="office1", frame_stride=10)
    kept = [scene.meta["frame_index"][c.name] for c in scene.cameras]
    assert kept == [i for i in stride_frames if not 474 <= i <= 503]
    split = {scene.meta["frame_index"][c.name]: c.split for c in scene.cameras}
    # test = every 4th position of the strided list (frames 0, 40, 80, ...), decided before rejection
    assert [i for i, s in split.items() if s == "test"] == [i for i in range(0, 520, 40) if i != 480]
    assert scene.meta["rejected_frames"] == [474, 503]


def test_max_frames(room0, tmp_path):
    root, _ = room0
    scene = do_import(root, tmp_path / "out", scene="room0", max_frames=5, init="sfm")
    assert len(scene.cameras) == 5 and scene.meta["init"] == "sfm"


def test_missing_instance_maps_refused(tmp_path):
    root = tmp_path / "Replica"
    write_replica_sequence(root / "room_0" / "Sequence_1", instance=False, semantic_class=True)
    with pytest.raises(Trace3DError, match=r"semantic_instance.*Replica_Instance_Segmentation.*semantic_class"):
        replica.import_replica(root, tmp_path / "out", replica.params_from({"scene": "room0"}))


@pytest.mark.parametrize(
    "breakage, pattern",
    [
        ("no_traj", r"traj_w_c\.txt is missing"),
        ("bad_traj_line", r"traj_w_c\.txt: line 3 has 15 numbers"),
        ("no_rgb_dir", r"rgb: folder is missing"),
        ("missing_rgb_file", r"rgb_5\.png: RGB image is missing \(1 of the 12 selected"),
        ("colour_instance", r"semantic_instance_2\.png: instance map must be a single-channel"),
        ("wrong_size", r"depth_7\.png: image is 16x12 but the sequence is 32x24"),
        ("not_rotation", r"frame 4\).*not a rotation"),
    ],
)
def test_wrong_layouts_refused(room0, tmp_path, breakage, pattern):
    root, _ = room0
    seq = root / "room_0" / "Sequence_1"
    if breakage == "no_traj":
        (seq / "traj_w_c.txt").unlink()
    elif breakage == "bad_traj_line":
        lines = (seq / "traj_w_c.txt").read_text().splitlines()
        lines[2] = " ".join(lines[2].split()[:15])
        (seq / "traj_w_c.txt").write_text("\n".join(lines) + "\n")
    elif breakage == "no_rgb_dir":
        for p in (seq / "rgb").iterdir():
            p.unlink()
        (seq / "rgb").rmdir()
    elif breakage == "missing_rgb_file":
        (seq / "rgb" / "rgb_5.png").unlink()
    elif breakage == "colour_instance":
        cv2.imwrite(str(seq / "semantic_instance" / "semantic_instance_2.png"), np.zeros((H, W, 3), np.uint8))
    elif breakage == "wrong_size":
        cv2.imwrite(str(seq / "depth" / "depth_7.png"), np.zeros((12, 16), np.uint16))
    elif breakage == "not_rotation":
        lines = (seq / "traj_w_c.txt").read_text().splitlines()
        values = [float(v) for v in lines[4].split()]
        values[0] *= 2.0
        lines[4] = " ".join(str(v) for v in values)
        (seq / "traj_w_c.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(Trace3DError, match=pattern):
        replica.import_replica(root, tmp_path / "out", replica.params_from({"scene": "room0"}))


def test_source_resolution_errors(room0, tmp_path):
    root, _ = room0
    with pytest.raises(Trace3DError, match=r"no `scene` parameter.*room_0"):
        replica.import_replica(root, tmp_path / "a", replica.params_from({}))
    with pytest.raises(Trace3DError, match=r"office_2.*Sequence_1.*missing"):
        replica.import_replica(root, tmp_path / "b", replica.params_from({"scene": "office2"}))
    with pytest.raises(Trace3DError, match=r"belongs to Replica scene 'room_0'.*'office_1'"):
        replica.import_replica(root / "room_0", tmp_path / "c", replica.params_from({"scene": "office1"}))
    with pytest.raises(Trace3DError, match=r"does not exist"):
        replica.import_replica(tmp_path / "nowhere", tmp_path / "d", replica.params_from({}))


def test_params_refused():
    with pytest.raises(ConfigError, match="unknown parameter"):
        replica.params_from({"stride": 2})
    with pytest.raises(ConfigError, match="not a Replica scene"):
        replica.params_from({"scene": "kitchen"})
    with pytest.raises(ConfigError, match="frame_stride"):
        replica.params_from({"frame_stride": 0})
    with pytest.raises(ConfigError, match="init"):
        replica.params_from({"init": "random"})
    assert replica.params_from({"scene": "office_3"}).scene == "office_3"


def test_evaluated_override_and_occlusion_free_views(room0, tmp_path):
    root, _ = room0
    views = {"room_0": {"6": [0, 4, 5, 8, 400], "0": [8]}}
    (tmp_path / "views.json").write_text(json.dumps(views))
    scene = do_import(root, tmp_path / "out", scene="room0", evaluated_ids=[6, 0],
                      occlusion_free_views=str(tmp_path / "views.json"))
    assert scene.objects.evaluated_ids() == [1, 7]
    # ours = Replica id + 1; only imported test frames are kept (5 is train, 400 absent)
    assert scene.meta["evaluation_views"] == {"7": ["rgb_0000", "rgb_0004", "rgb_0008"], "1": ["rgb_0008"]}
    (tmp_path / "bad.json").write_text(json.dumps({"office_0": {}}))
    with pytest.raises(Trace3DError, match=r"bad\.json: expected an object with a 'room_0' entry"):
        do_import(root, tmp_path / "out2", scene="room0", occlusion_free_views=str(tmp_path / "bad.json"))


def test_cli_scene_replica(room0, tmp_path, capsys):
    from trace3d.cli import main

    root, _ = room0
    out = tmp_path / "results" / "room0" / "scene"
    assert main(["scene", "replica", "--source", str(root), "--params", "{scene: room0, max_frames: 4}",
                 "--out", str(out)]) == 0
    assert len(Scene.read(out).cameras) == 4
    # a refused source exits 2 with one sentence and leaves no output behind
    bad = tmp_path / "results" / "bad" / "scene"
    assert main(["scene", "replica", "--source", str(root), "--params", "{scene: office2}", "--out", str(bad)]) == 2
    assert "Sequence_1" in capsys.readouterr().err and not bad.exists()
