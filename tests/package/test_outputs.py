"""Nothing a user owns is lost (issue 49): a step writes only where it may, its outputs carry a manifest
that the next step checks, and an OS failure is one sentence with nothing half-written.

The inputs are one tiny synthetic scene and its simulated masks, made once; each case works on copies.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from trace3d.cli import main
from trace3d.io import MANIFEST, read_manifest, verify_tree

TINY_SCENE = {"width": 32, "height": 24, "num_views": 4, "test_every": 2, "num_objects": 6, "supersample": 1}


@pytest.fixture(scope="module")
def made(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("outputs")
    scene, masks = root / "scene", root / "masks"
    assert main(["scene", "synthetic", "--out", str(scene), "--params", json.dumps(TINY_SCENE)]) == 0
    assert main(["masks", "--scene", str(scene), "--out", str(masks)]) == 0
    return {"root": root, "scene": scene, "masks": masks}


def snapshot(path: Path) -> dict[str, bytes] | bytes | None:
    """Every file's bytes under ``path`` (a file: its bytes; missing: None)."""
    if path.is_file():
        return path.read_bytes()
    if not path.exists():
        return None
    return {p.relative_to(path).as_posix(): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


def one_sentence(capsys, code: int) -> str:
    err = capsys.readouterr().err
    assert code == 2, err
    assert "Traceback" not in err, err
    lines = [line for line in err.splitlines() if line.startswith("trace3d ")]
    assert len(lines) == 1, err
    sentence = lines[0].split(": error: ", 1)[1]
    assert sentence.endswith("."), sentence
    return sentence


def no_temporaries(path: Path) -> None:
    assert not list(path.parent.glob(f".{path.name}.tmp-*")), list(path.parent.iterdir())


def copy(made: dict, name: str, tmp_path: Path) -> Path:
    target = tmp_path / name
    shutil.copytree(made[name], target)
    return target


# ----------------------------------------------------------------------------------------------
# a step writes only where it may
# ----------------------------------------------------------------------------------------------


def _the_scene_itself(made, tmp_path):
    scene = copy(made, "scene", tmp_path)
    return ["masks", "--scene", scene, "--out", scene], scene, [str(scene), "input"]


def _a_folder_holding_the_input(made, tmp_path):
    scene = copy(made, "scene", tmp_path / "mine")
    return ["masks", "--scene", scene, "--out", tmp_path / "mine"], tmp_path / "mine", [str(tmp_path / "mine"), "input"]


def _a_users_folder(made, tmp_path):
    folder = tmp_path / "thesis"
    folder.mkdir()
    (folder / "thesis.txt").write_text("three years of work\n")
    return ["masks", "--scene", made["scene"], "--out", folder], folder, [str(folder), "did not write"]


def _a_users_file(made, tmp_path):
    path = tmp_path / "afile"
    path.write_text("mine\n")
    return ["masks", "--scene", made["scene"], "--out", path], path, [str(path), "not a folder"]


def _another_steps_output(made, tmp_path):
    other = copy(made, "scene", tmp_path / "other")
    return ["masks", "--scene", made["scene"], "--out", other], other, [str(other), "trace3d scene"]


def _a_link_to_a_users_folder(made, tmp_path):
    folder = tmp_path / "real"
    folder.mkdir()
    (folder / "notes.txt").write_text("mine\n")
    link = tmp_path / "link"
    link.symlink_to(folder)
    return ["masks", "--scene", made["scene"], "--out", link], folder, [str(link)]


def _a_file_step_onto_its_input(made, tmp_path):
    scene = copy(made, "scene", tmp_path)
    return ["summary", scene, "--out", scene / "cameras.json"], scene, [str(scene / "cameras.json"), "input"]


DESTINATIONS = {"the scene itself (--out = --scene)": _the_scene_itself,
                "a folder holding the input": _a_folder_holding_the_input,
                "a user's folder with a file in it": _a_users_folder,
                "a user's file": _a_users_file,
                "another step's output": _another_steps_output,
                "a link to a user's folder": _a_link_to_a_users_folder,
                "a table written onto the file it reads": _a_file_step_onto_its_input}


@pytest.mark.parametrize("name", sorted(DESTINATIONS))
def test_out_that_is_not_the_steps_own_is_refused(made, tmp_path, capsys, name):
    argv, kept, phrases = DESTINATIONS[name](made, tmp_path)
    before = snapshot(kept)
    capsys.readouterr()
    sentence = one_sentence(capsys, main([str(a) for a in argv]))
    for phrase in phrases:
        assert phrase in sentence, (phrase, sentence)
    assert snapshot(kept) == before, f"{kept} was changed"
    no_temporaries(Path(argv[argv.index("--out") + 1]))


def test_the_steps_earlier_output_and_an_empty_folder_are_replaced(made, tmp_path):
    out = tmp_path / "masks"
    out.mkdir()  # an empty folder holds nothing of anyone's
    assert main(["masks", "--scene", str(made["scene"]), "--out", str(out)]) == 0
    first = snapshot(out)
    (out / "stray.txt").write_text("left in the step's own folder")
    assert main(["masks", "--scene", str(made["scene"]), "--out", str(out)]) == 0  # a rerun replaces it
    assert snapshot(out) == first
    no_temporaries(out)


def test_a_table_step_refused_leaves_no_out_folder(tmp_path, capsys):
    out = tmp_path / "tables"
    capsys.readouterr()
    sentence = one_sentence(capsys, main(["tables", "--results", str(tmp_path), "--out", str(out)]))
    assert "metrics.json" in sentence
    assert not out.exists()


def test_a_file_output_onto_a_folder_leaves_no_temporary(tmp_path):
    from trace3d.errors import Trace3DError
    from trace3d.io import atomic_file

    folder = tmp_path / "table.md"
    folder.mkdir()
    with pytest.raises(Trace3DError, match="is a folder"):
        with atomic_file(folder) as tmp:
            tmp.write_text("x")
    assert folder.is_dir() and not any(folder.iterdir())
    no_temporaries(folder)


# ----------------------------------------------------------------------------------------------
# manifests: written last, checked by the next step, `trace3d verify`
# ----------------------------------------------------------------------------------------------


def test_every_step_output_has_a_manifest_of_its_files(made):
    for name, step in (("scene", "scene"), ("masks", "masks")):
        manifest = read_manifest(made[name])
        assert manifest is not None and manifest["step"] == step
        files = {p.relative_to(made[name]).as_posix(): p.stat().st_size
                 for p in made[name].rglob("*") if p.is_file() and p.name != MANIFEST}
        assert {k: v[0] for k, v in manifest["files"].items()} == files
    folders, problems = verify_tree(made["root"])
    assert set(folders) == {made["scene"], made["masks"]} and problems == []


@pytest.mark.parametrize("damage", ["truncated", "same size, other bytes", "deleted"])
def test_a_damaged_input_is_named_with_the_rule_to_rerun(made, tmp_path, capsys, damage):
    masks = copy(made, "masks", tmp_path)
    victim = sorted(masks.glob("*.npz"))[0]
    data = victim.read_bytes()
    if damage == "truncated":
        victim.write_bytes(data[: len(data) // 2])
    elif damage == "deleted":
        victim.unlink()
    else:
        victim.write_bytes(data[:-1] + bytes([data[-1] ^ 1]))
    out = tmp_path / "patches"
    capsys.readouterr()
    sentence = one_sentence(capsys, main(["patches", "--scene", str(made["scene"]), "--masks", str(masks),
                                          "--out", str(out)]))
    assert str(victim) in sentence and "--forcerun=masks" in sentence, sentence
    assert not out.exists()
    # `trace3d verify` finds it in the tree, and passes the intact copy
    assert main(["verify", str(tmp_path)]) == 2
    report = capsys.readouterr()
    assert str(victim) in report.out and "differ" in report.err
    assert main(["verify", str(made["root"])]) == 0
    # a change the user means: remove the manifest, and the folder is read as the user's own
    (masks / MANIFEST).unlink()
    if damage != "truncated":
        assert main(["patches", "--scene", str(made["scene"]), "--masks", str(masks), "--out", str(out)]) in (0, 2)


def test_a_damaged_file_inside_an_input_folder_is_caught(made, tmp_path, capsys):
    """An input that is a subfolder of a step output (merge/instances, scene/images) is checked too."""
    scene = copy(made, "scene", tmp_path)
    image = sorted((scene / "images").glob("*.png"))[0]
    image.write_bytes(image.read_bytes()[:100])
    capsys.readouterr()
    sentence = one_sentence(capsys, main(["patches", "--scene", str(scene), "--masks", str(made["masks"]),
                                          "--out", str(tmp_path / "patches")]))
    assert str(image) in sentence and "--forcerun=scene" in sentence


# ----------------------------------------------------------------------------------------------
# OS errors: one sentence with the path, exit 2, nothing half-written
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EROFS, errno.EACCES, errno.ENOENT])
def test_an_os_error_while_writing_is_one_sentence(made, tmp_path, capsys, monkeypatch, code):
    out = tmp_path / "masks"
    assert main(["masks", "--scene", str(made["scene"]), "--out", str(out)]) == 0
    before = snapshot(out)
    real = np.savez_compressed

    def failing(file, *args, **kwargs):
        raise OSError(code, os.strerror(code), getattr(file, "name", str(file)))

    monkeypatch.setattr(np, "savez_compressed", failing)
    capsys.readouterr()
    sentence = one_sentence(capsys, main(["masks", "--scene", str(made["scene"]), "--out", str(out)]))
    monkeypatch.setattr(np, "savez_compressed", real)
    assert errno.errorcode[code] in sentence and str(out) in sentence and ".tmp-" not in sentence, sentence
    assert snapshot(out) == before  # the earlier output is whole
    no_temporaries(out)


def test_an_os_error_on_the_final_rename_puts_the_earlier_output_back(made, tmp_path, capsys, monkeypatch):
    out = tmp_path / "masks"
    assert main(["masks", "--scene", str(made["scene"]), "--out", str(out)]) == 0
    before = snapshot(out)
    real = os.replace
    calls = []

    def replace(src, dst):
        calls.append((src, dst))
        if len(calls) == 2:  # the new output onto the final name
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(dst))
        return real(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    capsys.readouterr()
    sentence = one_sentence(capsys, main(["masks", "--scene", str(made["scene"]), "--out", str(out)]))
    monkeypatch.setattr(os, "replace", real)
    assert "ENOSPC" in sentence and str(out) in sentence
    assert snapshot(out) == before
    no_temporaries(out)


@pytest.mark.parametrize("code", [errno.EROFS, errno.EACCES, errno.ENOSPC])
def test_a_cache_folder_that_cannot_be_written_is_one_sentence(made, tmp_path, capsys, monkeypatch, code):
    """A read-only (full, forbidden) NUMBA_CACHE_DIR is named before anything runs, instead of being announced
    as the cache while numba writes elsewhere (simulated: the tests run as root, whom no mode stops)."""
    import tempfile

    cache = tmp_path / "cache"
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(cache))
    monkeypatch.setenv("TRACE3D_NUMBA_CACHE_KEYED", str(cache))
    real = tempfile.NamedTemporaryFile

    def refused(*args, **kwargs):
        if kwargs.get("dir") == str(cache):
            raise OSError(code, os.strerror(code), str(cache))
        return real(*args, **kwargs)

    monkeypatch.setattr(tempfile, "NamedTemporaryFile", refused)
    out = tmp_path / "masks"
    capsys.readouterr()
    sentence = one_sentence(capsys, main(["masks", "--scene", str(made["scene"]), "--out", str(out)]))
    assert "NUMBA_CACHE_DIR" in sentence and str(cache) in sentence and errno.errorcode[code] in sentence, sentence
    assert not out.exists()


def test_duplicate_params_keys_and_too_many_threads_are_one_sentence(made, tmp_path, capsys):
    out = tmp_path / "masks"
    capsys.readouterr()
    sentence = one_sentence(capsys, main(["masks", "--scene", str(made["scene"]), "--out", str(out),
                                          "--params", "{seed: 1, seed: 2}"]))
    assert "'seed' appears twice" in sentence
    sentence = one_sentence(capsys, main(["--threads", "100000", "masks", "--scene", str(made["scene"]),
                                          "--out", str(out)]))
    assert "--threads 100000" in sentence
    assert not out.exists()


def test_a_lift_on_one_label_maps_warns(made, tmp_path, caplog):
    """Maps that hold one instance each give the contrastive loss nothing to separate: the lift says so in its
    log and in lift.json instead of training quietly to a loss of 0."""
    import cv2
    import torch

    from trace3d.gaussians import GaussianModel
    from trace3d.scene import Scene

    generator = torch.Generator().manual_seed(0)
    n = 32
    model = GaussianModel(means=torch.randn(n, 3, generator=generator),
                          quats=torch.nn.functional.normalize(torch.randn(n, 4, generator=generator), dim=1),
                          log_scales=torch.full((n, 2), -2.0), opacity_logits=torch.zeros(n),
                          sh_dc=torch.rand(n, 1, 3, generator=generator), sh_rest=torch.zeros(n, 0, 3))
    (tmp_path / "gaussians").mkdir()
    model.write_ply(tmp_path / "gaussians" / "point_cloud.ply")
    labels = tmp_path / "labels"
    labels.mkdir()
    for cam in Scene.read(made["scene"]).cameras:
        cv2.imwrite(str(labels / f"{cam.name}.png"), np.full((cam.height, cam.width), 3, np.uint16))
    out = tmp_path / "lift"
    assert main(["lift", "--scene", str(made["scene"]), "--gaussians", str(tmp_path / "gaussians"), "--labels",
                 str(labels), "--out", str(out), "--params", '{"iterations": 2, "pixels": 16, "pool_pixels": 64}']) == 0
    assert "holds two instances" in caplog.text
    assert "nothing to separate" in json.loads((out / "lift.json").read_text())["warning"]
