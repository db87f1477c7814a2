"""The fault catalogue: bad input at every step and in the config, each answered by one sentence.

Every CLI case asserts exit status 2, one line on stderr (``trace3d <step>: error: <sentence>``) that
names the file or key, no traceback, and no complete-looking output (nor a temporary sibling) left
behind. The config cases go through Snakemake's own validation of the config (the dry run's first
act) or a real dry run. The inputs are one tiny synthetic scene built once, random Gaussians standing
in for a fit (every fault here is refused before a kernel runs) and copies of them with one thing
broken.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
import yaml

from trace3d.cli import main
from trace3d.io import MANIFEST

REPO = Path(__file__).resolve().parents[2]
TINY_SCENE = {"width": 32, "height": 24, "num_views": 4, "test_every": 2, "num_objects": 6, "supersample": 1}


def write_png16(path: Path, array: np.ndarray) -> None:
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.asarray(array, np.uint16))


@dataclass
class World:
    root: Path
    scene: Path
    masks: Path
    patches: Path
    gaussians: Path
    trace: Path
    lift: Path
    train: list[str]
    test: list[str]
    size: tuple[int, int]
    counter: list[int] = field(default_factory=lambda: [0])

    def copy(self, folder: Path) -> Path:
        """A fresh copy of an input folder, to break one thing in: a user's own folder, without the step's
        manifest (a step output whose file changed is refused for that alone: tests/package/test_outputs.py)."""
        self.counter[0] += 1
        target = self.root / "copies" / f"{folder.name}-{self.counter[0]}"
        shutil.copytree(folder, target)
        (target / MANIFEST).unlink(missing_ok=True)
        return target

    def out(self, name: str = "out") -> Path:
        self.counter[0] += 1
        return self.root / "outs" / f"{self.counter[0]}" / name


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> World:
    import torch

    from trace3d.gaussians import GaussianModel
    from trace3d.scene import Scene
    from trace3d.tracing.git import GITStats

    root = tmp_path_factory.mktemp("bad_inputs")
    scene, masks, patches = root / "scene", root / "masks", root / "patches"
    assert main(["scene", "synthetic", "--out", str(scene), "--params", json.dumps(TINY_SCENE)]) == 0
    assert main(["masks", "--scene", str(scene), "--out", str(masks)]) == 0
    assert main(["patches", "--scene", str(scene), "--masks", str(masks), "--out", str(patches)]) == 0
    cams = Scene.read(scene).cameras
    train = [c.name for c in cams if c.split == "train"]
    test = [c.name for c in cams if c.split == "test"]
    # random Gaussians standing in for a fit: the faults below are refused before any kernel runs
    generator = torch.Generator().manual_seed(0)
    n = 64
    model = GaussianModel(
        means=torch.randn(n, 3, generator=generator), quats=torch.nn.functional.normalize(torch.randn(n, 4, generator=generator), dim=1),
        log_scales=torch.full((n, 2), -3.0), opacity_logits=torch.zeros(n), sh_dc=torch.rand(n, 1, 3, generator=generator),
        sh_rest=torch.zeros(n, 0, 3))
    gaussians = root / "gaussians"
    gaussians.mkdir()
    model.write_ply(gaussians / "point_cloud.ply")
    trace = root / "trace"
    trace.mkdir()
    rng = np.random.default_rng(0)
    num_labels = np.array([int(np.asarray(__import__("cv2").imread(str(patches / f"{f}.png"), -1)).max()) + 1
                           for f in train], np.int64)
    labels = np.stack([rng.integers(0, k, n) for k in num_labels], axis=1).astype(np.int32)
    GITStats(label=labels, prob=np.ones(labels.shape, np.float32), visibility=np.ones(labels.shape, np.float32),
             frames=train, num_labels=num_labels).save(trace / "git.npz")
    lift = root / "lift"
    lift.mkdir()
    (lift / "lift.json").write_text(json.dumps({"method": "contrastive", "params": {}}))
    return World(root, scene, masks, patches, gaussians, trace, lift, train, test,
                 (TINY_SCENE["width"], TINY_SCENE["height"]))


# ----------------------------------------------------------------------------------------------
# the catalogue: (id, builder) -> (argv, phrases the sentence must contain, output that must not exist)
# ----------------------------------------------------------------------------------------------

Case = Callable[[World], tuple[list, list[str], Path]]
CASES: dict[str, Case] = {}


def case(name: str):
    def register(fn: Case) -> Case:
        CASES[name] = fn
        return fn

    return register


def wrong_size_map(w: World, folder: Path, frame: str, scale: float) -> Path:
    copy = w.copy(folder)
    width, height = w.size
    write_png16(copy / f"{frame}.png", np.ones((int(height * scale), int(width * scale)), np.uint16))
    return copy


# --- scene ---------------------------------------------------------------------------------------
@case("scene: unknown synthetic parameter")
def _(w):
    out = w.out()
    return ["scene", "synthetic", "--out", out, "--params", '{"widht": 10}'], ["widht", "width"], out


@case("scene: parameter of the wrong type")
def _(w):
    out = w.out()
    return ["scene", "synthetic", "--out", out, "--params", '{"num_views": "many"}'], ["num_views", "integer"], out


@case("scene: importer without --source")
def _(w):
    out = w.out()
    return ["scene", "replica", "--out", out], ["--source"], out


@case("scene: canonical source that does not exist")
def _(w):
    out, missing = w.out(), w.root / "no-such-scene"
    return ["scene", "canonical", "--source", missing, "--out", out], [str(missing)], out


@case("--params file that does not exist")
def _(w):
    out, missing = w.out(), w.root / "missing.yaml"
    return ["scene", "synthetic", "--out", out, "--params", f"@{missing}"], [str(missing)], out


@case("--params that is not YAML")
def _(w):
    out = w.out()
    return ["scene", "synthetic", "--out", out, "--params", "{seed: [1,"], ["--params", "YAML"], out


# --- a broken scene folder -----------------------------------------------------------------------
@case("masks: scene folder missing")
def _(w):
    out, missing = w.out(), w.root / "nowhere"
    return ["masks", "--scene", missing, "--out", out], [str(missing)], out


@case("masks: cameras.json not JSON")
def _(w):
    scene, out = w.copy(w.scene), w.out()
    (scene / "cameras.json").write_text("{not json")
    return ["masks", "--scene", scene, "--out", out], [str(scene / "cameras.json")], out


@case("masks: an image missing")
def _(w):
    scene, out = w.copy(w.scene), w.out()
    (scene / "images" / f"{w.train[0]}.png").unlink()
    return ["masks", "--scene", scene, "--out", out], [f"{w.train[0]}.png"], out


@case("masks: a ground-truth instance map of the wrong size")
def _(w):
    scene, out = w.copy(w.scene), w.out()
    write_png16(scene / "instances" / f"{w.train[0]}.png", np.ones((10, 10), np.uint16))
    return ["masks", "--scene", scene, "--out", out], [str(scene / "instances" / f"{w.train[0]}.png"), "10x10", "32x24"], out


@case("masks: an 8-bit instance map")
def _(w):
    import cv2

    scene, out = w.copy(w.scene), w.out()
    cv2.imwrite(str(scene / "instances" / f"{w.train[0]}.png"), np.ones((24, 32), np.uint8))
    return ["masks", "--scene", scene, "--out", out], [f"{w.train[0]}.png", "16-bit"], out


@case("masks: unknown parameter of the simulated source")
def _(w):
    out = w.out()
    return ["masks", "--scene", w.scene, "--out", out, "--params", '{"inconsistncy": 0.2}'], ["inconsistncy", "inconsistency"], out


@case("masks: a negative seed")
def _(w):
    out = w.out()
    return ["masks", "--scene", w.scene, "--out", out, "--params", '{"seed": -3}'], ["seed", ">= 0", "-3"], out


@case("gaussians: a negative seed")
def _(w):
    out = w.out()
    return ["gaussians", "--scene", w.scene, "--out", out, "--params", '{"seed": -3}'], ["seed", ">= 0", "-3"], out


@case("tables: no evaluation under --results (no empty --out left)")
def _(w):
    out = w.out("tables")
    return ["tables", "--results", w.root, "--out", out], ["metrics.json"], out


@case("masks --source files: a mask stack of the wrong size")
def _(w):
    scene, out = w.copy(w.scene), w.out()
    (scene / "masks").mkdir(exist_ok=True)
    for frame in w.train + w.test:
        np.savez(scene / "masks" / f"{frame}.npz", masks=np.ones((2, 24, 32), bool))
    np.savez(scene / "masks" / f"{w.train[0]}.npz", masks=np.ones((2, 12, 16), bool))
    return ["masks", "--scene", scene, "--out", out, "--source", "files"], [f"{w.train[0]}.npz", "16x12"], out


@case("masks --source files: no view has a mask")
def _(w):
    scene, out = w.copy(w.scene), w.out()
    (scene / "masks").mkdir(exist_ok=True)
    for frame in w.train + w.test:
        np.savez(scene / "masks" / f"{frame}.npz", masks=np.zeros((0, 24, 32), bool))
    return ["masks", "--scene", scene, "--out", out, "--source", "files"], [str(scene), "no mask"], out


@case("masks --source files: a view's mask file missing")
def _(w):
    scene, out = w.copy(w.scene), w.out()
    (scene / "masks").mkdir(exist_ok=True)
    for frame in w.train:
        np.savez(scene / "masks" / f"{frame}.npz", masks=np.ones((1, 24, 32), bool))
    return ["masks", "--scene", scene, "--out", out, "--source", "files"], [w.test[0]], out


# --- patches -------------------------------------------------------------------------------------
@case("patches: masks folder missing a view")
def _(w):
    masks, out = w.copy(w.masks), w.out()
    (masks / f"{w.train[0]}.npz").unlink()
    return ["patches", "--scene", w.scene, "--masks", masks, "--out", out], [str(masks / f"{w.train[0]}.npz")], out


@case("patches: a corrupt mask file")
def _(w):
    masks, out = w.copy(w.masks), w.out()
    (masks / f"{w.train[0]}.npz").write_bytes(b"PK\x03\x04 truncated")
    return ["patches", "--scene", w.scene, "--masks", masks, "--out", out], [str(masks / f"{w.train[0]}.npz")], out


@case("patches: unknown parameter")
def _(w):
    out = w.out()
    return ["patches", "--scene", w.scene, "--masks", w.masks, "--out", out, "--params", '{"min_are": 3}'], ["min_are"], out


# --- gaussians -----------------------------------------------------------------------------------
@case("gaussians: misspelled parameter")
def _(w):
    out = w.out()
    return ["gaussians", "--scene", w.scene, "--out", out, "--params", '{"iteratons": 10}'], ["iteratons", "iterations"], out


@case("gaussians: poses folder missing")
def _(w):
    out, missing = w.out(), w.root / "no-poses"
    return ["gaussians", "--scene", w.scene, "--poses", missing, "--out", out], [str(missing)], out


# --- trace ---------------------------------------------------------------------------------------
@case("trace: point_cloud.ply missing")
def _(w):
    out, missing = w.out(), w.root / "empty-fit"
    missing.mkdir(exist_ok=True)
    return ["trace", "--scene", w.scene, "--gaussians", missing, "--labels", w.patches, "--out", out], [str(missing / "point_cloud.ply")], out


@case("trace: truncated PLY")
def _(w):
    gaussians, out = w.copy(w.gaussians), w.out()
    data = (gaussians / "point_cloud.ply").read_bytes()
    (gaussians / "point_cloud.ply").write_bytes(data[: len(data) // 2])
    return ["trace", "--scene", w.scene, "--gaussians", gaussians, "--labels", w.patches, "--out", out], [str(gaussians / "point_cloud.ply")], out


@case("trace: a label map of the wrong size")
def _(w):
    labels, out = wrong_size_map(w, w.patches, w.train[0], 0.5), w.out()
    return ["trace", "--scene", w.scene, "--gaussians", w.gaussians, "--labels", labels, "--out", out], [str(labels / f"{w.train[0]}.png"), "16x12", "32x24"], out


# --- merge ---------------------------------------------------------------------------------------
@case("merge: a patch map of the wrong size")
def _(w):
    patches, out = wrong_size_map(w, w.patches, w.train[0], 2.0), w.out()
    return ["merge", "--scene", w.scene, "--git", w.trace, "--patches", patches, "--out", out], [str(patches / f"{w.train[0]}.png"), "64x48"], out


@case("merge: every patch map empty")
def _(w):
    patches, out = w.copy(w.patches), w.out()
    for frame in w.train + w.test:
        write_png16(patches / f"{frame}.png", np.zeros((24, 32), np.uint16))
    return ["merge", "--scene", w.scene, "--git", w.trace, "--patches", patches, "--out", out], [str(patches), "no view has a patch"], out


@case("merge: typo in a parameter (theta for threshold)")
def _(w):
    out = w.out()
    return ["merge", "--scene", w.scene, "--git", w.trace, "--patches", w.patches, "--out", out, "--params", '{"theta": 0.4}'], ["theta", "threshold"], out


@case("merge: git.npz missing")
def _(w):
    out, empty = w.out(), w.root / "empty-trace"
    empty.mkdir(exist_ok=True)
    return ["merge", "--scene", w.scene, "--git", empty, "--patches", w.patches, "--out", out], [str(empty / "git.npz")], out


@case("merge: git.npz corrupt")
def _(w):
    trace, out = w.copy(w.trace), w.out()
    (trace / "git.npz").write_text("not an archive")
    return ["merge", "--scene", w.scene, "--git", trace, "--patches", w.patches, "--out", out], [str(trace / "git.npz")], out


# --- refine --------------------------------------------------------------------------------------
@case("refine: detect_at after the last iteration")
def _(w):
    out = w.out()
    params = {"iterations": 20, "detect_at": [1, 500], "schedule_scale": 1.0}
    return ["refine", "--scene", w.scene, "--gaussians", w.gaussians, "--labels", w.patches, "--out", out,
            "--params", json.dumps(params)], ["detect_at", "500", "iterations"], out


@case("refine: an instance map of the wrong size")
def _(w):
    labels, out = wrong_size_map(w, w.patches, w.train[-1], 0.5), w.out()
    params = {"iterations": 20, "detect_at": [1, 10], "schedule_scale": 1.0}
    return ["refine", "--scene", w.scene, "--gaussians", w.gaussians, "--labels", labels, "--out", out,
            "--params", json.dumps(params)], [str(labels / f"{w.train[-1]}.png"), "16x12"], out


# --- lift ----------------------------------------------------------------------------------------
@case("lift: an instance map smaller than its view")
def _(w):
    labels, out = wrong_size_map(w, w.patches, w.train[0], 0.5), w.out()
    return ["lift", "--scene", w.scene, "--gaussians", w.gaussians, "--labels", labels, "--out", out,
            "--params", '{"iterations": 2}'], [str(labels / f"{w.train[0]}.png"), "16x12", "32x24"], out


@case("lift: an instance map larger than its view")
def _(w):
    labels, out = wrong_size_map(w, w.patches, w.train[-1], 2.0), w.out()
    return ["lift", "--scene", w.scene, "--gaussians", w.gaussians, "--labels", labels, "--out", out,
            "--params", '{"iterations": 2}'], [str(labels / f"{w.train[-1]}.png"), "64x48", "32x24"], out


@case("lift: misspelled parameter")
def _(w):
    out = w.out()
    return ["lift", "--scene", w.scene, "--gaussians", w.gaussians, "--labels", w.patches, "--out", out,
            "--params", '{"iteratons": 10}'], ["iteratons", "iterations"], out


@case("lift: unknown method")
def _(w):
    out = w.out()
    return ["lift", "--scene", w.scene, "--gaussians", w.gaussians, "--labels", w.patches, "--out", out,
            "--params", '{"method": "magic"}'], ["method", "magic"], out


@case("lift: contrastive without --labels")
def _(w):
    out = w.out()
    return ["lift", "--scene", w.scene, "--gaussians", w.gaussians, "--out", out], ["--labels"], out


# --- evaluate ------------------------------------------------------------------------------------
@case("evaluate: an object id the scene does not have")
def _(w):
    out = w.out("eval")
    return ["evaluate", "--scene", w.scene, "--gaussians", w.gaussians, "--lift", w.lift, "--out", out,
            "--params", '{"objects": [9999]}'], ["evaluate params.objects", "9999", str(w.scene)], out


@case("evaluate: lift folder without lift.json")
def _(w):
    out, empty = w.out("eval"), w.root / "empty-lift"
    empty.mkdir(exist_ok=True)
    return ["evaluate", "--scene", w.scene, "--gaussians", w.gaussians, "--lift", empty, "--out", out], [str(empty / "lift.json")], out


@case("evaluate: --label not JSON")
def _(w):
    out = w.out("eval")
    return ["evaluate", "--scene", w.scene, "--gaussians", w.gaussians, "--lift", w.lift, "--out", out,
            "--label", "{variant: full"], ["--label", "JSON"], out


@case("evaluate: unknown protocol")
def _(w):
    out = w.out("eval")
    return ["evaluate", "--scene", w.scene, "--gaussians", w.gaussians, "--lift", w.lift, "--out", out,
            "--params", '{"protocol": "strict"}'], ["protocol", "strict"], out


# --- report --------------------------------------------------------------------------------------
@case("robustness: spec without runs")
def _(w):
    out = w.out("robustness.md")
    return ["robustness", "--spec", '{"runs": 3}', "--out", out], ["runs"], out


@case("bench fit: a malformed --size")
def _(w):
    out = w.out("bench.json")
    return ["bench", "fit", "--size", "160by120", "--out", out], ["--size", "160by120"], out


def test_catalogue_is_large_enough():
    assert len(CASES) + len(CONFIG_CASES) >= 30


@pytest.mark.parametrize("name", sorted(CASES))
def test_bad_input_is_one_sentence(world, name, capsys):
    argv, phrases, out = CASES[name](world)
    capsys.readouterr()
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert code == 2, (name, code, err)
    assert "Traceback" not in err, err
    lines = [line for line in err.splitlines() if line.startswith("trace3d ")]
    assert len(lines) == 1, err
    sentence = lines[0].split(": error: ", 1)[1]
    assert sentence.endswith((".", "?")), sentence
    for phrase in phrases:
        assert phrase in sentence, (phrase, sentence)
    assert not out.exists(), f"{out} was left behind"
    assert not list(out.parent.glob(f".{out.name}.tmp-*")) if out.parent.exists() else True


def test_a_view_without_masks_is_fine(world):
    """One view without masks is not an error: the masks step writes an empty stack for it."""
    scene, out = world.copy(world.scene), world.out()
    (scene / "masks").mkdir(exist_ok=True)
    for frame in world.train + world.test:
        np.savez(scene / "masks" / f"{frame}.npz", masks=np.ones((1, 24, 32), bool))
    np.savez(scene / "masks" / f"{world.train[0]}.npz", masks=np.zeros((0, 24, 32), bool))
    assert main(["masks", "--scene", str(scene), "--out", str(out), "--source", "files"]) == 0
    summary = json.loads((out / "masks.json").read_text())
    assert summary["masks_per_view"][world.train[0]] == 0 and summary["masks_per_view"][world.train[1]] == 1


def test_metrics_scene_is_not_the_parent_folder(tmp_path):
    from trace3d.scene import scene_name

    (tmp_path / "data" / "kitchen").mkdir(parents=True)
    (tmp_path / "results" / "room0" / "scene").mkdir(parents=True)
    assert scene_name(tmp_path / "data" / "kitchen") == "kitchen"
    assert scene_name(tmp_path / "results" / "room0" / "scene") == "room0"
    assert scene_name(tmp_path / "data" / "kitchen", {"name": "fern"}) == "fern"


# ----------------------------------------------------------------------------------------------
# the config: Snakemake's validation (the dry run's first act) against the generated schema
# ----------------------------------------------------------------------------------------------

CONFIG_CASES = {
    "merge theta for threshold": ({"defaults": {"merge": {"theta": 0.4}}}, ["'theta' is not one of", "'threshold'"]),
    "lift iteratons in a scene": ({"scenes": {"a": {"kind": "synthetic", "lift": {"iteratons": 10}}}},
                                  ["'iteratons' is not one of", "'iterations'"]),
    "gaussians iterations of the wrong type": ({"defaults": {"gaussians": {"iterations": "ten"}}}, ["'ten'", "integer"]),
    "masks simulated key misspelled": ({"defaults": {"masks": {"simulated": {"inconsistncy": 0.3}}}},
                                       ["'inconsistncy' is not one of", "'inconsistency'"]),
    "masks source unknown": ({"defaults": {"masks": {"source": "magic"}}}, ["'magic' is not one of"]),
    "refine train key misspelled": ({"defaults": {"refine": {"train": {"lamda_normal": 0.1}}}}, ["'lamda_normal'"]),
    "evaluate protocol unknown": ({"defaults": {"evaluate": {"protocol": "strict"}}}, ["'strict' is not one of"]),
    "lift method set in the config": ({"defaults": {"lift": {"method": "self_prompt"}}}, ["'method' is not one of"]),
    "unknown step section": ({"defaults": {"merging": {}}}, ["'merging' was unexpected"]),
    "synthetic seed of the wrong type": ({"scenes": {"a": {"kind": "synthetic", "synthetic": {"seed": 1.5}}}},
                                         ["1.5", "integer"]),
    "synthetic seed negative": ({"scenes": {"a": {"kind": "synthetic", "synthetic": {"seed": -3}}}},
                                ["-3", "minimum"]),
    "masks seed negative": ({"defaults": {"masks": {"simulated": {"seed": -3}}}}, ["-3", "minimum"]),
    "gaussians seed negative": ({"defaults": {"gaussians": {"seed": -3}}}, ["-3", "minimum"]),
    "a mask model's inconsistency above 1": (
        {"variants": {"full": {}},
         "mask_models": {"m": {"masks": {"simulated": {"inconsistency": 1.7}}, "variants": ["full"]}}},
        ["1.7", "maximum"]),
    "refine gamma 0": ({"defaults": {"refine": {"gamma": 0}}}, ["0", "exclusiveMinimum"]),
}


def validate_config(config: dict) -> None:
    from snakemake.utils import validate

    validate(config, schema=str(REPO / "workflow" / "schemas" / "config.schema.yaml"))


@pytest.mark.parametrize("name", sorted(CONFIG_CASES))
def test_config_mistake_is_refused_by_the_schema(name):
    override, phrases = CONFIG_CASES[name]
    config = {"scenes": {"a": {"kind": "synthetic"}}, **override}
    with pytest.raises(Exception, match="Error validating config file") as exc:  # snakemake's WorkflowError
        validate_config(json.loads(json.dumps(config)))
    text = str(exc.value)
    for phrase in phrases:
        assert phrase in text, (phrase, text)


def test_shipped_configs_pass_the_schema():
    for path in sorted((REPO / "config").glob("*.yaml")):
        validate_config(yaml.safe_load(path.read_text()))


# Fields whose check relates them to another field (JSON schema cannot say it): the schema holds the part
# of the range that stands alone, and the step refuses the rest in one sentence.
RELATED_FIELDS = {
    "SyntheticParams": ("camera_height", "camera_radius", "clear_radius"),  # the room's size, one another
    "GraphParams": ("max_area",),  # > min_area
    "GeometryParams": ("max_area", "finest_level"),  # > min_area; < the number of thresholds
    "RefineParams": ("iterations",),  # >= every detect_at
}


def _parameter_classes() -> list[type]:
    from trace3d.tooling.schema import _nested, _registry, mask_sources

    classes = []
    for group in [*_registry().values(), *mask_sources().values(), list(_nested().values())]:
        classes += [c for c in group if c not in classes]
    return classes


def test_schema_refuses_what_the_dataclasses_refuse():
    """Every numeric parameter, set alone to values around the usual bounds, is refused by the config schema
    exactly when the step refuses it (so a range checked only by the code fails here: declare it in the
    dataclass's RANGES, trace3d.params)."""
    import dataclasses
    import typing

    import jsonschema

    from trace3d.errors import ConfigError
    from trace3d.params import from_mapping
    from trace3d.tooling.schema import _nested, dataclass_schema

    ints = [-3, -1, 0, 1, 2, 3, 4, 8, 20, 150, 151, 10**9]
    floats = [-1.0, -0.5, 0.0, 1e-9, 0.5, 1.0, 1.5, 2.0, 20.0, 151.0, 1e9]
    disagreements = []
    for cls in _parameter_classes():
        hints = typing.get_type_hints(cls)
        schema = dataclass_schema([cls])
        for f in dataclasses.fields(cls):
            options = [a for a in typing.get_args(hints[f.name]) if a is not type(None)] or [hints[f.name]]
            if (cls, f.name) in _nested() or len(options) != 1 or options[0] not in (int, float):
                continue
            for value in ints + (floats if options[0] is float else []):
                try:
                    from_mapping(cls, {f.name: value})
                    code = True
                except ConfigError:
                    code = False
                schema_ok = jsonschema.Draft202012Validator(schema).is_valid({f.name: value})
                if code != schema_ok and not (f.name in RELATED_FIELDS.get(cls.__name__, ()) and code is False):
                    disagreements.append(f"{cls.__name__}.{f.name} = {value}: the step "
                                         f"{'accepts' if code else 'refuses'} it, the schema does not")
    assert not disagreements, "\n".join(disagreements[:30])


def test_schema_bounds_the_items_of_list_parameters():
    """A declared range holds for every item of a list parameter, also where the field may be a number or a list
    (``coarse_depth: int | list[int] | None``): the schema and the step refuse and accept the same values."""
    import jsonschema

    from trace3d.errors import ConfigError
    from trace3d.lifting.contrastive import ContrastiveParams
    from trace3d.params import from_mapping
    from trace3d.tooling.schema import dataclass_schema
    from trace3d.tracing.refine import RefineParams

    cases = [(ContrastiveParams, "coarse_depth", value) for value in (1, -1, [1, 0], [0, -1], [-2], None)]
    cases += [(RefineParams, "detect_at", value) for value in ([500, 1000], [-5, 1000])]
    for cls, key, value in cases:
        try:
            from_mapping(cls, {key: value})
            code = True
        except ConfigError:
            code = False
        schema_ok = jsonschema.Draft202012Validator(dataclass_schema([cls])).is_valid({key: value})
        assert code == schema_ok, (cls.__name__, key, value, code, schema_ok)
        negative = any(v < 0 for v in (value if isinstance(value, list) else [value]) if v is not None)
        assert code is not negative, (cls.__name__, key, value)


def test_a_range_is_one_sentence_naming_the_key():
    from trace3d.errors import ConfigError
    from trace3d.masks.simulate import SimulateParams
    from trace3d.params import from_mapping

    with pytest.raises(ConfigError, match=r"^masks: inconsistency must be in \[0, 1\], got 1.7\.$"):
        from_mapping(SimulateParams, {"inconsistency": 1.7}, "masks")
    with pytest.raises(ConfigError, match=r"seed must be >= 0, got -3"):
        from_mapping(SimulateParams, {"seed": -3}, "masks")


def test_schema_file_is_generated_from_the_dataclasses():
    """Fails when a parameter dataclass gains, loses or retypes a field without `python -m trace3d.tooling.schema`."""
    from trace3d.tooling.schema import SCHEMA_PATH, schema_text

    assert SCHEMA_PATH.read_text() == schema_text(), "run `python -m trace3d.tooling.schema` to regenerate " \
                                                     "workflow/schemas/steps.schema.yaml"


def test_schema_covers_every_dataclass_field():
    import dataclasses

    from trace3d.tooling.schema import WORKFLOW_SET, _registry, mask_sources

    defs = yaml.safe_load((REPO / "workflow" / "schemas" / "steps.schema.yaml").read_text())["$defs"]
    for step, classes in _registry().items():
        fields = {f.name for cls in classes for f in dataclasses.fields(cls)} - set(WORKFLOW_SET.get(step, ()))
        assert set(defs[step]["properties"]) == fields, step
        assert defs[step]["additionalProperties"] is False
    for source, classes in mask_sources().items():
        fields = {f.name for cls in classes for f in dataclasses.fields(cls)}
        assert set(defs["masks"]["properties"][source]["properties"]) == fields, source
    # every step section of the config refers to the generated definitions
    config_schema = yaml.safe_load((REPO / "workflow" / "schemas" / "config.schema.yaml").read_text())
    for where in (config_schema["properties"]["defaults"]["properties"], config_schema["$defs"]["scene"]["properties"]):
        for step in set(defs) - {"variant", "scene_kind", "imported_kind"}:
            assert where[step]["$ref"] == f"steps.schema.yaml#/$defs/{step}", step
    # the scene kinds are the registry's, not a hand list
    from trace3d.steps import SCENE_KINDS

    assert defs["scene_kind"]["enum"] == list(SCENE_KINDS)
    assert config_schema["$defs"]["scene"]["properties"]["kind"] == {"$ref": "steps.schema.yaml#/$defs/scene_kind"}
    # and a variant's settings to the one generated from trace3d.steps.Variant
    from trace3d.steps import Variant

    assert config_schema["properties"]["variants"]["additionalProperties"]["$ref"] == "steps.schema.yaml#/$defs/variant"
    assert set(defs["variant"]["properties"]) == {f.name for f in dataclasses.fields(Variant)}


def test_step_help_lists_every_parameter(capsys):
    from trace3d.tracing.merge import MergeParams

    with pytest.raises(SystemExit):
        main(["merge", "--help"])
    out = capsys.readouterr().out
    for name in MergeParams.__dataclass_fields__:
        assert f"  {name} = " in out, name
    assert "threshold = null  -- merge patch pairs whose similarity exceeds it" in out
    assert 'candidates = "coarser_mask"' in out


# ----------------------------------------------------------------------------------------------
# Snakemake itself: a dry run with a typo'd step key, a duplicate key, a misspelled target
# ----------------------------------------------------------------------------------------------

SNAKEMAKE = shutil.which("snakemake", path=str(Path(sys.executable).parent)) or shutil.which("snakemake")


def dry_run(tmp_path: Path, config_text: str, *targets: str) -> subprocess.CompletedProcess:
    path = tmp_path / "config.yaml"
    path.write_text(config_text)
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    # targets before --configfile, which takes several values
    return subprocess.run([SNAKEMAKE, "-s", str(REPO / "Snakefile"), "--directory", str(tmp_path), "-n", *targets,
                           "--configfile", str(path)], capture_output=True, text=True, env=env, timeout=300)


@pytest.mark.skipif(SNAKEMAKE is None, reason="snakemake is not installed")
@pytest.mark.parametrize("config_text, targets, phrases", [
    ("defaults:\n  merge: {theta: 0.4}\nscenes:\n  a: {kind: synthetic}\n", (),
     ["Error validating config file", "'theta' is not one of", "'threshold'"]),
    ("scenes:\n  a: {kind: synthetic, synthetic: {seed: 1}}\n  a: {kind: synthetic, synthetic: {seed: 2}}\n", (),
     ["key 'a' appears twice", "lines 2 and 3"]),
    ("scenes:\n  a: {kind: synthetic}\n", ("results/a/fulll/eval",), ["No rule to produce results/a/fulll/eval"]),
    ("scenes:\n  a: {kind: synthetic}\n", ("results/room1/full/eval",), ["No rule to produce results/room1/full/eval"]),
], ids=["step key typo", "duplicate scene", "misspelled variant", "scene not in the config"])
def test_dry_run_refuses_in_one_sentence(tmp_path, config_text, targets, phrases):
    result = dry_run(tmp_path, config_text, *targets)
    text = result.stdout + result.stderr
    assert result.returncode != 0, text
    for phrase in phrases:
        assert phrase in text, (phrase, text)
    assert "Traceback" not in text and "AttributeError" not in text, text
    assert not (tmp_path / "results").exists()


@pytest.mark.skipif(SNAKEMAKE is None, reason="snakemake is not installed")
def test_missing_trace3d_command_is_named_before_any_job(tmp_path):
    """Snakemake run without the environment active: a warning up front, not 'command not found' in every log."""
    (tmp_path / "config.yaml").write_text("scenes:\n  a: {kind: synthetic}\n")
    env = dict(os.environ, PATH="/usr/bin:/bin")
    result = subprocess.run([SNAKEMAKE, "-s", str(REPO / "Snakefile"), "--directory", str(tmp_path), "-n",
                             "--configfile", str(tmp_path / "config.yaml")], capture_output=True, text=True, env=env,
                            timeout=300)
    assert result.returncode == 0, result.stderr
    assert "The trace3d command is not on PATH" in result.stdout + result.stderr


# ----------------------------------------------------------------------------------------------
# interruptions: Ctrl-C in one line; a killed step leaves nothing stale and its rerun the same bytes
# ----------------------------------------------------------------------------------------------

def folder_bytes(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def step_env() -> dict:
    return dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))


def _default_sigint() -> None:
    """In the child before exec: Ctrl-C's default action, as in a terminal. A suite started in the background
    (``nohup ... &``, a CI runner) ignores SIGINT, the ignore is inherited, and Python then installs no
    KeyboardInterrupt handler: the step would not see the interruption at all."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def start_patches(world: World, out: Path, scene: Path | None = None, masks: Path | None = None) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "trace3d.cli", "patches", "--scene", str(scene or world.scene),
                             "--masks", str(masks or world.masks), "--out", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=step_env(),
                            preexec_fn=_default_sigint)


def wait_for_tmp(out: Path, proc: subprocess.Popen, timeout: float = 120.0) -> bool:
    """Wait until the step has created its temporary output folder (True) or ended (False)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if list(out.parent.glob(f".{out.name}.tmp-*")):
            return True
        if proc.poll() is not None:
            return False
        time.sleep(0.01)
    return False


def test_ctrl_c_is_one_line_and_exit_130(world, tmp_path):
    """Ctrl-C while the step writes: one line, exit 130, nothing written. The step runs with SIGINT's default
    action (:func:`_default_sigint`; in a suite started in the background it was ignored and the test skipped),
    on a scene large enough (160 x 120, 16 views: some 0.3 s of writing) that the signal arrives before the
    step ends."""
    scene, masks = tmp_path / "scene", tmp_path / "masks"
    assert main(["scene", "synthetic", "--out", str(scene), "--params",
                 json.dumps({**TINY_SCENE, "width": 160, "height": 120, "num_views": 16, "test_every": 4})]) == 0
    assert main(["masks", "--scene", str(scene), "--out", str(masks)]) == 0
    out = world.out("patches")
    out.parent.mkdir(parents=True, exist_ok=True)
    proc = start_patches(world, out, scene, masks)
    if not wait_for_tmp(out, proc):
        proc.wait()
        pytest.skip("the step ended before it could be interrupted")
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    if proc.returncode == 0:
        pytest.skip("the step ended before the interruption arrived")
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "SystemError" not in err, err
    lines = [line for line in err.splitlines() if line.startswith("trace3d ")]
    assert lines == ["trace3d patches: interrupted; nothing was written (an earlier output, if any, is unchanged)."]
    assert not out.exists() and not list(out.parent.glob(f".{out.name}.tmp-*"))


def test_killed_step_reruns_to_the_same_bytes(world):
    """SIGKILL (no clean-up possible) at several points of the patches step: the temporary folder is
    left, the next run removes it and writes exactly the bytes of an uninterrupted run; an earlier output
    survives a killed rerun untouched."""
    reference = world.out("patches")
    assert main(["patches", "--scene", str(world.scene), "--masks", str(world.masks), "--out", str(reference)]) == 0
    expected = folder_bytes(reference)
    out = world.out("patches")
    out.parent.mkdir(parents=True, exist_ok=True)
    kills = 0
    for delay in (0.0, 0.05, 0.2, 0.5):
        previous = folder_bytes(out) if out.exists() else None
        proc = start_patches(world, out)
        inside = wait_for_tmp(out, proc)
        time.sleep(delay)
        proc.kill()
        proc.wait()
        if inside and proc.returncode == -signal.SIGKILL:
            kills += 1
            if previous is not None:
                assert folder_bytes(out) == previous  # the earlier output is untouched
        assert main(["patches", "--scene", str(world.scene), "--masks", str(world.masks), "--out", str(out)]) == 0
        assert folder_bytes(out) == expected
        assert not list(out.parent.glob(f".{out.name}.tmp-*")), "a stale temporary folder was left"
    assert kills >= 1, "no kill landed inside the step"


# ----------------------------------------------------------------------------------------------
# the first run: a notice before compiling, an ETA without the compile, logs naming final paths
# ----------------------------------------------------------------------------------------------

def test_compile_notice_and_eta_leave_out_the_compile(caplog, monkeypatch):
    from tqdm import tqdm

    from trace3d.tooling import compiling

    monkeypatch.setattr(compiling, "_state", {"installed": True, "announced": False, "depth": 0, "start": 0.0,
                                              "seconds": 0.0})
    bar = compiling.track(tqdm(range(10), disable=False, file=open(os.devnull, "w")))
    start, last = bar.start_t, bar.last_print_t
    with caplog.at_level("INFO", logger="trace3d"):
        compiling._on_start()
        compiling._on_start()  # a nested compile (an inlined kernel) is part of the outer one
        time.sleep(0.2)
        compiling._on_end()
        compiling._on_end()
        compiling._on_start()
        compiling._on_end()
    notices = [r.getMessage() for r in caplog.records if "compiling kernels" in r.getMessage()]
    assert len(notices) == 1 and notices[0].startswith("compiling kernels (first run only, about 3 min")
    assert compiling.compile_seconds() >= 0.2
    assert bar.start_t - start >= 0.2 and bar.last_print_t - last >= 0.2  # the bar's clock skips the compile
    assert abs((bar.start_t - start) - compiling.compile_seconds()) < 1e-6
    bar.close()


def test_logs_name_the_final_paths(tmp_path):
    """A message logged inside a step that names the temporary folder names the final folder instead."""
    import logging

    from trace3d.io import TempPathFilter, atomic_dir

    record_text = []

    class Keep(logging.Handler):
        def emit(self, record):
            record_text.append(record.getMessage())

    handler = Keep()
    handler.addFilter(TempPathFilter())
    logger = logging.getLogger("trace3d.test_paths")
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        with atomic_dir(tmp_path / "poses") as tmp:
            logger.info("wrote %s", tmp / "cameras.json")
    finally:
        logger.removeHandler(handler)
    assert record_text == [f"wrote {tmp_path / 'poses' / 'cameras.json'}"]


def test_stale_temporary_siblings_of_dead_runs_are_removed(tmp_path):
    from trace3d.io import atomic_dir

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True).stdout.strip()
    stale = tmp_path / f".out.tmp-{dead}-0123abcd"
    (stale / "half").mkdir(parents=True)
    alive = tmp_path / f".out.tmp-{os.getppid()}-0123abcd"  # a running process's folder is left alone
    alive.mkdir()
    other = tmp_path / f".other.tmp-{dead}-0123abcd"  # another step's
    other.mkdir()
    with atomic_dir(tmp_path / "out") as tmp:
        (tmp / "x").write_text("1")
    assert not stale.exists() and alive.exists() and other.exists()
    assert (tmp_path / "out" / "x").read_text() == "1"
