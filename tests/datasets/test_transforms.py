"""The transforms.json importer (trace3d/datasets/transforms.py): fixtures written from a synthetic room
in the Blender, instant-ngp and nerfstudio conventions import into cameras that reproject the room's
points onto the ground truth's pixels; distortion is undistorted into the right pinhole image; every
bad input gets one sentence."""

from __future__ import annotations

import json
import math
import shutil

import cv2
import numpy as np
import pytest

from trace3d.cli import main as cli_main
from trace3d.datasets.transforms import OPENGL_TO_OPENCV, TransformsParams, import_transforms, params_from
from trace3d.errors import Trace3DError
from trace3d.scene import Scene

W, H = 40, 30


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    """A tiny synthetic room (exact cameras and depth) and its world points [P, 3] from the depth maps."""
    root = tmp_path_factory.mktemp("room")
    params = json.dumps({"seed": 2, "width": W, "height": H, "num_views": 6, "test_every": 3, "num_objects": 4,
                         "supersample": 1})
    assert cli_main(["scene", "synthetic", "--out", str(root / "scene"), "--params", params]) == 0
    scene = Scene.read(root / "scene")
    points = []
    for cam in scene.cameras:
        depth = scene.depth(cam.name)
        ys, xs = np.mgrid[1:H:4, 1:W:4]
        z = depth[ys, xs].astype(np.float64)
        ok = z > 0
        pix = np.stack([xs[ok] + 0.5, ys[ok] + 0.5, np.ones(ok.sum())], 1)
        cam_pts = (pix @ np.linalg.inv(cam.K).T) * z[ok][:, None]
        points.append((cam_pts - cam.translation) @ cam.rotation)  # R^T (x - t)
    return scene, np.concatenate(points)


def _opengl_c2w(cam, world_rotation=np.eye(3), world_scale=1.0, world_offset=np.zeros(3)) -> list:
    """The camera's OpenGL camera-to-world in a world moved by x' = s R x + t (what colmap2nerf does)."""
    c2w = cam.camera_to_world @ OPENGL_TO_OPENCV
    out = np.eye(4)
    out[:3, :3] = world_rotation @ c2w[:3, :3]
    out[:3, 3] = world_scale * world_rotation @ c2w[:3, 3] + world_offset
    return out.tolist()


def _copy_image(scene, name, path, rgba=False):
    path.parent.mkdir(parents=True, exist_ok=True)
    bgr = cv2.cvtColor(scene.image(name), cv2.COLOR_RGB2BGR)
    if rgba:
        bgr = np.concatenate([bgr, np.full(bgr.shape[:2] + (1,), 255, np.uint8)], 2)
    cv2.imwrite(str(path), bgr)


def write_blender(scene, folder):
    """transforms_train.json / _val / _test: camera_angle_x, file paths without extension, RGBA PNGs."""
    angle = 2 * math.atan(W / (2 * scene.cameras[0].K[0, 0]))
    for split in ("train", "val", "test"):
        cams = scene.split("train" if split == "val" else split)
        frames = []
        for k, cam in enumerate(cams):
            _copy_image(scene, cam.name, folder / split / f"r_{k}.png", rgba=True)
            frames.append({"file_path": f"./{split}/r_{k}", "rotation": 0.01, "transform_matrix": _opengl_c2w(cam)})
        (folder / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))
    # Blender's names repeat across splits: r_0 of train and r_0 of test
    return {**{f"train_r_{k}": c.name for k, c in enumerate(scene.train_cameras)},
            **{f"test_r_{k}": c.name for k, c in enumerate(scene.test_cameras)}}


WORLD_ROTATION = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # colmap2nerf's axis swap
WORLD_SCALE, WORLD_OFFSET = 0.37, np.array([0.2, -1.0, 0.5])


def write_instant_ngp(scene, folder):
    """transforms.json with global fl_x/fl_y/cx/cy/w/h, zero k1 k2 p1 p2, aabb_scale, a moved world."""
    K = scene.cameras[0].K
    frames = []
    for cam in scene.cameras:
        _copy_image(scene, cam.name, folder / "images" / f"{cam.name}.png")
        frames.append({"file_path": f"./images/{cam.name}.png", "sharpness": 50.0,
                       "transform_matrix": _opengl_c2w(cam, WORLD_ROTATION, WORLD_SCALE, WORLD_OFFSET)})
    data = {"camera_angle_x": 2 * math.atan(W / (2 * K[0, 0])), "fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2],
            "cy": K[1, 2], "w": W, "h": H, "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "aabb_scale": 16,
            "frames": frames}
    (folder / "transforms.json").write_text(json.dumps(data, indent=1))
    return {c.name: c.name for c in scene.cameras}


def write_nerfstudio(scene, folder, per_frame=True):
    """transforms.json with camera_model OPENCV, per-frame intrinsics, train/test file lists."""
    frames = []
    for k, cam in enumerate(scene.cameras):
        _copy_image(scene, cam.name, folder / "images" / f"frame_{k + 1:05d}.png")
        frame = {"file_path": f"images/frame_{k + 1:05d}.png", "transform_matrix": _opengl_c2w(cam)}
        if per_frame:
            frame.update({"fl_x": cam.K[0, 0], "fl_y": cam.K[1, 1], "cx": cam.K[0, 2], "cy": cam.K[1, 2],
                          "w": cam.width, "h": cam.height})
        frames.append(frame)
    data = {"camera_model": "OPENCV", "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "frames": frames,
            "applied_transform": np.eye(4)[:3].tolist(),
            "train_filenames": [f["file_path"] for f, c in zip(frames, scene.cameras) if c.split == "train"],
            "test_filenames": [f["file_path"] for f, c in zip(frames, scene.cameras) if c.split == "test"]}
    if not per_frame:
        data.update({"fl_x": scene.cameras[0].K[0, 0], "fl_y": scene.cameras[0].K[1, 1], "w": W, "h": H})
    (folder / "transforms.json").write_text(json.dumps(data, indent=1))
    return {f"frame_{k + 1:05d}": c.name for k, c in enumerate(scene.cameras)}


def _reprojection_error(imported, truth, points, world_to_file, scale=(1.0, 1.0)) -> float:
    """Largest pixel distance between the imported camera's projection of the points (moved into the
    file's world) and the true camera's (scaled to the imported size), over points in front of it."""
    uv_true, z = truth.project(points)
    uv_imp, z_imp = imported.project(world_to_file(points))
    ok = z > 0.05
    assert ok.sum() > 20 and (z_imp[ok] > 0).all()
    uv_true = uv_true[ok] * np.asarray(scale)
    return float(np.abs(uv_imp[ok] - uv_true).max())


@pytest.mark.parametrize("convention", ["blender", "instant-ngp", "nerfstudio"])
def test_each_convention_reprojects_the_rooms_points(room, tmp_path, convention):
    scene, points = room
    source = tmp_path / "capture"
    writer = {"blender": write_blender, "instant-ngp": write_instant_ngp, "nerfstudio": write_nerfstudio}[convention]
    names = writer(scene, source)
    out = tmp_path / "scene"
    assert cli_main(["scene", "transforms", "--source", str(source), "--out", str(out)]) == 0
    imported = Scene.read(out)
    assert imported.meta["convention"] == convention and imported.meta["importer"] == "transforms"
    assert sorted(names) == sorted(c.name for c in imported.cameras)  # the val file is not imported
    if convention == "instant-ngp":
        moved = lambda x: WORLD_SCALE * x @ WORLD_ROTATION.T + WORLD_OFFSET  # noqa: E731
        assert imported.meta["aabb_scale"] == 16
    else:
        moved = lambda x: x  # noqa: E731
    for cam in imported.cameras:
        truth = scene.camera(names[cam.name])
        assert (cam.width, cam.height) == (W, H)
        if convention != "instant-ngp":
            assert cam.split == truth.split  # Blender's files, nerfstudio's lists
        assert _reprojection_error(cam, truth, points, moved) < 0.5
        np.testing.assert_array_equal(imported.image(cam.name), scene.image(truth.name))
    if convention == "instant-ngp":
        assert [c.split for c in imported.cameras] == ["test"] + ["train"] * 5  # test_every 8, no split in file


def test_max_side_scales_intrinsics_and_points_follow(room, tmp_path):
    scene, points = room
    names = write_nerfstudio(scene, tmp_path / "ns", per_frame=False)
    out = tmp_path / "scene"
    import_transforms(tmp_path / "ns", out, TransformsParams(max_side=32))
    imported = Scene.read(out)
    for cam in imported.cameras:
        assert (cam.width, cam.height) == (32, 24)
        assert _reprojection_error(cam, scene.camera(names[cam.name]), points, lambda x: x, (0.8, 0.8)) < 0.5


def test_blender_rgba_is_composited_over_the_background(room, tmp_path):
    scene, _ = room
    write_blender(scene, tmp_path / "b")
    path = tmp_path / "b" / "train" / "r_0.png"
    rgba = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    rgba[:5, :5, 3] = 0  # transparent corner
    rgba[5:10, :5, 3] = 128
    cv2.imwrite(str(path), rgba)
    for background, value in (("white", 255), ("black", 0)):
        import_transforms(tmp_path / "b", tmp_path / background, TransformsParams(background=background))
        image = Scene.read(tmp_path / background).image("train_r_0")
        assert (image[:5, :5] == value).all()
        first = scene.image(scene.train_cameras[0].name)
        expected = np.round(first[5:10, :5].astype(float) * 128 / 255 + value * 127 / 255)
        assert np.abs(image[5:10, :5].astype(int) - expected).max() <= 1


def test_unknown_poses_leave_placeholders_for_colmap(room, tmp_path):
    scene, _ = room
    write_instant_ngp(scene, tmp_path / "ngp")
    data = json.loads((tmp_path / "ngp" / "transforms.json").read_text())
    del data["frames"][2]["transform_matrix"]  # a frame with no pose is fine when the poses are unknown
    (tmp_path / "ngp" / "transforms.json").write_text(json.dumps(data))
    import_transforms(tmp_path / "ngp", tmp_path / "s", params_from({"poses": "unknown"}))
    imported = Scene.read(tmp_path / "s")
    assert imported.meta["poses"] == "unknown"
    for cam in imported.cameras:
        np.testing.assert_array_equal(cam.world_to_camera, np.eye(4))
        np.testing.assert_allclose(cam.K, scene.camera(cam.name).K)
    from trace3d.poses.align import scene_has_reference_poses
    from trace3d.poses.colmap import scene_intrinsics_are_guessed

    assert not scene_has_reference_poses(imported)  # the poses step must run COLMAP (mode dataset refused)
    assert not scene_intrinsics_are_guessed(imported)  # ... from the file's intrinsics


def _analytic_image(x, y):
    """A smooth RGB pattern [.., 3] in [0, 255] at continuous pixel coordinates of the pinhole image."""
    return np.stack([127 + 100 * np.sin(x / 6.0), 127 + 100 * np.cos(y / 5.0), 127 + 80 * np.sin((x + y) / 9.0)], -1)


@pytest.mark.parametrize("model", ["OPENCV", "OPENCV_FISHEYE"])
def test_distorted_images_are_undistorted_into_the_pinhole_view(tmp_path, model):
    """A distorted capture of an analytic pinhole image: the undistorted import, read at its own K, is
    that pinhole image (checked at the imported K's rays), and ``distortion: refuse`` refuses it."""
    width, height, f = 80, 60, 50.0
    K = np.array([[f, 0, 41.0], [0, f, 29.5], [0, 0, 1.0]])
    if model == "OPENCV":
        coeffs = {"k1": -0.25, "k2": 0.05, "p1": 0.002, "p2": -0.001}
        D = np.array([-0.25, 0.05, 0.002, -0.001, 0.0])
    else:
        coeffs = {"k1": 0.15, "k2": -0.01, "k3": 0.002, "k4": 0.0}
        D = np.array([0.15, -0.01, 0.002, 0.0])
    # the distorted image: every distorted pixel centre -> its pinhole pixel (OpenCV: centres at integers)
    K_cv = K.copy()
    K_cv[:2, 2] -= 0.5
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    distorted_px = np.stack([xs.ravel(), ys.ravel()], 1)[:, None, :]
    if model == "OPENCV":
        ideal = cv2.undistortPoints(distorted_px, K_cv, D, P=K_cv)[:, 0]
    else:
        ideal = cv2.fisheye.undistortPoints(distorted_px, K_cv, D, P=K_cv)[:, 0]
    image = _analytic_image(ideal[:, 0] + 0.5, ideal[:, 1] + 0.5).reshape(height, width, 3)
    (tmp_path / "cap" / "images").mkdir(parents=True)
    for k in range(2):
        cv2.imwrite(str(tmp_path / "cap" / "images" / f"{k}.png"),
                    cv2.cvtColor(image.round().astype(np.uint8), cv2.COLOR_RGB2BGR))
    pose = np.eye(4).tolist()
    data = {"camera_model": model, "fl_x": f, "fl_y": f, "cx": 41.0, "cy": 29.5, "w": width, "h": height, **coeffs,
            "frames": [{"file_path": f"images/{k}.png", "transform_matrix": pose} for k in range(2)]}
    (tmp_path / "cap" / "transforms.json").write_text(json.dumps(data))
    import_transforms(tmp_path / "cap", tmp_path / "s", TransformsParams(test_every=0))
    imported = Scene.read(tmp_path / "s")
    assert imported.meta["undistorted"] == ["fisheye" if model == "OPENCV_FISHEYE" else "opencv"]
    cam = imported.camera("0")
    assert not np.allclose(cam.K, K)  # zoomed so that every pixel is covered
    got = imported.image("0").astype(np.float64)
    # each imported pixel centre's ray, seen by the pinhole camera K
    pix = np.stack([xs + 0.5, ys + 0.5, np.ones_like(xs)], -1) @ np.linalg.inv(cam.K).T @ K.T
    expected = _analytic_image(pix[..., 0], pix[..., 1])
    inner = (slice(3, -3), slice(3, -3))
    assert np.abs(got[inner] - expected[inner]).mean() < 1.5  # 0.39 (OPENCV) and 0.36 (fisheye) measured
    # without undistortion (the distorted image taken as pinhole) the same check fails clearly
    assert np.abs(image[inner] - expected[inner]).mean() > 4.0  # 16.1 and 6.2
    with pytest.raises(Trace3DError, match="distortion coefficients"):
        import_transforms(tmp_path / "cap", tmp_path / "r", TransformsParams(distortion="refuse"))


# ----------------------------------------------------------------------------------------------
# bad input: one sentence each, exit status 2 from the CLI, nothing written
# ----------------------------------------------------------------------------------------------


def _edit(folder, fn):
    path = folder / "transforms.json"
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))


def _set_matrix(data, k, matrix):
    data["frames"][k]["transform_matrix"] = matrix


SCALED = (np.diag([1.5, 1.5, 1.5, 1.0])).tolist()
SHEARED = [[1.0, 0.4, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
MIRRORED = np.diag([1.0, 1.0, -1.0, 1.0]).tolist()


@pytest.mark.parametrize("case, edit, message", [
    ("every image missing", lambda d: [f.update(file_path=f"./images/nope{k}.png") for k, f in enumerate(d["frames"])],
     "have an image file"),
    ("no pose", lambda d: d["frames"][3].pop("transform_matrix"), "no 'transform_matrix'"),
    ("scaled rotation", lambda d: _set_matrix(d, 0, SCALED), "not a rotation"),
    ("sheared", lambda d: _set_matrix(d, 0, SHEARED), "not a rotation"),
    ("reflection", lambda d: _set_matrix(d, 0, MIRRORED), "not a rotation"),
    ("bad last row", lambda d: d["frames"][0]["transform_matrix"][3].__setitem__(0, 0.5), "last row"),
    ("wrong shape", lambda d: _set_matrix(d, 0, [[1.0, 0.0], [0.0, 1.0]]), "shape"),
    ("no focal", lambda d: [d.pop(k) for k in ("fl_x", "fl_y", "camera_angle_x")], "no focal length"),
    ("size mismatch", lambda d: d.update(w=64), "the file says"),
    ("no file_path", lambda d: d["frames"][0].pop("file_path"), "no 'file_path'"),
    ("empty", lambda d: d.update(frames=[]), "empty"),
    ("unsupported model", lambda d: d.update(camera_model="EQUIRECTANGULAR"), "not supported"),
])
def test_bad_input_is_one_sentence(room, tmp_path, case, edit, message, capsys):
    scene, _ = room
    write_instant_ngp(scene, tmp_path / "ngp")
    _edit(tmp_path / "ngp", edit)
    out = tmp_path / "out"
    assert cli_main(["scene", "transforms", "--source", str(tmp_path / "ngp"), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if "error:" in line]
    assert len(errors) == 1 and "Traceback" not in err, err
    assert message in errors[0] and ("transforms.json" in errors[0] or "nope.png" in errors[0]), err
    assert not out.exists()


def test_frames_without_images_are_skipped_and_named(room, tmp_path, caplog):
    """A capture listing more frames than it ships images for imports the others, says so in one line
    (how many, the first three), and is refused only below min_images."""
    scene, points = room
    write_instant_ngp(scene, tmp_path / "ngp")
    gone = [scene.cameras[k].name for k in (1, 2, 4, 5)]
    for name in gone:
        (tmp_path / "ngp" / "images" / f"{name}.png").unlink()
    with caplog.at_level("WARNING", logger="trace3d.datasets.transforms"):
        import_transforms(tmp_path / "ngp", tmp_path / "s", TransformsParams(test_every=0))
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1, warnings
    assert f"skipped 4 of {len(scene.cameras)} frames" in warnings[0]
    assert all(f"{name}.png" in warnings[0] for name in gone[:3]) and "and 1 more" in warnings[0]
    assert f"{gone[3]}.png" not in warnings[0]
    imported = Scene.read(tmp_path / "s")
    kept = [c.name for c in scene.cameras if c.name not in gone]
    assert [c.name for c in imported.cameras] == kept
    for name in kept:  # the kept frames keep their own poses
        assert _reprojection_error(imported.camera(name), scene.camera(name), points,
                                   lambda x: WORLD_SCALE * x @ WORLD_ROTATION.T + WORLD_OFFSET) < 0.5
    # below the stated minimum: refused, naming the file, the counts and the first missing images
    with pytest.raises(Trace3DError, match=rf"only 2 of its {len(scene.cameras)} frames have an image file .*"
                                           r"fewer than min_images 3"):
        import_transforms(tmp_path / "ngp", tmp_path / "r", TransformsParams(min_images=3))
    assert not (tmp_path / "r").exists()


def test_mixed_sizes_need_per_frame_intrinsics(room, tmp_path):
    scene, points = room
    names = write_nerfstudio(scene, tmp_path / "ns", per_frame=False)
    # one image at half size: global intrinsics cannot describe it
    small = tmp_path / "ns" / "images" / "frame_00002.png"
    cv2.imwrite(str(small), cv2.resize(cv2.imread(str(small)), (W // 2, H // 2), interpolation=cv2.INTER_AREA))
    _edit(tmp_path / "ns", lambda d: [d.pop(k) for k in ("w", "h")])
    with pytest.raises(Trace3DError, match=r"different sizes .* frame 1 \(images/frame_00002.png\)"):  # the odd one
        import_transforms(tmp_path / "ns", tmp_path / "s", TransformsParams())
    # with its own (halved) intrinsics, the frame imports at its size and reprojects
    cam = scene.camera(names["frame_00002"])
    _edit(tmp_path / "ns", lambda d: d["frames"][1].update(fl_x=cam.K[0, 0] / 2, fl_y=cam.K[1, 1] / 2,
                                                           cx=cam.K[0, 2] / 2, cy=cam.K[1, 2] / 2))
    _edit(tmp_path / "ns", lambda d: [f.update(fl_x=d["fl_x"]) for f in d["frames"] if "fl_x" not in f])
    import_transforms(tmp_path / "ns", tmp_path / "s", TransformsParams())
    imported = Scene.read(tmp_path / "s").camera("frame_00002")
    assert (imported.width, imported.height) == (W // 2, H // 2)
    assert _reprojection_error(imported, cam, points, lambda x: x, (0.5, 0.5)) < 0.5


def test_a_byte_order_mark_and_windows_paths_are_read(room, tmp_path):
    """A transforms.json saved by a Windows editor (UTF-8 BOM) with backslashes in file_path imports as the
    same scene as the plain file (issue 49)."""
    scene, _ = room
    write_nerfstudio(scene, tmp_path / "plain")
    import_transforms(tmp_path / "plain", tmp_path / "a", TransformsParams())
    shutil.copytree(tmp_path / "plain", tmp_path / "win")
    _edit(tmp_path / "win", lambda d: [f.update(file_path=f["file_path"].replace("/", "\\")) for f in d["frames"]])
    path = tmp_path / "win" / "transforms.json"
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    import_transforms(tmp_path / "win", tmp_path / "b", TransformsParams())
    assert (tmp_path / "a" / "cameras.json").read_bytes() == (tmp_path / "b" / "cameras.json").read_bytes()
    assert sorted(p.name for p in (tmp_path / "b" / "images").iterdir()) == \
        sorted(p.name for p in (tmp_path / "a" / "images").iterdir())


def test_source_errors_and_params(tmp_path):
    with pytest.raises(Trace3DError, match="does not exist"):
        import_transforms(tmp_path / "none", tmp_path / "s", TransformsParams())
    (tmp_path / "empty").mkdir()
    with pytest.raises(Trace3DError, match="neither transforms.json"):
        import_transforms(tmp_path / "empty", tmp_path / "s", TransformsParams())
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(Trace3DError, match="not valid JSON"):
        import_transforms(tmp_path / "bad.json", tmp_path / "s", TransformsParams())
    with pytest.raises(Trace3DError, match="frame_strid"):
        params_from({"frame_strid": 2})
    with pytest.raises(Trace3DError):
        params_from({"poses": "maybe"})


def test_imported_capture_runs_poses_and_fit(room, tmp_path):
    """The imported scene feeds the poses step (dataset mode) and a short 2DGS fit."""
    scene, _ = room
    write_blender(scene, tmp_path / "b")
    out = tmp_path / "scene"
    assert cli_main(["scene", "transforms", "--source", str(tmp_path / "b"), "--out", str(out)]) == 0
    assert cli_main(["poses", "--scene", str(out), "--out", str(tmp_path / "poses"), "--params",
                     "{mode: dataset, dataset_points: none}"]) == 0
    fit = json.dumps({"schedule_scale": 1.0, "iterations": 12, "densify_from": 100, "sh_degree": 0,
                      "device": "cpu", "init": "random", "random_init_count": 800})
    assert cli_main(["gaussians", "--scene", str(out), "--poses", str(tmp_path / "poses"), "--out",
                     str(tmp_path / "gaussians"), "--params", fit]) == 0
    assert (tmp_path / "gaussians" / "point_cloud.ply").stat().st_size > 0


def test_readme_capture_config_dry_runs(tmp_path):
    """The README's `Your own capture` config, data_root pointing here: schema-valid (kind transforms), and
    the scene rule imports the capture with the importer parameters, the poses step in dataset mode."""
    import os
    import re
    import subprocess
    import sys
    from pathlib import Path

    import yaml

    repo = Path(__file__).resolve().parents[2]
    snakemake = shutil.which("snakemake", path=str(Path(sys.executable).parent)) or shutil.which("snakemake")
    if snakemake is None:
        pytest.skip("snakemake is not installed")
    section = (repo / "docs" / "capture.md").read_text().split("## Your own capture", 1)[1]
    config = yaml.safe_load(re.search(r"```yaml\n(.*?)```", section, flags=re.S).group(1))
    assert config["scenes"]["lego"]["kind"] == "transforms"
    config["data_root"] = str(tmp_path / "captures")
    (tmp_path / "captures" / config["scenes"]["lego"]["source"]).mkdir(parents=True)
    config["results"] = str(tmp_path / "results")
    (tmp_path / "my.yaml").write_text(yaml.safe_dump(config))
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    out = subprocess.run([snakemake, "-s", str(repo / "Snakefile"), "-n", "-p", "--cores", "2",
                          "--configfile=my.yaml", f"{tmp_path}/results/lego/gaussians"],
                         cwd=tmp_path, capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
    assert f"scene transforms --source {tmp_path}/captures/lego" in out.stdout
    assert '"max_side": 400' in out.stdout and '"mode": "dataset"' in out.stdout
    # the README's extract line parses (the flags the CLI knows)
    line = re.search(r"(trace3d extract .*?)\n\n", section, flags=re.S).group(1).replace("\\\n", " ")
    from trace3d.cli import build_parser

    args = build_parser().parse_args(line.split()[1:])
    assert args.view == "train_r_12" and args.point == "210,160"


def test_capture_doc_two_core_config_dry_runs(tmp_path):
    """docs/capture.md's 2-core capture config: an explicit fit length and lift, geometry masks, and the DAG
    gaussians -> masks (geometry) -> patches -> trace."""
    import os
    import re
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    import yaml

    repo = Path(__file__).resolve().parents[2]
    snakemake = shutil.which("snakemake", path=str(Path(sys.executable).parent)) or shutil.which("snakemake")
    if snakemake is None:
        pytest.skip("snakemake is not installed")
    section = (repo / "docs" / "capture.md").read_text().split("## A capture end to end on 2 CPU cores", 1)[1]
    config = yaml.safe_load(re.search(r"```yaml\n(.*?)```", section, flags=re.S).group(1))
    assert config["defaults"]["lift"]["iterations"] and config["defaults"]["gaussians"]["schedule_scale"]
    assert config["defaults"]["masks"]["source"] == "geometry"
    config["data_root"] = str(tmp_path / "captures")
    (tmp_path / "captures" / config["scenes"]["fern"]["source"]).mkdir(parents=True)
    config["results"] = str(tmp_path / "results")
    (tmp_path / "fern.yaml").write_text(yaml.safe_dump(config))
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    out = subprocess.run([snakemake, "-s", str(repo / "Snakefile"), "-n", "-p", "--cores", "2",
                          "--configfile=fern.yaml", f"{tmp_path}/results/fern/trace-paper"],
                         cwd=tmp_path, capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
    masks = re.search(r"trace3d --threads \d+ masks .*", out.stdout).group(0)
    assert "--source geometry" in masks and f"--gaussians {tmp_path}/results/fern/gaussians" in masks
    assert '"schedule_scale": 0.05' in out.stdout and '"images_factor": 8' in out.stdout
    # the `coarse` variant the section's results come from: the raw patches lifted with the coarse blocks
    out = subprocess.run([snakemake, "-s", str(repo / "Snakefile"), "-n", "-p", "--cores", "2",
                          "--configfile=fern.yaml", f"{tmp_path}/results/fern/coarse/segment"],
                         cwd=tmp_path, capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
    lift = re.search(r"trace3d --threads \d+ lift .*", out.stdout).group(0)
    assert f"--labels {tmp_path}/results/fern/patches" in lift and '"coarse_depth": [1, 0]' in lift
