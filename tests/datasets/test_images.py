"""`trace3d scene images`: a folder of photos -> a scene with unknown poses -> COLMAP -> a 2DGS fit.

The capture is rendered from a synthetic room (so the true cameras are known) and written as JPEGs
with EXIF (the 35 mm-equivalent focal length; one photo stored sideways with an orientation tag).
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from trace3d.cli import main as cli_main
from trace3d.datasets import images as images_mod
from trace3d.datasets.images import ImagesParams, Photo, focal_for, import_images, params_from, shrink_to_max_side
from trace3d.datasets.synthetic import SyntheticParams, generate_scene
from trace3d.errors import ConfigError, SceneFormatError, Trace3DError
from trace3d.pointcloud import umeyama
from trace3d.scene import Scene, read_cameras
from trace3d.poses.step import run_poses

NUM_VIEWS = 24
RENDER_W, RENDER_H = 280, 210
MAX_SIDE = 240  # -> 240 x 180
ROTATED = 5  # this photo is stored rotated 90 degrees counter-clockwise, with EXIF orientation 6


def exif_bytes(focal_35mm: int | None, orientation: int | None) -> bytes:
    exif = Image.Exif()
    if orientation is not None:
        exif[images_mod.TAG_ORIENTATION] = orientation
    if focal_35mm is not None:
        exif.get_ifd(images_mod.EXIF_IFD)[images_mod.TAG_FOCAL_35MM] = focal_35mm
    return exif.tobytes()


def save_jpeg(path: Path, rgb: np.ndarray, focal_35mm: int | None = None, orientation: int | None = None) -> None:
    Image.fromarray(rgb).save(path, quality=95, exif=exif_bytes(focal_35mm, orientation))


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """(truth scene, photo folder, the EXIF 35 mm focal length written)."""
    root = tmp_path_factory.mktemp("capture")
    params = SyntheticParams(seed=5, width=RENDER_W, height=RENDER_H, num_views=NUM_VIEWS, test_every=4,
                             num_objects=16, supersample=1)
    generate_scene(root / "truth", params)
    truth = Scene.read(root / "truth")
    fx = truth.cameras[0].K[0, 0]
    focal_35 = round(fx / math.hypot(RENDER_W, RENDER_H) * images_mod.FULL_FRAME_DIAGONAL_MM)
    photos = root / "photos"
    photos.mkdir()
    for k, cam in enumerate(truth.cameras):
        rgb = truth.image(cam.name)
        if k == ROTATED:  # stored sideways; orientation 6 = "rotate 90 degrees clockwise to display"
            save_jpeg(photos / f"IMG_{k:04d}.jpg", np.ascontiguousarray(np.rot90(rgb, 1)), focal_35, 6)
        else:
            save_jpeg(photos / f"IMG_{k:04d}.jpg", rgb, focal_35)
    return truth, photos, focal_35


@pytest.fixture(scope="module")
def imported(capture, tmp_path_factory):
    _, photos, _ = capture
    out = tmp_path_factory.mktemp("imported") / "scene"
    assert cli_main(["scene", "images", "--source", str(photos), "--out", str(out),
                     "--params", json.dumps({"max_side": MAX_SIDE, "test_every": 4})]) == 0
    return Scene.read(out)


def test_import_writes_an_upright_scene_with_unknown_poses(capture, imported):
    truth, _, focal_35 = capture
    scene = imported
    assert [c.name for c in scene.cameras] == [f"IMG_{k:04d}" for k in range(NUM_VIEWS)]
    assert [c.split for c in scene.cameras] == ["test" if k % 4 == 0 else "train" for k in range(NUM_VIEWS)]
    assert {(c.width, c.height) for c in scene.cameras} == {(240, 180)}
    assert scene.meta["poses"] == "unknown" and scene.meta["intrinsics"] == "exif_35mm"
    assert scene.meta["frames"][f"IMG_{ROTATED:04d}"]["exif_orientation"] == 6
    assert all(np.allclose(c.world_to_camera, np.eye(4)) for c in scene.cameras)
    # focal from the (rounded) 35 mm equivalent, scaled with the image: within 2 % of the truth
    true_f = truth.cameras[0].K[0, 0] * 240 / RENDER_W
    assert abs(scene.cameras[0].K[0, 0] - true_f) / true_f < 0.02
    assert np.allclose(scene.cameras[0].K[:2, 2], [120.0, 90.0])
    # the sideways photo is upright after import: it matches the truth shrunk the same way
    for k in (ROTATED, ROTATED + 1):
        name = f"IMG_{k:04d}"
        expected, _ = shrink_to_max_side(truth.image(truth.cameras[k].name), MAX_SIDE)
        diff = np.abs(scene.image(name).astype(float) - expected.astype(float)).mean()
        assert diff < 4.0, (name, diff)
    # ... and an importer that ignored the tag would not (the transposed content differs)
    wrong = np.asarray(Image.open(capture[1] / f"IMG_{ROTATED:04d}.jpg").convert("RGB"))
    assert wrong.shape[:2] == (RENDER_W, RENDER_H)


def test_import_is_deterministic(capture, imported, tmp_path):
    _, photos, _ = capture
    import_images(photos, tmp_path / "again", ImagesParams(max_side=MAX_SIDE, test_every=4))
    for rel in ["cameras.json", *(f"images/IMG_{k:04d}.png" for k in range(NUM_VIEWS))]:
        assert (tmp_path / "again" / rel).read_bytes() == (imported.root / rel).read_bytes(), rel


def test_placeholder_poses_are_refused(imported, tmp_path, capsys):
    with pytest.raises(ConfigError, match="poses mode 'dataset' needs the scene's own poses"):
        run_poses(imported, tmp_path / "p", {"mode": "dataset"})
    assert cli_main(["gaussians", "--scene", str(imported.root), "--out", str(tmp_path / "g")]) == 2
    err = capsys.readouterr().err
    assert "poses are unknown" in err and "--poses" in err and err.count("\n") == 1


def test_colmap_registers_and_the_fit_runs(capture, imported, tmp_path):
    truth, _, _ = capture
    poses = tmp_path / "poses"
    assert cli_main(["--threads", "2", "poses", "--scene", str(imported.root), "--out", str(poses),
                     "--params", json.dumps({"seed": 0, "num_threads": -1})]) == 0
    sfm = json.loads((poses / "sfm.json").read_text())
    assert sfm["images_registered"] == NUM_VIEWS and sfm["frame"] == "colmap"
    assert sfm["params"]["num_threads"] == 2  # -1 (all cores) became the --threads budget
    assert sfm["intrinsics"]["initial"] == "exif_35mm"
    cams = {c.name: c for c in read_cameras(poses / "cameras.json")}
    # the truth up to a similarity: camera centres after Umeyama, orientations after its rotation
    names = [f"IMG_{k:04d}" for k in range(NUM_VIEWS)]
    est = np.stack([cams[n].center for n in names])
    ref = np.stack([truth.cameras[k].center for k in range(NUM_VIEWS)])
    sim = umeyama(est, ref)
    aligned = sim.scale * est @ sim.rotation.T + sim.translation
    diameter = max(np.linalg.norm(a - b) for a in ref for b in ref)
    assert np.linalg.norm(aligned - ref, axis=1).max() < 0.03 * diameter
    for k, n in enumerate(names):
        r_est = cams[n].rotation @ sim.rotation.T  # world (truth) -> camera
        r_ref = truth.cameras[k].rotation
        angle = np.degrees(np.arccos(np.clip((np.trace(r_est.T @ r_ref) - 1) / 2, -1, 1)))
        assert angle < 2.0, (n, angle)
    true_f = truth.cameras[0].K[0, 0] * 240 / RENDER_W
    assert abs(cams[names[1]].K[0, 0] - true_f) / true_f < 0.03

    out = tmp_path / "gaussians"
    fit = {"schedule_scale": 1.0, "iterations": 40, "densify_from": 20, "densify_until": 35,
           "densify_interval": 20, "normal_from": 100, "sh_degree": 0, "device": "cpu", "log_interval": 10}
    assert cli_main(["--threads", "2", "gaussians", "--scene", str(imported.root), "--poses", str(poses),
                     "--out", str(out), "--params", json.dumps(fit)]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["num_train_views"] == 18 and np.isfinite(metrics["test_psnr"])
    rows = list(csv.DictReader((out / "train.csv").open()))
    first, last = float(rows[0]["psnr"]), float(rows[-1]["psnr"])
    assert last > first + 1.5, (first, last)  # it fits the registered views (7.3 -> 9.8 dB measured)


def test_focal_sources_in_order():
    photo = Photo(np.zeros((10, 20, 3), np.uint8), 1, focal_35mm=28.0, focal_plane_px=30.0)
    assert focal_for(photo, 100, 50, 0.5, ImagesParams(focal_px=77.0)) == (77.0, "params")
    f, src = focal_for(photo, 100, 50, 0.5, ImagesParams())
    assert src == "exif_35mm" and f == pytest.approx(28.0 / 43.2666 * math.hypot(100, 50), rel=1e-4)
    no35 = Photo(photo.rgb, 1, None, 30.0)
    assert focal_for(no35, 100, 50, 0.5, ImagesParams()) == (15.0, "exif_focal_plane")
    assert focal_for(no35, 100, 50, 0.5, ImagesParams(use_exif_focal=False)) == (120.0, "guess")


def test_pngs_without_exif_get_the_guess(tmp_path):
    folder = tmp_path / "pngs"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for k in range(3):
        Image.fromarray(rng.integers(0, 255, (30, 40, 3), dtype=np.uint8)).save(folder / f"v{k}.png")
    import_images(folder, tmp_path / "s", params_from({"test_every": 0}))
    scene = Scene.read(tmp_path / "s")
    assert scene.meta["intrinsics"] == "guess" and all(c.split == "train" for c in scene.cameras)
    assert scene.cameras[0].K[0, 0] == pytest.approx(1.2 * 40)


def test_bad_inputs_get_one_sentence(tmp_path, capsys):
    folder = tmp_path / "photos"
    folder.mkdir()
    assert cli_main(["scene", "images", "--source", str(folder), "--out", str(tmp_path / "s")]) == 2
    assert "contains no .png/.jpg images" in capsys.readouterr().err
    rgb = np.full((20, 30, 3), 128, np.uint8)
    for k in range(3):
        save_jpeg(folder / f"a{k}.jpg", rgb)
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="JPEG")
    (folder / "a1.jpg").write_bytes(buf.getvalue()[:40])  # truncated
    assert cli_main(["scene", "images", "--source", str(folder), "--out", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err
    assert "a1.jpg: photo is corrupt" in err and not (tmp_path / "s").exists()
    (folder / "a1.jpg").unlink()
    with pytest.raises(Trace3DError, match="fewer than min_images 3"):
        import_images(folder, tmp_path / "s2", ImagesParams())
    save_jpeg(folder / "a0.jpeg", rgb)
    with pytest.raises(Trace3DError, match="not unique"):
        import_images(folder, tmp_path / "s3", ImagesParams())
    with pytest.raises(ConfigError, match="max_sid"):
        params_from({"max_sid": 100})


def test_trace_without_poses_is_refused(imported):
    from trace3d.tracing.git import load_fitted

    with pytest.raises(SceneFormatError, match="poses are unknown"):
        load_fitted(imported, None, imported.root)


def test_readme_config_example_dry_runs(tmp_path):
    """The README's `Your own photos` config, with data_root pointing here: schema-valid, and the
    scene rule imports the photo folder with the importer parameters."""
    import os
    import re
    import shutil
    import subprocess
    import sys

    import yaml

    repo = Path(__file__).resolve().parents[2]
    snakemake = shutil.which("snakemake", path=str(Path(sys.executable).parent)) or shutil.which("snakemake")
    if snakemake is None:
        pytest.skip("snakemake is not installed")
    section = (repo / "docs" / "capture.md").read_text().split("## Your own photos", 1)[1]
    config = yaml.safe_load(re.search(r"```yaml\n(.*?)```", section, flags=re.S).group(1))
    assert config["scenes"]["plant"]["kind"] == "images"
    config["data_root"] = str(tmp_path / "captures")
    (tmp_path / "captures" / config["scenes"]["plant"]["source"]).mkdir(parents=True)  # the photos' folder exists
    config["results"] = str(tmp_path / "results")
    (tmp_path / "my.yaml").write_text(yaml.safe_dump(config))
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    out = subprocess.run([snakemake, "-s", str(repo / "Snakefile"), "-n", "-p", "--cores", "2",
                          "--configfile=my.yaml", f"{tmp_path}/results/plant/gaussians"],
                         cwd=tmp_path, capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
    assert f"scene images --source {tmp_path}/captures/plant" in out.stdout
    assert '"max_side": 640' in out.stdout and "trace3d --threads 1 poses" in out.stdout


def test_tracing_table_plots_without_ground_truth(tmp_path):
    """A user's scene has no ground truth: the tracing table still writes its plot (the rule's output)."""
    from trace3d.report.tracing import write_tracing_table

    merge = tmp_path / "plant" / "merge-paper"
    merge.mkdir(parents=True)
    (merge / "merge.json").write_text(json.dumps({"params": {"preset": "paper"}, "mean_patches": 6.7,
                                                  "mean_instances": 5.1, "merged_pairs": 12, "seconds": 1.0}))
    table = write_tracing_table([merge], None, tmp_path / "tracing.md", tmp_path / "plots" / "merge.png")
    assert "ARI before" not in table and (tmp_path / "plots" / "merge.png").stat().st_size > 1000
    assert "| plant " in (tmp_path / "tracing.md").read_text()
