# Shared helpers: config validation, per-scene parameter merging, code-version hashes.
import json
import os
import re
import shlex
import shutil
import sys
from pathlib import Path

import yaml
from snakemake.logging import logger
from snakemake.utils import validate

PACKAGE = Path(workflow.basedir) / "trace3d"

# The library's step registry (trace3d.steps: lift methods' keys, variant defaults) and the code hashes
# derived from its import graph (trace3d.tooling.codehash): both read the checkout's sources statically, so
# the Snakemake process imports neither torch nor numba.
if sys.path[:1] != [str(workflow.basedir)]:
    sys.path.insert(0, str(workflow.basedir))
import trace3d.tooling.codehash as _codehash
import trace3d.steps as _steps

if Path(_steps.__file__).resolve().parent.parent != PACKAGE.resolve():
    raise ValueError(f"rules/common.smk: imported the step registry from {_steps.__file__}, not from this "
                     f"checkout's {PACKAGE}; another trace3d is imported first.")


# --- checks made before the config is used: one sentence instead of a traceback -----------------
def _duplicate_key(path):
    """The first key given twice in one mapping of the YAML file ``path`` (PyYAML keeps the last one
    silently), as a sentence; None when there is none."""
    with open(path) as fh:
        try:
            root = yaml.compose(fh, Loader=yaml.SafeLoader)
        except yaml.YAMLError:
            return None  # Snakemake reports a malformed file itself
    stack = [root] if root is not None else []
    while stack:
        node = stack.pop()
        if isinstance(node, yaml.MappingNode):
            seen = {}
            for key, value in node.value:
                if isinstance(key, yaml.ScalarNode):
                    line = key.start_mark.line + 1
                    if key.value in seen:
                        return (f"config {path}: key '{key.value}' appears twice in one mapping (lines "
                                f"{seen[key.value]} and {line}); YAML would silently keep the second, so keep one.")
                    seen[key.value] = line
                stack.append(value)
        elif isinstance(node, yaml.SequenceNode):
            stack.extend(node.value)
    return None


for _path in map(str, workflow.configfiles):
    if os.path.isfile(_path) and (_message := _duplicate_key(_path)):
        raise ValueError(_message)


# Snakemake 9.14.5 crashes with "AttributeError - 'str' object has no attribute 'is_storage'" on a
# target that nothing produces (a misspelled scene or variant): its MissingRuleException formats the
# command-line target, a plain string, with snakemake.io.fmt.fmt_iofile, which expects an IOFile.
# Formatting plain strings as themselves restores its ordinary "No rule to produce <target>" message.
import snakemake.io.fmt as _snakemake_fmt

if not getattr(_snakemake_fmt.fmt_iofile, "_trace3d_accepts_str", False):
    _fmt_iofile = _snakemake_fmt.fmt_iofile

    def _fmt_iofile_or_str(f, *args, **kwargs):
        return _fmt_iofile(f, *args, **kwargs) if hasattr(f, "is_storage") else str(f)

    _fmt_iofile_or_str._trace3d_accepts_str = True
    _snakemake_fmt.fmt_iofile = _fmt_iofile_or_str


# Every job runs `trace3d`: without it on PATH each would fail with "command not found" in its log.
def _trace3d_missing():
    from snakemake_interface_executor_plugins.settings import DeploymentMethod

    if DeploymentMethod.CONDA in workflow.deployment_settings.deployment_method:
        return False  # the jobs' conda environment (workflow/envs/trace3d.yaml) provides it
    return shutil.which("trace3d") is None


if _trace3d_missing():
    logger.warning("The trace3d command is not on PATH, so every job would fail with 'trace3d: command not found': "
                   "activate the environment first (source .venv/bin/activate, after `make setup`), use "
                   "`make reproduce`, or run with --use-conda.")


validate(config, schema="../workflow/schemas/config.schema.yaml")

RESULTS = config.get("results", "results")
SCENES = sorted(config["scenes"])
# Scenes whose importer writes ground-truth instance maps and objects: the evaluate step scores them.
# (NVOS's target-view masks have their own protocol, below; a user's photos have no ground truth.)
EVAL_KINDS = tuple(k for k, truth in _steps.GROUND_TRUTH.items() if truth == "objects")
EVAL_SCENES = [s for s in SCENES if config["scenes"][s]["kind"] in EVAL_KINDS]


# Scenes with no ground truth at all (a user's photos or transforms.json, LLFF, a canonical scene without
# instances/): `reproduce` segments them into the objects the contrastive lift separates (rules/segment.smk).
def _without_ground_truth(name):
    cfg = config["scenes"][name]
    if _steps.GROUND_TRUTH[cfg["kind"]] is None:
        return True
    if cfg["kind"] == "canonical":
        return not os.path.isdir(os.path.join(config.get("data_root", "."), cfg["source"], "instances"))
    return False


SEGMENT_SCENES = [s for s in SCENES if _without_ground_truth(s)]
# NVOS scenes: scribbles on a reference view -> the target view's mask (rule evaluate_nvos, Table 4).
NVOS_SCENES = [s for s in SCENES if _steps.GROUND_TRUTH[config["scenes"][s]["kind"]] == "nvos"]
ENV = "../workflow/envs/trace3d.yaml"
# Process settings of every job (the shell commands inherit Snakemake's environment), made here
# because importing trace3d makes none: sleeping OpenMP waits (spinning workers steal the cores the
# numba kernels need, docs/performance.md) and numba's compile cache in the checkout, so that only the
# first job compiles.  Values already in the environment (e.g. from the Makefile) are respected.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("NUMBA_CACHE_DIR", str(Path(workflow.basedir) / ".numba_cache"))

# Scenes read from a data set need their folder before any job starts: one sentence, not a failed job.
def _check_sources():
    root = config.get("data_root", ".")
    for name, cfg in config["scenes"].items():
        if cfg["kind"] == "synthetic":
            continue
        source = os.path.normpath(os.path.join(root, cfg["source"]))
        if not os.path.isdir(root):
            raise ValueError(f"config data_root: {root} does not exist; set data_root to the folder that holds "
                             f"the data set (scene '{name}' reads its {cfg['kind']} data from it, docs/datasets.md).")
        if not os.path.exists(source):
            raise ValueError(f"config scenes.{name}.source: {source} does not exist (data_root {root} + source "
                             f"{cfg['source']}); docs/datasets.md shows the expected layout.")


_check_sources()


def deep_merge(base, override):
    """Mapping ``override`` merged over ``base`` key by key (nested mappings merged too)."""
    out = dict(base)
    for key, value in (override or {}).items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = value
    return out


def scene_config(scene):
    if scene in DERIVED:
        base, masks = DERIVED[scene]
        extra = {"masks": masks}
        if scene in MODEL_PATCHES:  # a mask model's own patch settings
            extra["patches"] = MODEL_PATCHES[scene]
        if scene in FITTED:  # a fit seed: the room's own settings with the fit's seed
            extra["gaussians"] = {"seed": FITTED[scene]}
        return deep_merge(config["scenes"][base], extra)
    return config["scenes"][scene]


# --- robustness: a room again under other simulated mask-inconsistency levels -----------------
# A level is a derived scene `<room>@inc<level>` that shares the room's scene, poses and 2DGS fit
# (its rules read the base room's folders; no copy, no refit) and runs its own masks, patches, trace,
# merge, refine, overlay, lift and evaluate with `masks: {simulated: {inconsistency: level}}`. The level
# the room already has is the room itself; where the config names none, the library's default
# (trace3d.masks.simulate.SimulateParams.inconsistency).
SIMULATED_DEFAULT_INCONSISTENCY = _steps.default_inconsistency()
ROBUSTNESS = config.get("robustness") or {}
DERIVED = {}  # derived scene name -> (base scene, the masks settings merged over the base scene's)


def base_scene(scene):
    """The scene whose scene/poses/gaussians folders ``scene`` uses (itself unless derived)."""
    return DERIVED[scene][0] if scene in DERIVED else scene


def _own_masks(base):
    """A configured scene's masks settings: the defaults' merged with its own."""
    return deep_merge(config.get("defaults", {}).get("masks", {}), config["scenes"][base].get("masks", {}))


def robustness_scene(base, level):
    """The scene that holds ``base`` at mask inconsistency ``level``: ``base`` itself at its own level."""
    masks = _own_masks(base)
    own = masks.get("simulated", {}).get("inconsistency", SIMULATED_DEFAULT_INCONSISTENCY)
    return base if float(level) == float(own) else f"{base}@inc{float(level):g}"


for _base in ROBUSTNESS.get("scenes", []):
    if _base not in config["scenes"]:
        raise ValueError(f"config robustness.scenes: '{_base}' is not one of the config's scenes.")
    _masks = _own_masks(_base)
    if _masks.get("source", "simulated") != "simulated":
        raise ValueError(f"config robustness.scenes: '{_base}' takes its masks from '{_masks['source']}'; "
                         f"the robustness curve varies the simulated masks' inconsistency, so it needs "
                         f"masks.source: simulated.")
    for _level in ROBUSTNESS.get("levels", []):
        _name = robustness_scene(_base, _level)
        if _name != _base:
            DERIVED[_name] = (_base, {"simulated": {"inconsistency": float(_level)}})


# --- mask models and the oracle: the same rooms under other 2D masks ----------------------------
# `mask_models: {<model>: {masks: {...}, patches: {...}, variants: [...]}}` adds, for every scene with
# ground truth, a derived scene `<room>@<model>` whose masks settings are `masks` merged over the room's
# own, and whose patch settings `patches` (optional) over the room's (its scene, poses and 2DGS fit are
# the room's), and runs `variants` on it.  `oracle: {variants: [...]}`
# runs those variants on exact object masks: the room at simulated inconsistency 0 (`<room>@inc0`,
# shared with the robustness curve), the upper end of every "share of the raw-to-oracle gap" figure.
MASK_MODELS = config.get("mask_models") or {}
ORACLE = config.get("oracle") or {}


MODEL_PATCHES = {}  # derived scene -> a mask model's own patch settings


for _model, _spec in MASK_MODELS.items():
    for _base in SCENES:
        if config["scenes"][_base]["kind"] in EVAL_KINDS:
            DERIVED[f"{_base}@{_model}"] = (_base, _spec.get("masks") or {})
            if _spec.get("patches"):
                MODEL_PATCHES[f"{_base}@{_model}"] = _spec["patches"]


def oracle_scene(base):
    """The scene holding ``base`` with exact object masks (simulated at inconsistency 0)."""
    return robustness_scene(base, 0.0)


if ORACLE.get("variants"):
    for _base in SCENES:
        if config["scenes"][_base]["kind"] not in EVAL_KINDS:
            continue
        if _own_masks(_base).get("source", "simulated") != "simulated":
            raise ValueError(f"config oracle: scene '{_base}' takes its masks from '{_own_masks(_base)['source']}'; "
                             f"the oracle's exact object masks are the simulated source at inconsistency 0, so the "
                             f"scene needs masks.source: simulated (other mask models go under mask_models).")
        _name = oracle_scene(_base)
        if _name != _base:
            DERIVED[_name] = (_base, {"simulated": {"inconsistency": 0.0}})

# --- fit seeds: `fit_seeds: {values: [0, 1], variants: [...]}` ----------------------------------------
# The 2DGS fit differs with its seed (and with the CPU kind: docs/performance.md), and PQ^scene per room
# moves with it, so a fit seed other than 0 is a derived scene `<room>.fit<seed>`: the room's scene and
# poses, its own masks and patches (the same settings, so the same maps), its own fit with
# `gaussians: {seed: <seed>}` and everything after it, for the variants `fit_seeds.variants` lists (at
# every lift seed of `seeds`). The study's intervals then sample rooms x fits x lift seeds.
FIT_SEEDS = config.get("fit_seeds") or {}
FITTED = {}  # fit-seed scene -> its fit seed
for _name in FIT_SEEDS.get("variants", []):
    if _name not in config.get("variants", {"full": {}}):
        raise ValueError(f"config fit_seeds.variants: '{_name}' is not one of the config's variants "
                         f"({', '.join(config.get('variants', {'full': {}}))}).")
for _base in SCENES:
    if config["scenes"][_base]["kind"] not in EVAL_KINDS or not FIT_SEEDS.get("variants"):
        continue
    for _seed in FIT_SEEDS.get("values", [0]):
        if int(_seed) < 0:
            raise ValueError(f"config fit_seeds.values: {_seed} is negative; fit seeds are integers >= 0.")
        if int(_seed) != 0:
            DERIVED[f"{_base}.fit{int(_seed)}"] = (_base, {})
            FITTED[f"{_base}.fit{int(_seed)}"] = int(_seed)


def fit_scene(scene):
    """The scene whose 2DGS fit ``scene`` uses: a fit-seed scene's own, else its base's."""
    return scene if scene in FITTED else base_scene(scene)


ALL_SCENES = SCENES + sorted(DERIVED)
# scene and poses exist for the configured scenes only (derived ones read their base's); gaussians for
# them and the fit-seed scenes.
BASE_SCENE_PATTERN = "|".join(re.escape(s) for s in SCENES)
FIT_SCENE_PATTERN = "|".join(re.escape(s) for s in SCENES + sorted(FITTED))


wildcard_constraints:
    scene="|".join(re.escape(s) for s in ALL_SCENES),


def base_folder(step):
    """An input function: the base scene's ``step`` folder (scene | poses | gaussians)."""

    def inner(wildcards):
        scene = fit_scene(wildcards.scene) if step == "gaussians" else base_scene(wildcards.scene)
        return f"{RESULTS}/{scene}/{step}"

    return inner


def step_params(scene, step):
    """The parameter mapping of ``step`` for ``scene``: defaults, then the scene's own entries."""
    merged = deep_merge(config.get("defaults", {}).get(step, {}), scene_config(scene).get(step, {}))
    return json.dumps(merged, sort_keys=True)


def step_code(command):
    """The code version of the ``trace3d <command>`` step: a hash of the library modules it imports,
    found from the import graph (trace3d.tooling.codehash), so that Snakemake reruns the step when one changes."""
    return _codehash.step_hash(command, PACKAGE)


def scene_kind_args(wildcards):
    """The `trace3d scene` arguments for a scene: its kind, data source and parameters."""
    cfg = scene_config(wildcards.scene)
    kind = cfg["kind"]
    if kind == "synthetic":
        params = shlex.quote(step_params(wildcards.scene, "synthetic"))
        return f"synthetic --params {params}"
    params = shlex.quote(step_params(wildcards.scene, "importer"))
    source = os.path.join(config.get("data_root", "."), cfg["source"])
    return f"{kind} --source {shlex.quote(os.path.normpath(source))} --params {params}"


# the mask sources that render the 2DGS fit: their masks need the gaussians
FITTED_MASK_SOURCES = _steps.FITTED_MASK_SOURCES


def mask_inputs(wildcards):
    """The masks rule's inputs: the scene; for a source that renders the fit, also the gaussians and poses."""
    inputs = {"scene": base_folder("scene")(wildcards)}
    if mask_source(wildcards) in FITTED_MASK_SOURCES:
        inputs["gaussians"] = base_folder("gaussians")(wildcards)
        inputs["poses"] = base_folder("poses")(wildcards)
    return inputs


def mask_args(wildcards):
    """The `trace3d masks` arguments: the mask source and that source's parameters (and the fit it renders)."""
    merged = json.loads(step_params(wildcards.scene, "masks"))
    source = merged.get("source", "simulated")
    params = shlex.quote(json.dumps(merged.get(source, {}), sort_keys=True))
    fitted = ""
    if source in FITTED_MASK_SOURCES:
        inputs = mask_inputs(wildcards)
        fitted = f" --gaussians {shlex.quote(inputs['gaussians'])} --poses {shlex.quote(inputs['poses'])}"
    return f"--source {source} --params {params}{fitted}"


def mask_source(wildcards):
    """The scene's mask source (simulated | files | sam | graph | geometry): SAM needs more threads, memory and time
    (graph: one thread, under a second per 160x120 view)."""
    return json.loads(step_params(wildcards.scene, "masks")).get("source", "simulated")


def quoted_params(step):
    """A params function returning the step's parameters as one shell-quoted JSON word."""

    def inner(wildcards):
        return shlex.quote(step_params(wildcards.scene, step))

    return inner


# --- variants: the rows of an ablation ------------------------------------------------------
# A variant names the settings of the paper's stages. Each step's output path carries only the
# settings that step depends on, so variants that agree up to a step share its folder (and
# Snakemake runs it once); a switched-off step is skipped by pointing the next step at its input.
#   trace   results/<scene>/trace-<preset>/            (GIT of the raw patches: git.npz)
#   merge   results/<scene>/merge-<preset>/instances/  (consistent instance maps)
#   refine  results/<scene>/refine-<preset>-<masks>/   (masks: merged | patches)
#   lift    results/<scene>/<variant>/lift/             (lifting: contrastive | self_prompt)
#   later   results/<scene>/<variant>/...              (evaluation: per variant)
#   overlay: lift on each view's masks painted into one label per pixel (no patches, no merge, no
#   refine: the EgoLifter-style baseline); it excludes consistent_masks and density_control.
VARIANT_DEFAULTS = _steps.variant_defaults()  # trace3d.steps.Variant
# merge_candidates: which patch pairs of a view the merge compares: those inside a common coarser mask
# (the supplementary; folder merge-<preset>) or all pairs (the paper's main text; folder merge-<preset>-all,
# refine-<preset>-mergedall); merge_method: the paper's vote or the hierarchical merge (beyond the paper;
# folder merge-<preset>-hier, refine-<preset>-mergedhier); merge_threshold: a threshold other than the
# preset's (folder merge-<preset>[-all|-hier]-t<threshold>, refine-<preset>-merged[all|hier]-t<threshold>).
VARIANTS = {name: {**VARIANT_DEFAULTS, **(v or {})} for name, v in config.get("variants", {"full": {}}).items()}
# A variant's own `lift:` settings (e.g. the self-prompting prompt source) join the scene's lift params.
for _name, _v in VARIANTS.items():
    if _v["overlay"] and (_v["consistent_masks"] or _v["density_control"]):
        raise ValueError(f"config variants.{_name}: overlay: true lifts the overlaid masks directly, so it needs "
                         f"consistent_masks: false and density_control: false.")


for _name in ROBUSTNESS.get("variants", []):
    if _name not in VARIANTS:
        raise ValueError(f"config robustness.variants: '{_name}' is not one of the config's variants "
                         f"({', '.join(VARIANTS)}).")


for _model, _spec in MASK_MODELS.items():
    for _name in _spec.get("variants", []):
        if _name not in VARIANTS:
            raise ValueError(f"config mask_models.{_model}.variants: '{_name}' is not one of the config's variants "
                             f"({', '.join(VARIANTS)}).")
for _name in ORACLE.get("variants", []):
    if _name not in VARIANTS:
        raise ValueError(f"config oracle.variants: '{_name}' is not one of the config's variants ({', '.join(VARIANTS)}).")

# The paper's own rows (`paper_rows:`, default every variant): Tables 2, 3 and 5 of these alone are written
# first (rule tables_paper_rows, target paper_tables), so that `make reproduce` shows them before the jobs of
# the variants beyond the paper.
PAPER_ROWS = list(config.get("paper_rows") or VARIANTS)
for _name in PAPER_ROWS:
    if _name not in VARIANTS:
        raise ValueError(f"config paper_rows: '{_name}' is not one of the config's variants ({', '.join(VARIANTS)}).")

# --- lift seeds: `seeds: {values: [0, 1, 2], variants: [...]}` --------------------------------------
# A seed other than 0 is a run of its own, `<variant>.s<seed>` (results/<scene>/full.s1/lift, eval, ...),
# with the lift's `seed` set to it; seed 0 keeps the variant's plain folder.  Only the lift (and what
# follows it) depends on the seed, so the seeds share every step before it.
SEEDS = config.get("seeds") or {}
SEED_VALUES = [int(s) for s in SEEDS.get("values", [0])]
for _name in SEEDS.get("variants", []):
    if _name not in VARIANTS:
        raise ValueError(f"config seeds.variants: '{_name}' is not one of the config's variants ({', '.join(VARIANTS)}).")


def variant_runs(names):
    """The run names (variant folders) of ``names``: each at seed 0, and at every seed of `seeds` for
    the variants that `seeds.variants` lists."""
    out = []
    for name in names:
        seeds = SEED_VALUES if name in SEEDS.get("variants", []) else [0]
        for seed in sorted(set(seeds) | {0}):
            out.append(name if seed == 0 else f"{name}.s{seed}")
    return out


def split_run(run):
    """(variant name, lift seed) of a run folder name (``full`` -> (full, 0); ``full.s2`` -> (full, 2))."""
    name, _, seed = run.partition(".s")
    return name, int(seed) if seed else 0


wildcard_constraints:
    preset="paper|official",
    masks=r"merged(all|hier|released)?(-t[0-9]+(\.[0-9]+)?)?|patches",
    mtag=r"(-all|-hier|-released)(-t[0-9]+(\.[0-9]+)?)?|-t[0-9]+(\.[0-9]+)?",
    variant=f"({'|'.join(VARIANTS)})" r"(\.s[0-9]+)?",


def variant(name):
    return VARIANTS[split_run(name)[0]]


def run_label(run):
    """What an evaluation writes into metrics.json about its run: variant name, settings, lift seed."""
    name, seed = split_run(run)
    return {"variant": name, **VARIANTS[name], "seed": seed}


def scene_runs():
    """Every (scene, run) that `reproduce` lifts: the config's scenes with all variants (and seeds),
    each mask model's derived scenes with its variants, the oracle scenes with the oracle's variants."""
    pairs = [(s, r) for s in SCENES for r in variant_runs(VARIANTS)]
    for model, spec in MASK_MODELS.items():
        pairs += [(f"{b}@{model}", r) for b in SCENES if f"{b}@{model}" in DERIVED
                  for r in variant_runs(spec.get("variants", []))]
    if ORACLE.get("variants"):
        pairs += [(oracle_scene(b), f"{r}") for b in EVAL_SCENES for r in variant_runs(ORACLE["variants"])]
    pairs += [(s, r) for s in FITTED for r in variant_runs(FIT_SEEDS.get("variants", []))]
    return sorted(set(pairs))


def labels_dir(scene, v):
    """The label maps a variant's later stages use: consistent instance maps, the raw patches, or the
    overlaid masks."""
    if v["overlay"]:
        return f"{RESULTS}/{scene}/overlay"
    if v["consistent_masks"]:
        return f"{RESULTS}/{scene}/merge-{v['preset']}{merge_suffix(v)}"
    return f"{RESULTS}/{scene}/patches"


# A merge flavour other than the preset's own is a folder of its own, merge-<preset>-<flavour> (refine:
# refine-<preset>-merged<flavour>), with these keys over the scene's merge parameters:
MERGE_FLAVOURS = {
    "all": {"candidates": "all_pairs"},  # variant merge_candidates: all_pairs (the paper's main text)
    "hier": {"method": "hierarchical"},  # variant merge_method: hierarchical (beyond the paper)
    # variant merge_method: released: the released code's merge (its vote rules and greedy grouping, the
    # official preset's merge keys, on its conflict areas) on the variant's own trace
    "released": {"preset": "official", "candidates": "conflict_area"},
}


def merge_flavour(v):
    """The variant's merge flavour ('' for the preset's own merge)."""
    if v.get("merge_method") == "hierarchical":
        return "hier"
    if v.get("merge_method") == "released":
        return "released"
    return "all" if v.get("merge_candidates") == "all_pairs" else ""


def merge_suffix(v):
    """What a variant's merge folder carries after merge-<preset>: -all (all pairs) or -hier (the
    hierarchical merge), then -t<threshold> (a threshold other than the preset's)."""
    flavour = merge_flavour(v)
    threshold = v.get("merge_threshold")
    return (f"-{flavour}" if flavour else "") + (f"-t{float(threshold):g}" if threshold is not None else "")


def gaussians_dir(scene, v):
    """The Gaussians a variant's later stages use: refined, or the plain 2DGS fit."""
    if v["density_control"]:
        suffix = merge_suffix(v)
        suffix = suffix[1:] if suffix.startswith(("-all", "-hier", "-released")) else suffix
        masks = f"merged{suffix}" if v["consistent_masks"] else "patches"
        return f"{RESULTS}/{scene}/refine-{v['preset']}-{masks}"
    return f"{RESULTS}/{fit_scene(scene)}/gaussians"


def variant_outputs(scene, v):
    """Every shared-step folder a variant needs (what `reproduce` asks for until lifting exists)."""
    return sorted({labels_dir(scene, v), gaussians_dir(scene, v)})


def preset_params(step):
    """A params function: the step's parameters with the wildcard's preset, one shell-quoted JSON word."""

    def inner(wildcards):
        merged = json.loads(step_params(wildcards.scene, step))
        merged.setdefault("preset", wildcards.preset)
        return shlex.quote(json.dumps(merged, sort_keys=True))

    return inner


def refine_labels(wildcards):
    if wildcards.masks.startswith("merged"):  # merged[all|hier][-t<threshold>] -> merge-<preset>[-all|-hier][-t<threshold>]
        suffix = wildcards.masks[len("merged"):]
        dash = "-" if suffix.startswith(("all", "hier", "released")) else ""
        return f"{RESULTS}/{wildcards.scene}/merge-{wildcards.preset}{dash}{suffix}"
    return f"{RESULTS}/{wildcards.scene}/patches"


def refine_labels_arg(wildcards):
    folder = refine_labels(wildcards)
    return f"{folder}/instances" if wildcards.masks != "patches" else folder


def merge_tag_params(wildcards):
    """The merge step's parameters for merge-<preset><mtag>: the preset's, with the flavour's keys
    (MERGE_FLAVOURS) and the threshold the tag names, if any."""
    merged = json.loads(step_params(wildcards.scene, "merge"))
    merged.setdefault("preset", wildcards.preset)
    flavour, _, threshold = wildcards.mtag.partition("-t")
    if flavour:
        merged.update(MERGE_FLAVOURS[flavour.lstrip("-")])
    if threshold:
        merged["threshold"] = float(threshold)
    return shlex.quote(json.dumps(merged, sort_keys=True))


# The full method's (first variant with both stages on, else the first) merge and refine figures per scene.
def table_variant():
    for name, v in VARIANTS.items():
        if v["consistent_masks"] and v["density_control"] and not merge_suffix(v):
            return v
    return None


# --- lift (rules/lift.smk) ------------------------------------------------------------------
def lift_labels(wildcards):
    return labels_dir(wildcards.scene, variant(wildcards.variant))


def lift_labels_arg(wildcards):
    """The instance maps themselves: a merge folder keeps them in instances/, the patches folder is the maps."""
    v = variant(wildcards.variant)
    folder = labels_dir(wildcards.scene, v)
    return f"{folder}/instances" if v["consistent_masks"] else folder


def lift_params(wildcards):
    v = variant(wildcards.variant)
    merged = deep_merge(json.loads(step_params(wildcards.scene, "lift")), v.get("lift") or {})
    seed = split_run(wildcards.variant)[1]
    if seed:
        merged["seed"] = seed
    merged.setdefault("preset", v["preset"])
    # a shared `lift` block holds several methods' keys: the ones of other methods only do not apply
    # (trace3d.steps.lift_params_for, from the methods' dataclasses)
    merged = _steps.lift_params_for(v["lifting"], merged)
    return shlex.quote(json.dumps(merged, sort_keys=True))


# --- evaluate (rules/evaluate.smk) ------------------------------------------------------------
def evaluate_params(protocol):
    def inner(wildcards):
        merged = json.loads(step_params(wildcards.scene, "evaluate"))
        merged["protocol"] = protocol
        if protocol == "official":  # the objects' files come from the standard evaluation (<variant>/objects)
            merged["object_files"] = False
        return shlex.quote(json.dumps(merged, sort_keys=True))

    return inner


# --- robustness (rules/robustness.smk) -----------------------------------------------------------
def robustness_spec():
    runs, merges = [], []
    consistent = [VARIANTS[n] for n in ROBUSTNESS.get("variants", []) if VARIANTS[n]["consistent_masks"]]
    for base in ROBUSTNESS.get("scenes", []):
        for level in ROBUSTNESS.get("levels", []):
            scene = robustness_scene(base, level)
            for name in ROBUSTNESS.get("variants", []):
                runs.append({"scene": base, "level": float(level), "variant": name,
                             "eval": f"{RESULTS}/{scene}/{name}/eval"})
            if consistent:
                merges.append({"scene": base, "level": float(level),
                               "merge": f"{RESULTS}/{scene}/merge-{consistent[0]['preset']}"})
    return {"runs": runs, "merges": merges}


# --- effects (rules/effects.smk) ------------------------------------------------------------------
def effects_spec():
    """Every scored run beside the main tables' (mask models, oracle, seeds) and the main ones
    themselves: {"runs": [{room, masks, variant, seed, eval}]}; `masks` names the mask model (the
    rooms' own masks: "default"; exact object masks: "oracle")."""
    runs = []
    for scene, run in scene_runs():
        base = base_scene(scene)
        if base not in EVAL_SCENES:
            continue
        if scene == base or scene in FITTED:
            masks = "default"
        elif ORACLE.get("variants") and scene == oracle_scene(base) and split_run(run)[0] in ORACLE["variants"]:
            masks = "oracle"
        else:
            masks = scene.split("@", 1)[1]
        name, seed = split_run(run)
        runs.append({"room": base, "masks": masks, "variant": name, "seed": seed, "fit": FITTED.get(scene, 0),
                     "eval": f"{RESULTS}/{scene}/{run}/eval"})
    if not (MASK_MODELS or ORACLE.get("variants") or SEEDS.get("variants") or FITTED):
        runs = []
    return {"runs": runs, "oracle": list(ORACLE.get("variants", [])), "raw": ORACLE.get("raw", "both_off")}
