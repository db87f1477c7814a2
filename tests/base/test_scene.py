"""The canonical scene format: round trip and every validation error."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from trace3d.errors import SceneFormatError
from trace3d.scene import (
    Camera,
    ObjectTable,
    Scene,
    SceneObject,
    write_cameras,
    write_frame,
    write_u16,
    write_rgb,
)
from trace3d.io import write_json

W, H = 16, 12


def look_at(center, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """[4, 4] OpenCV world_to_camera looking from ``center`` to ``target``."""
    center, target, up = map(np.asarray, (center, target, up))
    z = target - center
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ center
    return w2c


def make_scene(root, n=3, with_instances=True, with_depth=True):
    K = np.array([[20.0, 0, W / 2], [0, 20.0, H / 2], [0, 0, 1]])
    cams = []
    rng = np.random.default_rng(0)
    for i in range(n):
        angle = 2 * math.pi * i / n
        w2c = look_at([3 * math.cos(angle), 3 * math.sin(angle), 1.0], [0, 0, 0.5])
        cam = Camera(f"{i:05d}", "test" if i == n - 1 else "train", W, H, K, w2c)
        cams.append(cam)
        inst = rng.integers(0, 4, size=(H, W)).astype(np.uint16) if with_instances else None
        depth = rng.uniform(0.5, 5.0, size=(H, W)) if with_depth else None
        write_frame(root, cam.name, rng.integers(0, 255, (H, W, 3), dtype=np.uint8), inst, depth)
    write_cameras(root, cams)
    objects = ObjectTable(
        [
            SceneObject(1, "table", "object", 3, "table", True),
            SceneObject(2, "table/leg", "part", 1, "table", False),
            SceneObject(3, "dining group", "group", None, "group", False),
        ]
    )
    write_json(root / "objects.json", objects.to_json())
    return cams


def test_round_trip(tmp_path):
    cams = make_scene(tmp_path)
    scene = Scene.read(tmp_path)
    assert [c.name for c in scene.cameras] == [c.name for c in cams]
    for a, b in zip(scene.cameras, cams):
        np.testing.assert_allclose(a.world_to_camera, b.world_to_camera)
        np.testing.assert_allclose(a.K, b.K)
        assert a.split == b.split
    assert [c.name for c in scene.test_cameras] == ["00002"]
    assert scene.image("00000").shape == (H, W, 3)
    assert scene.instances("00000").dtype == np.uint16
    depth = scene.depth("00001")
    assert depth.dtype == np.float32 and depth.min() >= 0.5 - 1e-3
    assert scene.objects.evaluated_ids() == [1]
    assert scene.objects.ancestor(2, "object") == 1
    assert scene.objects.ancestor(2, "group") == 3
    assert scene.objects.ancestor(3, "part") == 3
    np.testing.assert_array_equal(scene.objects.lookup("object"), [0, 1, 1, 3])


def test_camera_geometry():
    w2c = look_at([1.0, 2.0, 3.0], [0.0, 0.0, 0.0])
    cam = Camera("a", "train", W, H, np.eye(3), w2c)
    np.testing.assert_allclose(cam.center, [1.0, 2.0, 3.0], atol=1e-12)
    np.testing.assert_allclose(cam.camera_to_world @ cam.world_to_camera, np.eye(4), atol=1e-12)
    _, z = cam.project(np.zeros((1, 3)))
    assert z[0] == pytest.approx(math.sqrt(14))


def _edit_cameras(root, **changes):
    data = json.loads((root / "cameras.json").read_text())
    data["frames"][0].update(changes)
    (root / "cameras.json").write_text(json.dumps(data))


def test_missing_image(tmp_path):
    make_scene(tmp_path)
    (tmp_path / "images" / "00001.png").unlink()
    with pytest.raises(SceneFormatError, match=r"00001\.png: image file is missing"):
        Scene.read(tmp_path)


def test_corrupt_image(tmp_path):
    make_scene(tmp_path)
    (tmp_path / "images" / "00001.png").write_bytes(b"not a png")
    with pytest.raises(SceneFormatError, match=r"00001\.png: image file is corrupt"):
        Scene.read(tmp_path)


def test_size_mismatch(tmp_path):
    make_scene(tmp_path)
    write_rgb(tmp_path / "images" / "00000.png", np.zeros((H + 1, W, 3), np.uint8))
    with pytest.raises(SceneFormatError, match=rf"00000\.png: image is {W}x{H + 1} but cameras.json says {W}x{H}"):
        Scene.read(tmp_path)


def test_non_orthonormal_rotation(tmp_path):
    make_scene(tmp_path)
    bad = np.eye(4)
    bad[0, 0] = 1.5
    _edit_cameras(tmp_path, world_to_camera=bad.tolist())
    with pytest.raises(SceneFormatError, match="not orthonormal"):
        Scene.read(tmp_path)


def test_reflection_refused(tmp_path):
    make_scene(tmp_path)
    bad = np.diag([1.0, 1.0, -1.0, 1.0])
    _edit_cameras(tmp_path, world_to_camera=bad.tolist())
    with pytest.raises(SceneFormatError, match="det"):
        Scene.read(tmp_path)


def test_unknown_split(tmp_path):
    make_scene(tmp_path)
    _edit_cameras(tmp_path, split="validation")
    with pytest.raises(SceneFormatError, match="unknown split 'validation'"):
        Scene.read(tmp_path)


def test_instance_map_wrong_size(tmp_path):
    make_scene(tmp_path)
    write_u16(tmp_path / "instances" / "00002.png", np.zeros((H, W + 2), np.uint16))
    with pytest.raises(SceneFormatError, match=rf"instances/00002\.png: instance map is {W + 2}x{H}"):
        Scene.read(tmp_path)


def test_instance_map_wrong_dtype(tmp_path):
    make_scene(tmp_path)
    write_rgb(tmp_path / "instances" / "00002.png", np.zeros((H, W, 3), np.uint8))
    with pytest.raises(SceneFormatError, match=r"instances/00002\.png: instance map must be a 16-bit"):
        Scene.read(tmp_path)


def test_missing_cameras_json(tmp_path):
    make_scene(tmp_path)
    (tmp_path / "cameras.json").unlink()
    with pytest.raises(SceneFormatError, match="cameras.json is missing"):
        Scene.read(tmp_path)


def test_corrupt_cameras_json(tmp_path):
    make_scene(tmp_path)
    (tmp_path / "cameras.json").write_text("{not json")
    with pytest.raises(SceneFormatError, match="cameras.json: not valid JSON"):
        Scene.read(tmp_path)


def test_missing_key(tmp_path):
    make_scene(tmp_path)
    data = json.loads((tmp_path / "cameras.json").read_text())
    del data["frames"][0]["K"]
    (tmp_path / "cameras.json").write_text(json.dumps(data))
    with pytest.raises(SceneFormatError, match=r"missing the key\(s\) \['K'\]"):
        Scene.read(tmp_path)


def test_objects_unknown_parent(tmp_path):
    make_scene(tmp_path)
    write_json(tmp_path / "objects.json", {"objects": [{"id": 1, "name": "a", "parent": 7}]})
    with pytest.raises(SceneFormatError, match="names parent 7"):
        Scene.read(tmp_path)
