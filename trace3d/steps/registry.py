"""The pipeline's steps in one table: what the CLI, the Snakemake rules and the config schema read.

One :class:`Step` per ``trace3d`` subcommand: its command-line flags and help, the library function it
runs (``entry``), its parameter dataclasses by config section (``params``), the Snakemake rules that run
it (``rules``), and the module holding its ``run(args)`` handler, ``trace3d.steps.<command>``
(``-`` written ``_``). :mod:`trace3d.cli` builds its parser from :data:`STEPS`; the rules hash each
step's code from the import graph of that module (:mod:`trace3d.tooling.codehash`) and read the lift methods'
keys and the variant defaults from here; ``trace3d describe --json`` prints it all.

Importing this module is cheap (no numpy, torch or numba; nothing else of the package): the handler
modules are loaded by name when their command runs (:func:`handler`), and dataclasses are named as
``"module:Class"`` strings. :func:`fields_static` reads a dataclass's fields and literal defaults from
its source (``ast``, no import), which is how the Snakemake process learns them without importing torch;
``tests/cli/test_steps.py`` checks that the static reading and the imported dataclasses agree.

A new step: a :class:`Step` in :data:`STEPS`, its handler ``trace3d/steps/<command>.py`` with
``run(args)`` (library imports inside the function, so that ``trace3d --help`` stays fast), and a rule
whose ``params`` hold ``code=step_code("<command>")``; a parameter dataclass named in ``params`` joins
the generated config schema (``python -m trace3d.tooling.schema``).
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import importlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

PACKAGE = Path(__file__).resolve().parent.parent
PARAMS_HELP = "parameter overrides: inline JSON/YAML mapping, or @file.yaml"


@dataclass(frozen=True)
class Arg:
    """One command-line argument: ``flags`` and ``kwargs`` as :meth:`argparse.ArgumentParser.add_argument`
    takes them."""

    flags: tuple[str, ...]
    kwargs: dict = field(default_factory=dict)


def arg(*flags: str, **kwargs: Any) -> Arg:
    return Arg(tuple(flags), kwargs)


def params_arg(more: str = "") -> Arg:
    return arg("--params", help=PARAMS_HELP + (f" ({more})" if more else ""))


@dataclass(frozen=True)
class Step:
    """A ``trace3d`` subcommand.

    command: the subcommand (``trace3d <command>``); its handler is ``trace3d.steps.<module>.run``.
    help: the one line ``trace3d --help`` shows.
    args: its command-line arguments.
    entry: the library functions it calls, as ``module:function`` (the first is the step's own).
    params: config section -> its parameter dataclasses as ``module:Class`` (several: any one's keys).
    rules: the Snakemake rules that run the command (empty: run by hand or by another tool only).
    kernels: whether it runs numba kernels (False: no compile listener, no numba import).
    spin: whether its workers should spin briefly between parallel regions (``GOMP_SPINCOUNT``).
    """

    command: str
    help: str
    args: tuple[Arg, ...]
    entry: tuple[str, ...]
    params: dict[str, tuple[str, ...]] = field(default_factory=dict)
    rules: tuple[str, ...] = ()
    kernels: bool = True
    spin: bool = False

    @property
    def module(self) -> str:
        """The module holding the command's ``run(args)``."""
        return f"{__package__}.{self.command.replace('-', '_')}"


# The lifting methods (a variant's `lifting`, the lift step's `method`) and their parameter dataclasses.
LIFT_METHODS = {
    "contrastive": "trace3d.lifting.contrastive:ContrastiveParams",
    "self_prompt": "trace3d.lifting.self_prompt:SelfPromptParams",
    "labels": "trace3d.lifting.labels:LabelsParams",
}
IMPORTERS = {  # `trace3d scene <kind>`: kind -> the parameter dataclass of its importer
    "replica": "trace3d.datasets.replica:ReplicaParams",
    "nvos": "trace3d.datasets.llff:LLFFParams",
    "llff": "trace3d.datasets.llff:LLFFParams",
    "images": "trace3d.datasets.images:ImagesParams",
    "transforms": "trace3d.datasets.transforms:TransformsParams",
}
SCENE_KINDS = ("synthetic", "replica", "nvos", "llff", "canonical", "images", "transforms")
# The ground truth a kind's scene folder holds: "objects" (instance maps and objects.json: the evaluate
# step scores it), "nvos" (NVOS's target-view masks: evaluate-nvos), None (a user's photos or capture,
# LLFF: the segment step separates its objects without ground truth); a canonical folder holds objects
# when it has instances/ (the rules look).
GROUND_TRUTH = {"synthetic": "objects", "replica": "objects", "nvos": "nvos", "llff": None, "images": None,
                "transforms": None, "canonical": "objects if instances/"}
# The mask sources that render the 2DGS fit (the masks step then takes --gaussians and --poses, and its rule
# depends on the fit); trace3d.masks.FITTED_SOURCES is the same tuple (tests/masks/test_geometry.py).
FITTED_MASK_SOURCES = ("geometry",)
# The simulated masks' default inconsistency (a room "already has" this level: rules/common.smk).
SIMULATE_PARAMS = "trace3d.masks.simulate:SimulateParams"

_SCENE = arg("--scene", required=True)
_POSES = arg("--poses", help="poses folder whose cameras the fitted scene lives with")
_OUT = arg("--out", required=True)
_LABEL = arg("--label", help="JSON mapping copied into metrics.json as \"variant\" (name and settings)")
_LIFTED_GAUSSIANS = arg("--gaussians", required=True, help="the Gaussians the lifting used (point_cloud.ply)")

STEPS: tuple[Step, ...] = (
    Step("scene", "build a canonical scene folder (synthetic room or an importer)",
         (arg("kind", choices=list(SCENE_KINDS)),
          arg("--out", required=True, help="output scene folder"),
          arg("--source", help="data set folder (importers only; images: a folder of photos; transforms: "
                               "the folder of a transforms.json capture, or the .json file)"),
          params_arg()),
         ("trace3d.datasets.synthetic:generate_scene", "trace3d.datasets.replica:import_replica",
          "trace3d.datasets.llff:import_nvos", "trace3d.datasets.llff:import_llff",
          "trace3d.datasets.images:import_images", "trace3d.datasets.transforms:import_transforms"),
         {"synthetic": ("trace3d.datasets.synthetic.params:SyntheticParams",),
          "importer": tuple(dict.fromkeys(IMPORTERS.values()))},
         rules=("scene",)),
    Step("masks", "2D instance masks per view (simulated | files | sam | graph | geometry)",
         (_SCENE, _OUT,
          arg("--source", default="simulated", choices=["simulated", "files", "sam", "graph", "geometry"]),
          params_arg(),
          arg("--gaussians", help="geometry source: the 2DGS fit's folder (point_cloud.ply) whose depth and normals "
                                  "it renders"),
          _POSES),
         ("trace3d.masks:run_masks",), rules=("masks",)),
    Step("masks-stats", "statistics of a masks folder (calibration: docs/masks_calibration.md)",
         (_SCENE, arg("--masks", required=True, help="a `trace3d masks` output folder"),
          arg("--patch-params", help="patch step parameters for the patch statistics (" + PARAMS_HELP + ")"),
          arg("--out", help="also write the statistics to this JSON file")),
         ("trace3d.masks.stats:scene_statistics",)),
    Step("patches", "overlap masks into disjoint primitive patches + hierarchy",
         (_SCENE, arg("--masks", required=True), _OUT, params_arg()),
         ("trace3d.masks.patches:run_patches",), {"patches": ("trace3d.masks.patches:PatchParams",)},
         rules=("patches",)),
    Step("overlay", "overlay each view's masks into one label per pixel (baselines without patches)",
         (_SCENE, arg("--masks", required=True), _OUT),
         ("trace3d.masks.overlay:run_overlay",), rules=("overlay",)),
    Step("poses", "camera poses by pycolmap structure-from-motion (or the data set's)",
         (_SCENE, _OUT, params_arg()),
         ("trace3d.poses.step:run_poses",), {"poses": ("trace3d.poses.params:PosesParams",)}, rules=("poses",)),
    Step("gaussians", "fit a 2D Gaussian Splatting scene",
         (_SCENE, arg("--poses", help="poses folder (cameras.json, points3D.ply); default: the scene's cameras"),
          _OUT, params_arg()),
         ("trace3d.training.step:run_gaussians",), {"gaussians": ("trace3d.training.params:TrainParams",)},
         rules=("gaussians",)),
    Step("trace", "GIT: trace every training view's label map through the fitted scene",
         (_SCENE, _POSES, arg("--gaussians", required=True, help="fitted scene folder (point_cloud.ply)"),
          arg("--labels", required=True, help="label maps <frame>.png (16-bit): the patches folder"),
          _OUT, params_arg()),
         ("trace3d.tracing.git:run_trace",), {"trace": ("trace3d.tracing.git:TraceParams",)}, rules=("trace",)),
    Step("merge", "consistent instance maps: merge patches by majority vote over views",
         (_SCENE, arg("--git", required=True, help="trace step folder (git.npz)"),
          arg("--patches", required=True, help="patches folder (maps and hierarchy JSON)"), _OUT, params_arg()),
         ("trace3d.tracing.merge:run_merge",), {"merge": ("trace3d.tracing.merge:MergeParams",)},
         rules=("merge", "merge_variant")),
    Step("refine", "GIT-guided density control: split / prune ambiguous Gaussians while retraining",
         (_SCENE, _POSES, arg("--gaussians", required=True, help="fitted scene folder (point_cloud.ply, config.json)"),
          arg("--labels", required=True, help="instance maps <frame>.png: merge/instances (or raw patches)"),
          _OUT, params_arg()),
         ("trace3d.tracing.refine:run_refine",), {"refine": ("trace3d.tracing.refine:RefineParams",)},
         rules=("refine",)),
    Step("evaluate", "3D object extraction and novel-view segmentation of a lifted scene",
         (_SCENE, _POSES, _LIFTED_GAUSSIANS,
          arg("--lift", required=True, help="lift step folder (lift.json names the method)"),
          _OUT, params_arg(), _LABEL,
          arg("--objects", help="folder for the objects' PLY + turntable files (default: <out>/objects)")),
         ("trace3d.evaluation.step:run_evaluate",), {"evaluate": ("trace3d.evaluation.params:EvaluateParams",)},
         rules=("evaluate", "evaluate_official")),
    Step("evaluate-nvos", "NVOS (Table 4): scribbles on the reference view -> the target view's mask",
         (arg("--scene", required=True, help="an NVOS scene folder (trace3d scene nvos)"), _POSES, _LIFTED_GAUSSIANS,
          arg("--lift", required=True, help="lift step folder"),
          arg("--labels", required=True,
              help="the instance maps the lifting used (the scribbles select instances there)"),
          _OUT, _LABEL),
         ("trace3d.evaluation.nvos:run_evaluate_nvos",), rules=("evaluate_nvos",)),
    Step("tables", "paper-layout Tables 2, 3 and 5 from results/<scene>/<variant>/eval/metrics.json",
         (arg("--results", required=True, help="results folder"),
          arg("--out", required=True, help="output folder (results/tables)"),
          arg("--evals", nargs="+", help="only these evaluate folders (<results>/<scene>/<variant>/eval)")),
         ("trace3d.report.tables:write_tables",),
         rules=("tables", "tables_paper_rows", "tables_official", "tables_nvos"),
         kernels=False),
    Step("robustness", "object / NVS mIoU per variant against the simulated mask inconsistency",
         (arg("--spec", required=True,
              help="JSON/YAML (or @file): {runs: [{scene, level, variant, eval}], merges: [{scene, level, merge}]}"),
          arg("--out", required=True, help="Markdown table (results/tables/robustness.md; a CSV beside it)"),
          arg("--plot", help="PNG of the curves (results/plots/robustness.png)")),
         ("trace3d.report.robustness:write_robustness",), rules=("robustness",), kernels=False),
    Step("effects", "every variant under every mask model and seed: 95 %% CIs, paired effects, "
                    "share of the raw-to-oracle gap",
         (arg("--spec", required=True,
              help="JSON/YAML (or @file): {runs: [{room, masks, variant, seed, eval}], oracle: [variants], raw}"),
          arg("--out", required=True, help="Markdown table (results/tables/effects.md; CSVs beside it)"),
          arg("--plot", help="PNG of the means and intervals (results/plots/effects.png)")),
         ("trace3d.report.effects:write_effects",), rules=("effects",)),
    Step("lift", "lift the instance maps into the scene: contrastive features or self-prompting",
         (_SCENE, _POSES, arg("--gaussians", required=True, help="fitted (or refined) scene folder (point_cloud.ply)"),
          arg("--labels", help="instance maps <frame>.png (16-bit, 0 = unlabelled): merge/instances or patches"),
          _OUT, params_arg("method: contrastive | self_prompt, preset: paper | official")),
         ("trace3d.lifting.step:run_lift",), {"lift": tuple(LIFT_METHODS.values())}, rules=("lift",), spin=True),
    Step("extract", "one object out by a click: its Gaussians (PLY) and renders, from a contrastive lift",
         (_SCENE, _POSES, _LIFTED_GAUSSIANS,
          arg("--lift", required=True, help="contrastive lift folder (features.npy, lift.json)"),
          arg("--view", help="the training view clicked on (frame name)"),
          arg("--point", metavar="X,Y", help="the clicked pixel: column,row of the view's image (0-based)"),
          arg("--out", required=True, help="output folder: object.ply, object.png, turntable.png, extract.json"),
          params_arg("view, point: [x, y], selection: features | segment | region, threshold, ...; the flags win")),
         ("trace3d.extract:run_extract",)),
    Step("segment", "the objects a contrastive lift separates, without ground truth: per-object PLYs, "
                    "turntable renders and a contact sheet",
         (_SCENE, _POSES, _LIFTED_GAUSSIANS,
          arg("--lift", required=True, help="contrastive lift folder (features.npy, lift.json)"),
          arg("--out", required=True, help="output folder: objects/<k>.ply, objects/<k>.png, contact_sheet.png, "
                                           "segment.json"),
          params_arg("method: graph | hdbscan_graph | features, neighbours, threshold_scale, min_share, "
                     "min_size, ...")),
         ("trace3d.segment:run_segment",), {"segment": ("trace3d.segment:SegmentParams",)}, rules=("segment",)),
    Step("summary", "write the per-scene summary table (results/scenes.md)",
         (arg("scenes", nargs="+", help="scene folders"), arg("--out", required=True)),
         ("trace3d.report.summary:write_scene_table",), rules=("scenes_table",), kernels=False),
    Step("reconstruction-table", "write the reconstruction table (poses + 2DGS fit per scene)",
         (arg("--poses", nargs="+", required=True, help="poses folders, one per scene"),
          arg("--gaussians", nargs="+", required=True, help="gaussians folders, same order"),
          arg("--out", required=True, help="Markdown table (a CSV is written beside it)"),
          arg("--plot", help="PNG bar plot of test PSNR and minutes per scene")),
         ("trace3d.report.summary:write_reconstruction_table",), rules=("reconstruction_table",), kernels=False),
    Step("tracing-table", "write the merge / refine table (results/tracing.md)",
         (arg("--merge", nargs="+", required=True, help="merge folders, one per scene"),
          arg("--refine", nargs="+", help="refine folders, same order"),
          arg("--out", required=True, help="Markdown table (a CSV is written beside it)"),
          arg("--plot", help="PNG bars of the merge quality before / after")),
         ("trace3d.report.tracing:write_tracing_table",), rules=("tracing_table",), kernels=False),
    Step("scale-table", "every step's CPU time and peak memory at two scene sizes, and their growth with "
                        "views x pixels (docs/scale.md)",
         (arg("--results", required=True, help="results folder holding benchmarks/<scene>/ and <scene>/scene/ "
                                               "(config/scale.yaml: results/scale)"),
          arg("--small", required=True, help="the smaller scene's name (s320)"),
          arg("--large", required=True, help="the larger scene's name (s640)"),
          arg("--out", required=True, help="Markdown table (docs/bench/scale.md; a CSV is written beside it)")),
         ("trace3d.report.scale:write_scale_table",), kernels=False),
)
BY_COMMAND = {s.command: s for s in STEPS}
BY_RULE = {rule: s for s in STEPS for rule in s.rules}


def step(command: str) -> Step:
    return BY_COMMAND[command]


def handler(command: str):
    """The ``run(args)`` of a command (imports its module, which imports no heavy library at load)."""
    return importlib.import_module(step(command).module).run


# ----------------------------------------------------------------------------------------------
# variants: the rows of an ablation (config `variants`)
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Variant:
    """A variant's settings of the paper's stages (config ``variants.<name>``).

    preset: the paper's values or the released code's (trace, merge, refine).
    consistent_masks: merge patches into consistent instance maps (off = later stages use the raw patches).
    density_control: GIT-guided split / prune while retraining (off = later stages use the plain 2DGS fit).
    lifting: how the instance maps are lifted: contrastive features, per-query self-prompting, or labels
        (closed-form per-Gaussian label assignment, the FlashSplat-style baseline; needs ids consistent
        across views).
    overlay: lift on each view's masks painted into one label per pixel (smallest on top) instead of
        patches: the EgoLifter-style baseline; needs consistent_masks and density_control false.
    merge_candidates: which patch pairs of a view the merge compares: those inside a common coarser mask
        (the supplementary) or all pairs (the paper's main text).
    merge_method: the paper's argmax-patch vote, the hierarchical merge (beyond the paper: the mask-level
        vote over every pair, average linkage; trace3d/tracing/consistency.py) or the released code's merge
        (the official preset's merge keys on conflict areas, greedy grouping) on the variant's own trace.
    merge_threshold: the merge's similarity threshold, when not the preset's (e.g. 0.4, the released
        merge_patches.py's, on the paper preset); its merge folder is merge-<preset>[-all|-hier]-t<threshold>.
    lift: lift step parameters of this variant, merged over the scene's `lift` (e.g. the self-prompting
        variant's prompt_source).
    """

    preset: Literal["paper", "official"] = "paper"
    consistent_masks: bool = True
    density_control: bool = True
    lifting: Literal["contrastive", "self_prompt", "labels"] = "contrastive"
    overlay: bool = False
    merge_candidates: Literal["coarser_mask", "all_pairs"] = "coarser_mask"
    merge_method: Literal["vote", "hierarchical", "released"] = "vote"
    merge_threshold: float | None = None
    lift: dict = field(default_factory=dict)


def variant_defaults() -> dict:
    """The settings a variant takes where the config names none (``lift`` left out: it has no default)."""
    return {f.name: f.default for f in dataclasses.fields(Variant) if f.default is not dataclasses.MISSING}


# ----------------------------------------------------------------------------------------------
# dataclasses read statically (no import) and imported
# ----------------------------------------------------------------------------------------------


def _module_file(module: str) -> Path:
    rel = Path(*module.split(".")[1:])
    path = PACKAGE / rel
    return path / "__init__.py" if path.is_dir() else path.with_suffix(".py")


@functools.lru_cache(maxsize=None)
def fields_static(ref: str) -> tuple[tuple[str, Any], ...]:
    """((field name, default), ...) of the dataclass ``module:Class``, read from its source without
    importing it; a default that is not a literal (a ``field(default_factory=...)``) reads as ``...``.
    Only fields written in the class body itself (the step dataclasses do not inherit)."""
    module, name = ref.split(":")
    tree = ast.parse(_module_file(module).read_text())
    for node in tree.body:
        if isinstance(node, ast.ClassDef) and node.name == name:
            out = []
            for item in node.body:
                if isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name):
                    if "ClassVar" in ast.unparse(item.annotation):
                        continue
                    try:
                        default = ast.literal_eval(item.value) if item.value is not None else dataclasses.MISSING
                    except ValueError:
                        default = ...
                    out.append((item.target.id, default))
            return tuple(out)
    raise LookupError(f"{ref}: no class {name} in {_module_file(module)}")


def load_class(ref: str) -> type:
    module, name = ref.split(":")
    return getattr(importlib.import_module(module), name)


def lift_keys() -> dict[str, tuple[str, ...]]:
    """Lifting method -> the lift parameters it takes (the fields of its dataclass), read statically."""
    return {method: tuple(name for name, _ in fields_static(ref)) for method, ref in LIFT_METHODS.items()}


def lift_params_for(method: str, params: dict) -> dict:
    """The lift parameters of ``method`` out of a mapping that may hold several methods' keys (a shared
    ``lift`` block): a key that belongs to another method only is dropped, every other key kept (an
    unknown one is the library's to refuse); ``method`` set."""
    keys = lift_keys()
    others = {k for m, names in keys.items() if m != method for k in names} - set(keys[method])
    out = {k: v for k, v in params.items() if k not in others}
    out["method"] = method
    return out


def default_inconsistency() -> float:
    """The simulated masks' default inconsistency (:class:`trace3d.masks.simulate.SimulateParams`)."""
    return float(dict(fields_static(SIMULATE_PARAMS))["inconsistency"])
