"""LLFF and NVOS importers: tiny fixtures in the exact release layouts, imported and checked.

The fixture is a forward-facing capture of a sphere (the NVOS "object") in front of a textured
wall.  poses_bounds.npy is written in LLFF's [down, right, back] axes, images_4/ at a quarter of
the hwf size, and the NVOS labels (target mask, reference image, scribbles) at the images_4 size,
as in the real release.  The sphere's silhouette is known analytically, so prompts and masks can
be checked through the imported cameras.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from trace3d.datasets import llff
from trace3d.errors import ConfigError, Trace3DError
from trace3d.scene import Scene

W, H = 32, 24  # images_4 size
FULL_W, FULL_H, FULL_F = 128, 96, 110.0  # hwf of the "full-resolution" capture
SPHERE_C, SPHERE_R = np.array([0.0, 0.0, 0.0]), 0.6
FERN_NAMES = [f"IMG_{n}" for n in range(4027, 4039)]  # contains target IMG_4027 and reference IMG_4038


def look_at_c2w(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """[4, 4] OpenCV camera-to-world (x right, y down, z forward), world z up."""
    forward = (target - position) / np.linalg.norm(target - position)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([right, np.cross(forward, right), forward], axis=1)
    c2w[:3, 3] = position
    return c2w


def capture_poses(n: int) -> list[np.ndarray]:
    out = []
    for k in range(n):
        a = 2 * math.pi * k / n
        out.append(look_at_c2w(np.array([0.5 * math.cos(a), -3.0, 0.35 * math.sin(a)]), np.array([0.0, 0.0, 0.1])))
    return out


def rays(c2w: np.ndarray, width: int, height: int, focal: float) -> tuple[np.ndarray, np.ndarray]:
    cols, rows = np.meshgrid(np.arange(width), np.arange(height))
    d = np.stack([(cols + 0.5 - width / 2) / focal, (rows + 0.5 - height / 2) / focal, np.ones((height, width))], -1)
    return c2w[:3, 3], d @ c2w[:3, :3].T


def hits_sphere(origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """[...] bool: the ray meets the sphere."""
    oc = origin - SPHERE_C
    a = (dirs * dirs).sum(-1)
    b = 2 * (dirs * oc).sum(-1)
    c = oc @ oc - SPHERE_R**2
    return b * b - 4 * a * c >= 0


def render(c2w: np.ndarray, width: int = W, height: int = H) -> tuple[np.ndarray, np.ndarray]:
    """rgb [H, W, 3] uint8 and the sphere silhouette [H, W] bool."""
    origin, dirs = rays(c2w, width, height, FULL_F * width / FULL_W)
    sphere = hits_sphere(origin, dirs)
    t_wall = (2.0 - origin[1]) / dirs[..., 1]
    wall = origin + dirs * t_wall[..., None]
    checker = (np.floor(wall[..., 0] * 3) + np.floor(wall[..., 2] * 3)).astype(int) % 2
    rgb = np.where(checker[..., None] == 1, [90, 140, 200], [40, 60, 90]).astype(np.uint8)
    rgb[sphere] = [230, 120, 40]
    return rgb, sphere


def to_llff(c2w: np.ndarray) -> np.ndarray:
    """[3, 5] LLFF pose row: [down, right, back] columns, position, hwf."""
    return np.concatenate([np.stack([c2w[:3, 1], c2w[:3, 0], -c2w[:3, 2], c2w[:3, 3]], 1),
                           np.array([[FULL_H], [FULL_W], [FULL_F]])], 1)


def write_llff_scene(scene_dir: Path, names: list[str]) -> list[np.ndarray]:
    poses = capture_poses(len(names))
    rows = []
    for c2w in poses:
        mat = to_llff(c2w)
        # the fixture's LLFF matrix means what LLFF says: "back" points away from what the camera
        # sees, "down" points down in a z-up world for an upright camera
        assert mat[:, 2] @ (SPHERE_C - c2w[:3, 3]) < 0 and mat[2, 0] < 0
        rows.append(np.concatenate([mat.ravel(), [1.5, 6.0]]))
    scene_dir.mkdir(parents=True, exist_ok=True)
    np.save(scene_dir / "poses_bounds.npy", np.array(rows))
    (scene_dir / "images_4").mkdir()
    for name, c2w in zip(names, poses):
        rgb, _ = render(c2w)
        cv2.imwrite(str(scene_dir / "images_4" / f"{name}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    return poses


def write_nvos_labels(labels: Path, obj: str, target_c2w: np.ndarray, reference_c2w: np.ndarray,
                      scribble_stem: str | None = None) -> None:
    """NVOS label files at the images_4 size (as the release: 1008x756 for 4032x3024 captures)."""
    _, target, reference = llff.NVOS_OBJECTS[obj]
    stem = scribble_stem or obj
    for sub in ("masks", "reference_image", "scribbles"):
        (labels / sub / obj).mkdir(parents=True, exist_ok=True)
    rgb_t, sil_t = render(target_c2w)
    cv2.imwrite(str(labels / "masks" / obj / f"{target}.JPG"), rgb_t)
    cv2.imwrite(str(labels / "masks" / obj / f"{target}_mask.png"), sil_t.astype(np.uint8) * 255)
    rgb_r, sil_r = render(reference_c2w)
    cv2.imwrite(str(labels / "reference_image" / obj / f"{reference}.JPG"), rgb_r)
    pos = np.zeros((H, W, 3), np.uint8)  # scribbles drawn in colour, as in the release
    neg = np.zeros((H, W, 3), np.uint8)
    inner = cv2.erode(sil_r.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    rows, cols = np.nonzero(inner)
    cross = np.zeros_like(inner)
    cross[int(np.median(rows)), :] = True
    cross[:, int(np.median(cols))] = True
    pos[cross & inner] = (0, 255, 0)  # a cross-shaped stroke inside the sphere
    neg[2, 1 : W - 1] = (0, 0, 255)
    neg[1 : H - 1, 1] = (0, 0, 255)
    assert not (neg.any(-1) & sil_r).any()
    cv2.imwrite(str(labels / "scribbles" / obj / f"pos_0_{stem}.png"), pos)
    cv2.imwrite(str(labels / "scribbles" / obj / f"neg_0_{stem}.png"), neg)


@pytest.fixture
def nvos_root(tmp_path: Path) -> tuple[Path, list[np.ndarray]]:
    root = tmp_path / "nvos"
    poses = write_llff_scene(root / "fern", FERN_NAMES)
    write_nvos_labels(root / "labels" / "llff", "fern", poses[0], poses[-1])
    return root, poses


def point_rays_hit(cam, points: np.ndarray) -> np.ndarray:
    """[P] bool: rays of the imported camera through (x, y) pixel coordinates meet the sphere."""
    pix = np.concatenate([points, np.ones((len(points), 1))], 1)
    dirs = (pix @ np.linalg.inv(cam.K).T) @ cam.camera_to_world[:3, :3].T
    return hits_sphere(cam.center, dirs)


# ----------------------------------------------------------------------------------------------


def test_llff_round_trip(nvos_root, tmp_path):
    root, poses = nvos_root
    llff.import_llff(root / "fern", tmp_path / "out", llff.params_from({}))
    scene = Scene.read(tmp_path / "out")
    assert [c.name for c in scene.cameras] == FERN_NAMES
    assert [c.name for c in scene.test_cameras] == ["IMG_4027", "IMG_4035"]  # positions 0 and 8
    for cam, c2w in zip(scene.cameras, poses):
        assert (cam.width, cam.height) == (W, H)
        np.testing.assert_allclose(cam.K, [[FULL_F / 4, 0, 16], [0, FULL_F / 4, 12], [0, 0, 1]])
        np.testing.assert_allclose(cam.camera_to_world, c2w, atol=1e-9)
        rgb, sil = render(c2w)
        np.testing.assert_array_equal(scene.image(cam.name), rgb)
        # the imported camera sees the sphere exactly where it was rendered
        rows, cols = np.nonzero(np.ones((H, W), bool))
        hit = point_rays_hit(cam, np.stack([cols + 0.5, rows + 0.5], 1)).reshape(H, W)
        np.testing.assert_array_equal(hit, sil)
    assert scene.meta["llff"]["bounds"]["IMG_4030"] == [1.5, 6.0]
    assert scene.meta["llff"]["focal_scale_from_hwf"] == pytest.approx(0.25)


def test_llff_scene_subfolder_and_test_every(nvos_root, tmp_path):
    root, _ = nvos_root
    llff.import_llff(root, tmp_path / "out", llff.params_from({"scene": "fern", "test_every": 0}))
    assert not Scene.read(tmp_path / "out").test_cameras


def test_nvos_round_trip(nvos_root, tmp_path):
    root, poses = nvos_root
    llff.import_nvos(root, tmp_path / "out", llff.params_from({"scene": "fern"}))
    scene = Scene.read(tmp_path / "out")
    assert [c.name for c in scene.test_cameras] == ["IMG_4027"]
    assert len(scene.train_cameras) == 11
    nvos = scene.meta["nvos"]
    assert (nvos["reference_frame"], nvos["target_frame"], nvos["llff_scene"]) == ("IMG_4038", "IMG_4027", "fern")
    target_mask = cv2.imread(str(scene.root / nvos["target_mask"]), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(target_mask > 0, render(poses[0])[1])
    ref = scene.camera(nvos["reference_frame"])
    pos, neg = np.array(nvos["positive_points"]), np.array(nvos["negative_points"])
    assert len(pos) >= 1 and len(neg) >= 1
    assert point_rays_hit(ref, pos).all()  # positive prompts lie on the object in 3D
    assert not point_rays_hit(ref, neg).any()
    assert ((pos >= 0) & (pos <= [W, H])).all()
    # seeded: same seed, same points; SA3D's default fractions keep about 2 % / 0.5 % of the skeleton
    llff.import_nvos(root, tmp_path / "again", llff.params_from({"scene": "fern"}))
    assert Scene.read(tmp_path / "again").meta["nvos"]["positive_points"] == nvos["positive_points"]
    llff.import_nvos(root, tmp_path / "all", llff.params_from({"scene": "fern", "positive_fraction": 1.0,
                                                               "negative_fraction": 1.0}))
    dense = Scene.read(tmp_path / "all").meta["nvos"]
    assert len(dense["positive_points"]) > 3 * len(pos)
    assert point_rays_hit(ref, np.array(dense["positive_points"])).all()
    assert not point_rays_hit(ref, np.array(dense["negative_points"])).any()


def test_nvos_downscale_scales_prompts_and_mask(nvos_root, tmp_path):
    root, poses = nvos_root
    params = {"scene": "fern", "downscale": 2, "positive_fraction": 1.0, "negative_fraction": 1.0}
    llff.import_nvos(root, tmp_path / "out", llff.params_from(params))
    scene = Scene.read(tmp_path / "out")
    ref = scene.camera("IMG_4038")
    assert (ref.width, ref.height) == (16, 12)
    np.testing.assert_allclose(ref.K, [[FULL_F / 8, 0, 8], [0, FULL_F / 8, 6], [0, 0, 1]])
    nvos = scene.meta["nvos"]
    full = llff.params_from({**params, "downscale": 1})
    llff.import_nvos(root, tmp_path / "full", full)
    pos_full = np.array(Scene.read(tmp_path / "full").meta["nvos"]["positive_points"])
    np.testing.assert_allclose(np.array(nvos["positive_points"]), pos_full / 2, atol=1e-3)
    assert point_rays_hit(ref, np.array(nvos["positive_points"])).all()
    mask = cv2.imread(str(scene.root / nvos["target_mask"]), cv2.IMREAD_UNCHANGED) > 0
    tgt = scene.camera("IMG_4027")
    assert mask.shape == (12, 16)
    rows, cols = np.nonzero(np.ones((12, 16), bool))
    hit = point_rays_hit(tgt, np.stack([cols + 0.5, rows + 0.5], 1)).reshape(12, 16)
    assert (mask == hit).mean() > 0.9  # a 2x2 block straddling the silhouette may go either way


def test_horns_objects_share_the_scene_and_scribble_names(tmp_path):
    root = tmp_path / "nvos"
    names = ["DJI_20200223_163016_000", "DJI_20200223_163024_597", "DJI_20200223_163040_000",
             "DJI_20200223_163055_437", "DJI_20200223_163100_000"]
    poses = write_llff_scene(root / "nerf_llff_data" / "horns", names)
    for obj in ("horns_center", "horns_left"):
        write_nvos_labels(root / "labels" / "llff", obj, poses[1], poses[3], scribble_stem="horns")
        llff.import_nvos(root, tmp_path / obj, llff.params_from({"scene": obj}))
        meta = Scene.read(tmp_path / obj).meta
        assert meta["nvos"]["llff_scene"] == "horns" and meta["nvos"]["target_frame"] == names[1]
        assert meta["nvos"]["label_files"]["positive_scribble"].endswith("pos_0_horns.png")


def test_sa3d_layout_and_explicit_dirs(nvos_root, tmp_path):
    root, poses = nvos_root
    # SA3D keeps masks/, reference_image/, scribbles/ next to the scene folders
    sa3d = tmp_path / "sa3d"
    write_llff_scene(sa3d / "fern", FERN_NAMES)
    write_nvos_labels(sa3d, "fern", poses[0], poses[-1])
    llff.import_nvos(sa3d / "fern", tmp_path / "a", llff.params_from({}))  # object from the folder name
    assert Scene.read(tmp_path / "a").meta["nvos"]["object"] == "fern"
    llff.import_nvos(tmp_path, tmp_path / "b",
                     llff.params_from({"scene": "fern", "scene_dir": str(root / "fern"),
                                       "labels_dir": "nvos/labels/llff"}))
    assert Scene.read(tmp_path / "b").meta["llff"]["scene_dir"] == str((root / "fern").resolve())


@pytest.mark.parametrize(
    "breakage, pattern",
    [
        ("no_poses", r"no LLFF scene 'fern' found.*poses_bounds\.npy"),
        ("bad_poses_shape", r"poses_bounds\.npy: expected an \[N, 17\] array"),
        ("count_mismatch", r"images_4: holds 11 images but .*poses_bounds\.npy has 12 poses"),
        ("no_images_folder", r"images_4: image folder is missing"),
        ("no_mask", r"masks/fern: NVOS target mask IMG_4027_mask is missing"),
        ("no_labels", r"NVOS labels for 'fern' are missing"),
        ("no_neg_scribble", r"scribbles/fern: NVOS negative scribble neg_0_fern is missing"),
        ("no_reference", r"reference_image/fern: NVOS reference image IMG_4038 is missing"),
        ("target_not_in_images", r"the NVOS target view IMG_4027 of 'fern' is not among the scene's images"),
        ("scribble_size", r"pos_0_fern\.png: scribble is 16x12 but the reference image IMG_4038\.JPG is 32x24"),
        ("aspect", r"IMG_4027_mask\.png: label is 32x32, a different aspect ratio"),
        ("empty_mask", r"IMG_4027_mask\.png: the target mask is empty"),
    ],
)
def test_wrong_layouts_refused(nvos_root, tmp_path, breakage, pattern):
    root, _ = nvos_root
    labels = root / "labels" / "llff"
    if breakage == "no_poses":
        (root / "fern" / "poses_bounds.npy").unlink()
    elif breakage == "bad_poses_shape":
        np.save(root / "fern" / "poses_bounds.npy", np.zeros((12, 15)))
    elif breakage == "count_mismatch":
        (root / "fern" / "images_4" / "IMG_4031.png").unlink()
    elif breakage == "no_images_folder":
        (root / "fern" / "images_4").rename(root / "fern" / "images_8")
    elif breakage == "no_mask":
        (labels / "masks" / "fern" / "IMG_4027_mask.png").unlink()
    elif breakage == "no_labels":
        (labels / "masks" / "fern").rename(labels / "masks" / "fern_old")
    elif breakage == "no_neg_scribble":
        (labels / "scribbles" / "fern" / "neg_0_fern.png").unlink()
    elif breakage == "no_reference":
        reference = labels / "reference_image" / "fern"
        (reference / "IMG_4038.JPG").rename(reference / "IMG_4000.JPG")
    elif breakage == "target_not_in_images":
        np.save(root / "fern" / "poses_bounds.npy", np.load(root / "fern" / "poses_bounds.npy"))
        (root / "fern" / "images_4" / "IMG_4027.png").rename(root / "fern" / "images_4" / "IMG_4026.png")
    elif breakage == "scribble_size":
        cv2.imwrite(str(labels / "scribbles" / "fern" / "pos_0_fern.png"), np.full((12, 16), 255, np.uint8))
    elif breakage == "aspect":
        cv2.imwrite(str(labels / "masks" / "fern" / "IMG_4027_mask.png"), np.full((32, 32), 255, np.uint8))
    elif breakage == "empty_mask":
        cv2.imwrite(str(labels / "masks" / "fern" / "IMG_4027_mask.png"), np.zeros((H, W), np.uint8))
    with pytest.raises(Trace3DError, match=pattern):
        llff.import_nvos(root, tmp_path / "out", llff.params_from({"scene": "fern"}))


def test_unknown_object_and_bad_params(nvos_root, tmp_path):
    root, _ = nvos_root
    with pytest.raises(Trace3DError, match=r"NVOS object 'nvos' is unknown"):
        llff.import_nvos(root, tmp_path / "out", llff.params_from({}))
    with pytest.raises(Trace3DError, match=r"poses_bounds\.npy is missing"):
        llff.import_llff(root, tmp_path / "out2", llff.params_from({}))
    with pytest.raises(ConfigError, match="unknown parameter"):
        llff.params_from({"factor": 4})
    with pytest.raises(ConfigError, match="positive_fraction"):
        llff.params_from({"positive_fraction": 0.0})
    with pytest.raises(ConfigError, match="images_factor"):
        llff.params_from({"images_factor": 0})


def test_scribble_points_unit():
    scribble = np.zeros((20, 30), bool)
    scribble[8:12, 5:25] = True  # a thick horizontal stroke; its skeleton is one row
    rng = np.random.default_rng(0)
    pts = llff.scribble_points(scribble, 1.0, rng, (1.0, 1.0))
    assert len(pts) >= 15 and np.all((pts[:, 1] > 8) & (pts[:, 1] < 12))
    one = llff.scribble_points(scribble, 1e-9, np.random.default_rng(0), (2.0, 0.5))
    assert one.shape == (1, 2)  # at least one point survives
    assert llff.scribble_points(np.zeros((5, 5), bool), 0.5, rng, (1, 1)).shape == (0, 2)


def test_cli_scene_nvos(nvos_root, tmp_path):
    from trace3d.cli import main

    root, _ = nvos_root
    out = tmp_path / "results" / "fern" / "scene"
    assert main(["scene", "nvos", "--source", str(root), "--params", "{scene: fern}", "--out", str(out)]) == 0
    scene = Scene.read(out)
    assert (out / scene.meta["nvos"]["target_mask"]).is_file()


def test_read_nvos_labels(nvos_root, tmp_path):
    root, poses = nvos_root
    llff.import_nvos(root, tmp_path / "out", llff.params_from({"scene": "fern"}))
    scene = Scene.read(tmp_path / "out")
    labels = llff.read_nvos_labels(scene)
    assert (labels.object, labels.reference_frame, labels.target_frame) == ("fern", "IMG_4038", "IMG_4027")
    np.testing.assert_array_equal(labels.target_mask, render(poses[0])[1])
    assert labels.positive_points.shape[1] == 2
    assert point_rays_hit(scene.camera("IMG_4038"), labels.positive_points).all()
    llff.import_llff(root / "fern", tmp_path / "plain", llff.params_from({}))
    with pytest.raises(Trace3DError, match=r"meta\.json: has no 'nvos' entry"):
        llff.read_nvos_labels(Scene.read(tmp_path / "plain"))
