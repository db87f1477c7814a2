"""The Snakemake workflow: config validation, lint, and a tiny end-to-end run."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import yaml

from trace3d.cli import main

REPO = Path(__file__).resolve().parents[2]
SNAKEMAKE = shutil.which("snakemake", path=str(Path(sys.executable).parent)) or shutil.which("snakemake")

pytestmark = pytest.mark.skipif(SNAKEMAKE is None, reason="snakemake is not installed")


def run_snakemake(workdir: Path, *args: str, config: dict | None = None, timeout: float | None = None):
    cmd = [SNAKEMAKE, "-s", str(REPO / "Snakefile"), "--directory", str(workdir)]
    if config is not None:
        path = workdir / "config.yaml"
        path.write_text(yaml.safe_dump(config))
        cmd += ["--configfile", str(path)]
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env.setdefault("NUMBA_CACHE_DIR", str(REPO / ".numba_cache"))
    return subprocess.run(cmd + list(args), capture_output=True, text=True, env=env, timeout=timeout)


@pytest.mark.parametrize(
    "config, message",
    [
        ({"scenes": {"r0": {"kind": "synthetic", "synthtic": {"seed": 0}}}}, "'synthtic' was unexpected"),
        ({"scenes": {"r0": {"kind": "mesh"}}}, "'mesh' is not one of"),
        ({"scenes": {"r0": {"kind": "replica"}}}, "'source' is a required property"),
        ({"scenes": {"r0": {"kind": "synthetic"}}, "results": 3}, "3 is not of type 'string'"),
        ({"scenes": {}}, "should be non-empty"),
    ],
)
def test_schema_refuses_bad_config(tmp_path, config, message):
    result = run_snakemake(tmp_path, "-n", config=config)
    assert result.returncode != 0
    assert "Error validating config file" in result.stderr + result.stdout
    assert message in result.stderr + result.stdout


def test_lint_is_clean(tmp_path):
    result = subprocess.run(
        [SNAKEMAKE, "--lint"], cwd=REPO, capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 0, result.stdout + result.stderr


def test_dry_run_default_config():
    result = subprocess.run(
        [SNAKEMAKE, "-n", "reproduce"], cwd=REPO, capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 0, result.stderr
    for scene in ("room0", "room1", "room2", "room3"):
        assert f"scene={scene}" in result.stdout


TINY_TRAINING = {"schedule_scale": 1.0, "iterations": 40, "densify_from": 10, "densify_until": 30,
                 "densify_interval": 10, "normal_from": 20, "sh_degree": 1, "sh_degree_interval": 20,
                 "device": "cpu"}
RESULTS_NAME = "my rés ults"  # the whole-DAG test's results folder
TINY_SYNTHETIC = {"width": 48, "height": 36, "num_views": 6, "test_every": 3, "num_objects": 10, "supersample": 1}


@pytest.mark.slow
@pytest.mark.xdist_group("whole_dag")  # whole-DAG runs take turns on one worker (tests/conftest.py)
def test_end_to_end_tiny(tmp_path):
    config = {
        "defaults": {
            "synthetic": TINY_SYNTHETIC,
            # six views 60 degrees apart do not overlap enough for SfM (tests/poses/test_poses.py covers COLMAP)
            "poses": {"mode": "dataset"},
            "masks": {"source": "simulated", "simulated": {"inconsistency": 0.5}},
            "gaussians": TINY_TRAINING,
            "refine": {"iterations": 20, "detect_at": [1, 10], "schedule_scale": 1.0, "highlight_views": 1},
            "lift": {"iterations": 30, "pixels": 256, "pool_pixels": 512, "pca_views": 1},
            "evaluate": {"min_pixels": 20, "turntable_views": 3, "turntable_size": 32},
        },
        # both ablation switches: the shared steps must run once
        "variants": {"full": {}, "no_refine": {"density_control": False}, "raw": {"consistent_masks": False},
                     "sp": {"lifting": "self_prompt"}, "off": {"preset": "official"}},
        # one room through the whole DAG: a second room would rerun the same 38 jobs (~45 % of the test's
        # CPU; every job pays ~2.5 s of process start); the steps' and tables' handling of several
        # rooms is checked by the dry runs below (one job per room and step) and tests/report/test_tables.py,
        # and the scenes table's by a second room's scene step at the end
        "scenes": {"a": {"kind": "synthetic", "synthetic": {"seed": 1}}},
        # one more mask level of scene a, on a's fit (0.5 is a itself)
        "robustness": {"scenes": ["a"], "levels": [0.0, 0.5], "variants": ["no_refine"]},
        # a space and a non-ASCII letter in every path the rules pass to a shell (issue 49)
        "results": RESULTS_NAME,
    }
    results = tmp_path / RESULTS_NAME
    # the whole DAG with both evaluation protocols: a few minutes on an idle 2-core machine, far more beside
    # other jobs (600 s ran out on 2026-11-27 under a load average of 10)
    result = run_snakemake(tmp_path, "--cores", "2", "reproduce", config=config)
    assert result.returncode == 0, result.stderr[-4000:]
    # the Snakefile's onstart took Snakemake's job-rate limiter off this local run (trace3d/tooling/scheduling.py)
    assert "job-rate limiter is off for this local run" in result.stderr
    for scene in ("a",):
        root = results / scene / "scene"
        assert len(list((root / "images").glob("*.png"))) == 6
        assert (root / "preview.png").stat().st_size > 1000
        assert (results / "logs" / scene / "scene.log").is_file()
        assert (results / "benchmarks" / scene / "scene.tsv").is_file()
        for step in ("poses", "masks", "patches", "gaussians"):
            assert (results / scene / step).is_dir(), step
        assert len(list((results / scene / "patches").glob("*.png"))) >= 6
        assert (results / scene / "gaussians" / "point_cloud.ply").is_file()
        for step in ("trace-paper", "merge-paper", "refine-paper-merged", "refine-paper-patches"):
            assert (results / scene / step).is_dir(), step
        assert not (results / scene / "refine-official-patches").exists()  # no such variant
        assert (results / scene / "refine-official-merged").is_dir()  # the official preset's own
        assert len(list((results / scene / "merge-paper" / "instances").glob("*.png"))) >= 4
        for name in ("full", "no_refine", "raw"):
            assert (results / scene / name / "lift" / "features.npy").is_file(), name
            assert (results / scene / name / "eval" / "metrics.json").is_file(), name
            official = json.loads((results / scene / name / "eval-official" / "metrics.json").read_text())
            assert official["protocol"] == "official" and official["params"]["views"] == "all", name
            assert list((results / scene / name / "objects").glob("*.ply")), name
            assert not (results / scene / name / "eval" / "objects").exists()
    tables = results / "tables"
    for name in ("table2", "table3", "table5"):
        text = (tables / f"{name}.md").read_text()
        assert "full" in text, (name, text)
        assert (tables / f"{name}.csv").is_file() and (tables / f"{name}.tex").is_file()
    assert "no_refine" in (tables / "table2.md").read_text() and "raw" in (tables / "table3.md").read_text()
    for scene in ("a",):  # self-prompting: no features, its own evaluation; the official preset: its own lift
        assert json.loads((results / scene / "sp" / "lift" / "lift.json").read_text())["method"] == \
            "self_prompt"
        assert (results / scene / "sp" / "eval" / "metrics.json").is_file()
        assert json.loads((results / scene / "off" / "lift" / "lift.json").read_text())["params"][
            "preset"] == "official"
    assert "| sp |" in (tables / "table5.md").read_text() and "| off |" in (tables / "table2.md").read_text()
    assert "official" in (tables / "official" / "table2.md").read_text()  # its protocol note
    assert "standard" in (tables / "table2.md").read_text() and "official" not in (tables / "table2.md").read_text()
    assert (results / "plots" / "lift" / "a-full.png").stat().st_size > 1000
    # the robustness level: its own masks and evaluation, the base scene's fit (no scene/poses/gaussians)
    derived = results / "a@inc0"
    assert (derived / "no_refine" / "eval" / "metrics.json").is_file()
    assert not any((derived / step).exists() for step in ("scene", "poses", "gaussians"))
    robust = pd.read_csv(tables / "robustness.csv")
    assert sorted(robust["level"]) == [0.0, 0.5] and set(robust["variant"]) == {"no_refine"}
    assert (robust["scene"] == "a").all() and robust["object mIoU"].notna().all()
    assert (results / "plots" / "robustness.png").stat().st_size > 1000
    report = run_snakemake(tmp_path, "--cores", "1", "reproduce", "--report", str(tmp_path / "report.html"),
                           config=config)
    assert report.returncode == 0, report.stderr[-4000:]
    html = (tmp_path / "report.html").read_text(errors="replace")
    assert "table2" in html and "Tables" in html and "Robustness" in html
    tracing = (results / "tracing.md").read_text()
    assert "| a " in tracing and "ARI before" in tracing
    reconstruction = (results / "reconstruction.md").read_text()
    assert "| a " in reconstruction and "| mean " in reconstruction
    assert (results / "plots" / "reconstruction.png").stat().st_size > 1000
    table = (results / "scenes.md").read_text()
    assert "| a " in table and "| b " not in table and "48x36" in table
    # every step output is whole: its files match the manifest it wrote last
    assert main(["verify", str(results)]) == 0
    assert not list(tmp_path.glob("my")) and not list(tmp_path.glob("ults*")), "a path was split at its space"
    # nothing left to do: a second run is a no-op
    again = run_snakemake(tmp_path, "--cores", "2", "reproduce", "-n", config=config)
    assert again.returncode == 0
    assert "Nothing to be done" in again.stdout + again.stderr
    # a second room: the scenes table lists both, after only that room's scene step (a's outputs stay)
    two = {**config, "scenes": {**config["scenes"], "b": {"kind": "synthetic", "synthetic": {"seed": 2}}}}
    more = run_snakemake(tmp_path, "--cores", "2", f"{RESULTS_NAME}/scenes.md", config=two)
    assert more.returncode == 0, more.stderr[-4000:]
    assert re.search(r"^scene +1$", more.stdout + more.stderr, re.M), (more.stdout + more.stderr)[-3000:]
    table = (results / "scenes.md").read_text()
    assert "| a " in table and "| b " in table and "48x36" in table


GRID = {"full": {}, "no_merge": {"consistent_masks": False}, "no_refine": {"density_control": False},
        "both_off": {"consistent_masks": False, "density_control": False},
        "egolifter": {"consistent_masks": False, "density_control": False, "overlay": True},
        "flashsplat": {"density_control": False, "lifting": "labels"}}


def test_variants_switch_steps_off_by_handing_their_input_through(tmp_path):
    """Each variant's lift reads exactly the folders its switches name: a switched-off step is skipped,
    its input handed on (the raw patches, the plain fit), never a copy."""
    config = {"scenes": {"a": {"kind": "synthetic"}}, "variants": GRID}
    result = run_snakemake(tmp_path, "-n", "-p", "reproduce", config=config)
    assert result.returncode == 0, result.stderr[-3000:]
    lifts = {line.split("--out results/a/")[1].split("/")[0]: line
             for line in result.stdout.splitlines() if " lift --scene" in line}
    assert set(lifts) == set(GRID)
    expect = {  # variant: (gaussians, labels)
        "full": ("refine-paper-merged", "merge-paper/instances"),
        "no_merge": ("refine-paper-patches", "patches"),
        "no_refine": ("gaussians", "merge-paper/instances"),
        "both_off": ("gaussians", "patches"),
        "egolifter": ("gaussians", "overlay"),
        "flashsplat": ("gaussians", "merge-paper/instances"),
    }
    for name, (gaussians, labels) in expect.items():
        assert f"--gaussians results/a/{gaussians} " in lifts[name], lifts[name]
        assert f"--labels results/a/{labels} " in lifts[name], lifts[name]
    assert '"method": "labels"' in lifts["flashsplat"] and '"method": "contrastive"' in lifts["egolifter"]
    # shared steps once: one trace, one merge, two refines (merged and patches) for six variants
    shells = result.stdout
    assert shells.count(" trace --scene") == 1 and shells.count(" merge --scene") == 1
    assert shells.count(" refine --scene") == 2 and shells.count(" overlay --scene") == 1


def test_overlay_variant_with_merging_is_refused(tmp_path):
    config = {"scenes": {"a": {"kind": "synthetic"}}, "variants": {"bad": {"overlay": True}}}
    result = run_snakemake(tmp_path, "-n", "reproduce", config=config)
    assert result.returncode != 0
    assert "variants.bad: overlay: true" in result.stdout + result.stderr


def test_seeds_config_repeats_the_default_grid_over_more_rooms():
    default = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    seeds = yaml.safe_load((REPO / "config" / "seeds.yaml").read_text())
    assert seeds["variants"] == default["variants"] and seeds["defaults"] == default["defaults"]
    assert seeds["results"] != default["results"]  # never mixes with the default run's tables
    assert [s["synthetic"]["seed"] for s in seeds["scenes"].values()] == list(range(12))
    result = subprocess.run([SNAKEMAKE, "-n", "--configfile=config/seeds.yaml", "reproduce"], cwd=REPO,
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "room11/full/eval" in result.stdout and "room11/egolifter/lift" in result.stdout


def _robust_config(**robustness):
    return {"scenes": {"a": {"kind": "synthetic"}, "b": {"kind": "synthetic"}}, "variants": GRID,
            "robustness": {"scenes": ["a"], "levels": [0.0, 0.5, 1.0],
                           "variants": ["full", "both_off", "egolifter", "flashsplat"], **robustness}}


def test_robustness_levels_share_the_scene_poses_and_fit(tmp_path):
    """Every mask level of a room runs its own masks ... evaluate on the room's one scene, poses and fit."""
    result = run_snakemake(tmp_path, "-n", "-p", "reproduce", config=_robust_config())
    assert result.returncode == 0, result.stderr[-3000:]
    shells = [line[line.index("trace3d "):] for line in result.stdout.splitlines() if "trace3d --threads" in line]
    outs = {}  # step -> the folders its jobs write
    for line in shells:
        words = line.split()
        outs.setdefault(words[3], []).append(words[words.index("--out") + 1])
    for step in ("scene", "poses", "gaussians"):  # one job per configured scene, none for the levels
        assert sorted(outs[step]) == [f"results/a/{step}", f"results/b/{step}"], outs[step]
    assert sorted(outs["masks"]) == ["results/a/masks", "results/a@inc0/masks", "results/a@inc1/masks",
                                     "results/b/masks"]
    masks = {line.split("--out ")[1].split()[0]: line for line in shells if " masks --scene" in line}
    assert masks["results/a@inc0/masks"].startswith("trace3d")
    assert '"inconsistency": 0.0' in masks["results/a@inc0/masks"]
    assert '"inconsistency": 1.0' in masks["results/a@inc1/masks"]
    assert "inconsistency" not in masks["results/a/masks"] and "results/a@inc0.5/masks" not in masks
    assert all("--scene results/a/scene " in line for out, line in masks.items() if out.startswith("results/a"))
    lifts = {line.split("--out ")[1].split()[0]: line for line in shells if " lift --scene" in line}
    full = lifts["results/a@inc1/full/lift"]
    assert "--gaussians results/a@inc1/refine-paper-merged " in full
    assert "--labels results/a@inc1/merge-paper/instances " in full
    assert "--gaussians results/a/gaussians " in lifts["results/a@inc1/both_off/lift"]
    assert "--labels results/a@inc1/overlay " in lifts["results/a@inc1/egolifter/lift"]
    assert "results/a@inc1/no_merge/lift" not in lifts  # only the curve's variants run per level
    assert "results/b@inc1/full/lift" not in lifts
    robust = [line for line in shells if " robustness --spec" in line]
    assert len(robust) == 1 and "results/a@inc0/flashsplat/eval" in robust[0] and "results/a/full/eval" in robust[0]


@pytest.mark.parametrize("override, message", [
    ({"scenes": ["c"]}, "robustness.scenes: 'c' is not one of the config's scenes"),
    ({"variants": ["nope"]}, "robustness.variants: 'nope' is not one of the config's variants"),
])
def test_robustness_config_mistakes_are_one_sentence(tmp_path, override, message):
    result = run_snakemake(tmp_path, "-n", "reproduce", config=_robust_config(**override))
    assert result.returncode != 0
    assert message in result.stdout + result.stderr


def test_robustness_needs_simulated_masks(tmp_path):
    config = _robust_config()
    config["scenes"]["a"]["masks"] = {"source": "files"}
    result = run_snakemake(tmp_path, "-n", "reproduce", config=config)
    assert result.returncode != 0
    assert "needs masks.source: simulated" in result.stdout + result.stderr


def _study_config():
    return {"scenes": {"a": {"kind": "synthetic"}, "b": {"kind": "synthetic"}},
            "variants": {**GRID, "sp": {"lifting": "self_prompt", "lift": {"points": 5}}},
            "mask_models": {"hi": {"masks": {"simulated": {"inconsistency": 1.0}}, "variants": ["full", "both_off"]},
                            "top": {"masks": {}, "patches": {"max_depth": 0}, "variants": ["both_off"]}},
            "oracle": {"variants": ["both_off"]},
            "seeds": {"values": [0, 2], "variants": ["full", "both_off"]}}


def test_mask_models_oracle_and_seeds_share_the_rooms_fit(tmp_path):
    """A mask model is a derived scene <room>@<model> on the room's scene, poses and fit; the oracle is the
    room at inconsistency 0; a lift seed s > 0 is the run <variant>.s<s> with the lift's seed set; the
    effects table reads every one of them."""
    result = run_snakemake(tmp_path, "-n", "-p", "reproduce", config=_study_config())
    assert result.returncode == 0, result.stderr[-3000:]
    shells = [line[line.index("trace3d "):] for line in result.stdout.splitlines() if "trace3d --threads" in line]
    outs = {}
    for line in shells:
        words = line.split()
        outs.setdefault(words[3], []).append(words[words.index("--out") + 1])
    for step in ("scene", "poses", "gaussians"):
        assert sorted(outs[step]) == [f"results/a/{step}", f"results/b/{step}"], outs[step]
    assert sorted(outs["masks"]) == ["results/a/masks", "results/a@hi/masks", "results/a@inc0/masks",
                                     "results/a@top/masks", "results/b/masks", "results/b@hi/masks",
                                     "results/b@inc0/masks", "results/b@top/masks"]
    # a mask model's own patch settings reach its patches step, and only its
    patches = {line.split("--out ")[1].split()[0]: line for line in shells if " patches --scene" in line}
    assert '"max_depth": 0' in patches["results/a@top/patches"]
    assert all('"max_depth"' not in line for out, line in patches.items() if "@top" not in out)
    lifts = {line.split("--out ")[1].split()[0]: line for line in shells if " lift --scene" in line}
    assert sorted(k for k in lifts if "@" in k) == sorted(
        [f"results/{r}@hi/{v}/lift" for r in "ab" for v in ("full", "full.s2", "both_off", "both_off.s2")]
        + [f"results/{r}@{m}/{v}/lift" for r in "ab" for m in ("inc0", "top") for v in ("both_off", "both_off.s2")])
    assert '"seed": 2' in lifts["results/a@hi/full.s2/lift"] and '"seed"' not in lifts["results/a@hi/full/lift"]
    assert "--gaussians results/a@hi/refine-paper-merged " in lifts["results/a@hi/full.s2/lift"]
    assert "--gaussians results/a/gaussians " in lifts["results/a@inc0/both_off/lift"]
    assert '"points": 5' in lifts["results/a/sp/lift"] and "results/a/sp.s2/lift" not in lifts
    evals = [line for line in shells if " evaluate --scene" in line and "results/a/full.s2/eval" in line]
    assert len(evals) == 1 and '"seed": 2' in evals[0] and '"variant": "full"' in evals[0]
    effects = [line for line in shells if " effects --spec" in line]
    assert len(effects) == 1
    spec = json.loads(effects[0].split("--spec ")[1].split(" --out")[0].strip("'"))
    masks = {(r["room"], r["masks"], r["variant"], r["seed"]) for r in spec["runs"]}
    assert ("a", "oracle", "both_off", 2) in masks and ("b", "hi", "full", 0) in masks
    assert ("a", "default", "sp", 0) in masks and spec["oracle"] == ["both_off"]


@pytest.mark.parametrize("override, message", [
    ({"mask_models": {"hi": {"masks": {}, "variants": ["nope"]}}}, "mask_models.hi.variants: 'nope' is not one"),
    ({"oracle": {"variants": ["nope"]}}, "oracle.variants: 'nope' is not one"),
    ({"seeds": {"values": [1], "variants": ["nope"]}}, "seeds.variants: 'nope' is not one"),
])
def test_study_config_mistakes_are_one_sentence(tmp_path, override, message):
    result = run_snakemake(tmp_path, "-n", "reproduce", config={**_study_config(), **override})
    assert result.returncode != 0
    assert message in result.stdout + result.stderr


def test_all_pairs_variant_has_its_own_merge_and_refine(tmp_path):
    """merge_candidates: all_pairs runs the merge with candidates all_pairs into merge-<preset>-all and
    refines on those maps; the coarser-mask variants keep their folders."""
    config = {"scenes": {"a": {"kind": "synthetic"}},
              "variants": {"full": {}, "full_all": {"merge_candidates": "all_pairs"},
                           "all_no_refine": {"merge_candidates": "all_pairs", "density_control": False}}}
    result = run_snakemake(tmp_path, "-n", "-p", "reproduce", config=config)
    assert result.returncode == 0, result.stderr[-3000:]
    shells = [line[line.index("trace3d "):] for line in result.stdout.splitlines() if "trace3d --threads" in line]
    merges = {line.split("--out ")[1].split()[0]: line for line in shells if " merge --scene" in line}
    assert sorted(merges) == ["results/a/merge-paper", "results/a/merge-paper-all"]
    assert '"candidates": "all_pairs"' in merges["results/a/merge-paper-all"]
    assert "candidates" not in merges["results/a/merge-paper"]
    lifts = {line.split("--out ")[1].split()[0]: line for line in shells if " lift --scene" in line}
    assert ("--gaussians results/a/refine-paper-mergedall --labels results/a/merge-paper-all/instances "
            in lifts["results/a/full_all/lift"])
    assert "--labels results/a/merge-paper-all/instances " in lifts["results/a/all_no_refine/lift"]
    assert "--gaussians results/a/refine-paper-merged " in lifts["results/a/full/lift"]


def test_threshold_variant_has_its_own_merge_and_refine(tmp_path):
    """merge_threshold: 0.4 runs the merge at that threshold into merge-<preset>-t0.4 (with all pairs:
    merge-<preset>-all-t0.4) and refines on those maps; the preset's folders stay as they are."""
    config = {"scenes": {"a": {"kind": "synthetic"}},
              "variants": {"full": {}, "full_t04": {"merge_threshold": 0.4},
                           "all_t03": {"merge_candidates": "all_pairs", "merge_threshold": 0.3},
                           "official_t05": {"preset": "official", "merge_threshold": 0.5, "density_control": False}}}
    result = run_snakemake(tmp_path, "-n", "-p", "reproduce", config=config)
    assert result.returncode == 0, result.stderr[-3000:]
    shells = [line[line.index("trace3d "):] for line in result.stdout.splitlines() if "trace3d --threads" in line]
    merges = {line.split("--out ")[1].split()[0]: line for line in shells if " merge --scene" in line}
    assert sorted(merges) == ["results/a/merge-official-t0.5", "results/a/merge-paper",
                              "results/a/merge-paper-all-t0.3", "results/a/merge-paper-t0.4"]
    assert '"threshold": 0.4' in merges["results/a/merge-paper-t0.4"]
    assert "candidates" not in merges["results/a/merge-paper-t0.4"]
    assert '"candidates": "all_pairs"' in merges["results/a/merge-paper-all-t0.3"]
    assert '"threshold": 0.3' in merges["results/a/merge-paper-all-t0.3"]
    assert '"preset": "official"' in merges["results/a/merge-official-t0.5"]
    assert "threshold" not in merges["results/a/merge-paper"]
    lifts = {line.split("--out ")[1].split()[0]: line for line in shells if " lift --scene" in line}
    assert ("--gaussians results/a/refine-paper-merged-t0.4 --labels results/a/merge-paper-t0.4/instances "
            in lifts["results/a/full_t04/lift"])
    assert ("--gaussians results/a/refine-paper-mergedall-t0.3 --labels results/a/merge-paper-all-t0.3/instances "
            in lifts["results/a/all_t03/lift"])
    assert "--labels results/a/merge-official-t0.5/instances " in lifts["results/a/official_t05/lift"]
    refines = [line for line in shells if " refine --scene" in line]
    assert any("--labels results/a/merge-paper-t0.4/instances" in line for line in refines)


def test_hierarchical_variant_has_its_own_merge_and_refine(tmp_path):
    """merge_method: hierarchical runs the merge with method hierarchical into merge-<preset>-hier and refines
    on those maps, beside the paper's merge."""
    config = {"scenes": {"a": {"kind": "synthetic"}},
              "variants": {"full": {}, "full_hier": {"merge_method": "hierarchical"},
                           "full_released": {"merge_method": "released"}}}
    result = run_snakemake(tmp_path, "-n", "-p", "reproduce", config=config)
    assert result.returncode == 0, result.stderr[-3000:]
    shells = [line[line.index("trace3d "):] for line in result.stdout.splitlines() if "trace3d --threads" in line]
    merges = {line.split("--out ")[1].split()[0]: line for line in shells if " merge --scene" in line}
    assert sorted(merges) == ["results/a/merge-paper", "results/a/merge-paper-hier", "results/a/merge-paper-released"]
    assert '"method": "hierarchical"' in merges["results/a/merge-paper-hier"]
    released = merges["results/a/merge-paper-released"]
    assert '"preset": "official"' in released and '"candidates": "conflict_area"' in released
    assert "--git results/a/trace-paper " in released  # the released merge on this variant's own trace
    assert "hierarchical" not in merges["results/a/merge-paper"]
    refines = [line for line in shells if " refine --scene" in line]
    assert any("--labels results/a/merge-paper-hier/instances " in r and "--out results/a/refine-paper-mergedhier "
               in r for r in refines)
    lifts = {line.split("--out ")[1].split()[0]: line for line in shells if " lift --scene" in line}
    assert ("--gaussians results/a/refine-paper-mergedhier --labels results/a/merge-paper-hier/instances "
            in lifts["results/a/full_hier/lift"])


def test_fit_seeds_fit_the_room_again_and_join_the_study(tmp_path):
    """fit_seeds: a fit seed s > 0 is the derived scene <room>.fit<s>: the room's scene and poses, its own fit
    with gaussians.seed = s and everything after it, for fit_seeds.variants; the effects spec samples it."""
    config = {**_study_config(), "fit_seeds": {"values": [0, 3], "variants": ["full", "both_off"]}}
    result = run_snakemake(tmp_path, "-n", "-p", "reproduce", config=config)
    assert result.returncode == 0, result.stderr[-3000:]
    shells = [line[line.index("trace3d "):] for line in result.stdout.splitlines() if "trace3d --threads" in line]
    fits = {line.split("--out ")[1].split()[0]: line for line in shells if " gaussians --scene" in line}
    assert sorted(fits) == ["results/a.fit3/gaussians", "results/a/gaussians", "results/b.fit3/gaussians",
                            "results/b/gaussians"]
    assert "--scene results/a/scene --poses results/a/poses " in fits["results/a.fit3/gaussians"]
    assert '"seed": 3' in fits["results/a.fit3/gaussians"] and '"seed"' not in fits["results/a/gaussians"]
    traces = [line for line in shells if " trace --scene" in line and "results/a.fit3/" in line]
    assert len(traces) == 1 and "--gaussians results/a.fit3/gaussians " in traces[0]
    lifts = {line.split("--out ")[1].split()[0]: line for line in shells if " lift --scene" in line}
    assert "--gaussians results/a.fit3/gaussians " in lifts["results/a.fit3/both_off.s2/lift"]
    assert "results/a.fit3/sp/lift" not in lifts
    effects = [line for line in shells if " effects --spec" in line]
    spec = json.loads(effects[0].split("--spec ")[1].split(" --out")[0].strip("'"))
    samples = {(r["room"], r["masks"], r["variant"], r["fit"], r["seed"]) for r in spec["runs"]}
    assert ("a", "default", "full", 3, 2) in samples and ("a", "default", "full", 0, 2) in samples
    assert not any(r["fit"] == 3 and r["masks"] != "default" for r in spec["runs"])
