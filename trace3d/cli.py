"""``trace3d <step>``: one subcommand per pipeline step, plus ``trace3d bench <name>``.

Thin by design: parse flags, call the library, write outputs atomically (into a temporary sibling
that is renamed at the end).  Errors caused by the input are printed as one sentence and exit 2.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import sys
from pathlib import Path

from .errors import Trace3DError

log = logging.getLogger("trace3d")


# Commands whose inner loop alternates short parallel regions with short serial parts (the lifting's
# fast step: five numba regions in about 2.5 ms): there, waking sleeping workers for every region
# costs about 45 us each, so their workers spin for about half a millisecond before sleeping.
SPIN_COMMANDS = {("lift", None), ("bench", "lift"), ("bench", "lift-forms")}
# Commands that run no numba kernel: no compile listener (trace3d.compiling), so no numba import.
NO_KERNEL_COMMANDS = {"tables", "robustness", "summary", "reconstruction-table", "tracing-table"}


def _entry_point_environment() -> None:
    """Process settings of the ``trace3d`` command, made here rather than on import of the library.

    ``OMP_WAIT_POLICY=PASSIVE``: OpenMP threads that spin while waiting (the GNU default) steal the
    CPU from numba's and torch's workers on a busy machine; sleeping waits halved forward + backward
    wall time on the 2-core box (docs/performance.md).  It takes effect only if set before torch and
    numba load their OpenMP runtime, which the step handlers import lazily, after this call.  An
    explicit value in the environment is respected.  Numba's compile cache is left to
    ``NUMBA_CACHE_DIR`` when set (the Makefile and the rules point it at the checkout's
    ``.numba_cache/``), else to numba's default (``__pycache__`` beside the sources).

    ``NUMBA_CPU_FEATURES`` with 512-bit vectors preferred on AVX-512 CPUs (:mod:`trace3d.cputarget`:
    LLVM's Intel models split the kernels' 16-lane loops into two 256-bit halves otherwise), unless the
    environment names a CPU target already.
    """
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from .cputarget import set_wide_vectors

    set_wide_vectors()


def _command_environment(args: argparse.Namespace) -> None:
    """``GOMP_SPINCOUNT=10000`` for the commands in :data:`SPIN_COMMANDS` only (an explicit value in the
    environment is respected): workers spin about 0.5 ms after a parallel region before they sleep
    (PASSIVE alone: not at all), which took the default room's lift iteration from 3.2 to 2.7 ms
    (docs/lifting.md). The rules give the lift step both cores, so the spinning takes no core from
    another job. Called after parsing, before any handler imports torch or numba."""
    if (args.command, getattr(args, "name", None)) in SPIN_COMMANDS:
        os.environ.setdefault("GOMP_SPINCOUNT", "10000")


# ----------------------------------------------------------------------------------------------
# step handlers (imports stay inside so that `trace3d --help` is fast)
# ----------------------------------------------------------------------------------------------


def _cmd_scene(args: argparse.Namespace) -> None:
    from .io import atomic_dir
    from .params import load_params_arg

    params = load_params_arg(args.params)
    source = _need_source(args) if args.kind != "synthetic" else None
    out = Path(args.out)
    with atomic_dir(out) as tmp:
        if args.kind == "synthetic":
            from .datasets import synthetic

            synthetic.generate_scene(tmp, synthetic.params_from(params))
        elif args.kind == "replica":
            from .datasets import replica

            replica.import_replica(source, tmp, replica.params_from(params))
        elif args.kind == "nvos":
            from .datasets import llff

            llff.import_nvos(source, tmp, llff.params_from(params))
        elif args.kind == "llff":
            from .datasets import llff

            llff.import_llff(source, tmp, llff.params_from(params))
        elif args.kind == "images":
            from .datasets import images

            images.import_images(source, tmp, images.params_from(params))
        elif args.kind == "transforms":
            from .datasets import transforms

            transforms.import_transforms(source, tmp, transforms.params_from(params))
        elif args.kind == "canonical":
            from .scene import Scene

            import shutil

            scene = Scene.read(source)
            shutil.copytree(scene.root, tmp, dirs_exist_ok=True)
        from .preview import scene_preview
        from .scene import Scene

        scene_preview(Scene.read(tmp), tmp / "preview.png")
    log.info("wrote scene %s", out)


def _need_source(args: argparse.Namespace) -> Path:
    if not args.source:
        raise Trace3DError(f"`trace3d scene {args.kind}` needs --source pointing at the data set folder.")
    return Path(args.source)


def _cmd_masks(args: argparse.Namespace) -> None:
    from .io import atomic_dir
    from .params import load_params_arg
    from .scene import Scene

    scene = Scene.read(args.scene)
    from .masks import run_masks

    with atomic_dir(args.out) as tmp:
        run_masks(scene, tmp, args.source, load_params_arg(args.params))


def _cmd_patches(args: argparse.Namespace) -> None:
    from .io import atomic_dir
    from .params import load_params_arg
    from .scene import Scene

    scene = Scene.read(args.scene)
    from .masks.patches import run_patches

    with atomic_dir(args.out) as tmp:
        run_patches(scene, Path(args.masks), tmp, load_params_arg(args.params))


def _cmd_masks_stats(args: argparse.Namespace) -> None:
    import json

    from .io import write_json
    from .params import from_mapping, load_params_arg
    from .scene import Scene

    scene = Scene.read(args.scene)
    from .masks.patches import PatchParams
    from .masks.stats import scene_statistics

    patch_params = from_mapping(PatchParams, load_params_arg(args.patch_params), "patches params")
    result = scene_statistics(scene, Path(args.masks), patch_params)
    if args.out:
        write_json(Path(args.out), result)
    print(json.dumps(result, indent=2))


def _cmd_overlay(args: argparse.Namespace) -> None:
    from .io import atomic_dir
    from .scene import Scene

    scene = Scene.read(args.scene)
    from .masks.overlay import run_overlay

    with atomic_dir(args.out) as tmp:
        run_overlay(scene, Path(args.masks), tmp)


def _cmd_poses(args: argparse.Namespace) -> None:
    from .io import atomic_dir
    from .params import load_params_arg
    from .scene import Scene

    scene = Scene.read(args.scene)
    from .sfm import run_poses

    with atomic_dir(args.out) as tmp:
        run_poses(scene, tmp, load_params_arg(args.params))


def _cmd_gaussians(args: argparse.Namespace) -> None:
    from .io import atomic_dir
    from .params import load_params_arg
    from .scene import Scene

    scene = Scene.read(args.scene)
    from .training import run_gaussians

    with atomic_dir(args.out) as tmp:
        run_gaussians(scene, Path(args.poses) if args.poses else None, tmp, load_params_arg(args.params))


def _cmd_trace(args: argparse.Namespace) -> None:
    from .io import atomic_dir
    from .params import load_params_arg
    from .scene import Scene
    from .tracing.git import run_trace

    scene = Scene.read(args.scene)
    with atomic_dir(args.out) as tmp:
        run_trace(scene, Path(args.poses) if args.poses else None, Path(args.gaussians), Path(args.labels), tmp,
                  load_params_arg(args.params))


def _cmd_merge(args: argparse.Namespace) -> None:
    from .io import atomic_dir
    from .params import from_mapping, load_params_arg
    from .scene import Scene
    from .tracing.merge import MergeParams, run_merge

    params = load_params_arg(args.params)
    from_mapping(MergeParams, params, "merge params")  # refuse bad parameters before reading anything heavy
    scene = Scene.read(args.scene)
    _check_patch_maps(scene, Path(args.git), Path(args.patches))
    with atomic_dir(args.out) as tmp:
        run_merge(scene, Path(args.git), Path(args.patches), tmp, params)


def _check_patch_maps(scene, git_dir: Path, patches_dir: Path) -> None:
    """The merge's inputs agree with the scene: every traced view's patch map has its image's size, and
    some view has a patch (with none, there is nothing to merge)."""
    import numpy as np

    from .scene import read_u16
    from .tracing.git import GITStats

    stats = GITStats.load(git_dir / "git.npz")
    known = {c.name: c for c in scene.cameras}
    any_patch = False
    for frame in stats.frames:
        if frame not in known:
            raise Trace3DError(f"{git_dir / 'git.npz'}: traced view '{frame}' is not a view of the scene "
                               f"{scene.root}; rerun the trace step on this scene.")
        cam = known[frame]
        patch_map = read_u16(patches_dir / f"{frame}.png", "patch map", (cam.width, cam.height))
        any_patch = any_patch or bool(np.any(patch_map))
    if stats.frames and not any_patch:
        raise Trace3DError(f"{patches_dir}: no view has a patch (every patch map is empty), so there is nothing "
                           f"to merge; check the masks step's output.")


def _cmd_refine(args: argparse.Namespace) -> None:
    from .io import atomic_dir
    from .params import load_params_arg
    from .scene import Scene
    from .params import from_mapping
    from .tracing.refine import RefineParams, run_refine

    params = load_params_arg(args.params)
    from_mapping(RefineParams, params, "refine params")  # refuse bad parameters before reading anything heavy
    scene = Scene.read(args.scene)
    with atomic_dir(args.out) as tmp:
        run_refine(scene, Path(args.poses) if args.poses else None, Path(args.gaussians), Path(args.labels), tmp,
                   params)


def _cmd_evaluate(args: argparse.Namespace) -> None:
    from .evaluation.step import run_evaluate
    from .io import atomic_dir
    from .params import load_params_arg

    label = _json_arg(args.label, "--label")
    params = load_params_arg(args.params)
    _check_evaluate_inputs(Path(args.scene), Path(args.lift), params)
    with contextlib.ExitStack() as stack:
        tmp = stack.enter_context(atomic_dir(args.out))
        objects = stack.enter_context(atomic_dir(args.objects)) if args.objects else None
        run_evaluate(Path(args.scene), Path(args.poses) if args.poses else None, Path(args.gaussians), Path(args.lift),
                     tmp, params, label, objects_dir=objects)


def _check_evaluate_inputs(scene_dir: Path, lift_dir: Path, params: dict) -> None:
    """Refuse bad evaluate parameters, a scene without ground truth and object ids the scene does not
    have before the lifted scene is loaded."""
    from .evaluation.params import EvaluateParams
    from .params import from_mapping
    from .scene import Scene

    p = from_mapping(EvaluateParams, params, "evaluate params")
    scene = Scene.read(scene_dir)
    if scene.objects is None or not scene.has_instances:
        raise Trace3DError(f"{scene_dir}: evaluation needs ground truth (objects.json and instances/), which this "
                           f"scene lacks; evaluate scenes from the synthetic or replica importers.")
    if p.objects is not None:
        unknown = sorted(set(p.objects) - set(scene.objects.by_id))
        if unknown:
            ids = sorted(scene.objects.by_id)
            has = f"ids {ids[0]} to {ids[-1]}" if ids else "no objects"
            raise Trace3DError(f"evaluate params.objects: ids {unknown[:5]} are not objects of the scene {scene_dir} "
                               f"(its objects.json has {has}); use ids from that file.")
    if not (lift_dir / "lift.json").is_file():
        raise Trace3DError(f"{lift_dir / 'lift.json'}: lift.json is missing; is {lift_dir} the output of a lift step?")


def _cmd_evaluate_nvos(args: argparse.Namespace) -> None:
    from .evaluation.nvos import run_evaluate_nvos
    from .io import atomic_dir

    label = _json_arg(args.label, "--label")
    with atomic_dir(args.out) as tmp:
        run_evaluate_nvos(Path(args.scene), Path(args.poses) if args.poses else None, Path(args.gaussians),
                          Path(args.lift), Path(args.labels), tmp, label)


def _json_arg(text: str | None, flag: str) -> dict:
    if not text:
        return {}
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        raise Trace3DError(f"{flag}: not valid JSON ({exc}).") from exc
    if not isinstance(value, dict):
        raise Trace3DError(f"{flag}: expected a JSON mapping, got {type(value).__name__}.")
    return value


def _cmd_tables(args: argparse.Namespace) -> None:
    from .report.tables import write_tables

    write_tables(Path(args.results), Path(args.out), [Path(e) for e in args.evals] if args.evals else None)


def _cmd_robustness(args: argparse.Namespace) -> None:
    from .params import load_params_arg
    from .report.robustness import write_robustness

    write_robustness(load_params_arg(args.spec), Path(args.out), Path(args.plot) if args.plot else None)


def _cmd_effects(args: argparse.Namespace) -> None:
    from .params import load_params_arg
    from .report.effects import write_effects

    write_effects(load_params_arg(args.spec), Path(args.out), Path(args.plot) if args.plot else None)


def _cmd_lift(args: argparse.Namespace) -> None:
    from .io import atomic_dir
    from .lifting.step import parse_lift_params, run_lift
    from .params import load_params_arg
    from .scene import Scene

    params = load_params_arg(args.params)
    parse_lift_params(params)  # refuse bad parameters before reading anything heavy
    scene = Scene.read(args.scene)
    with atomic_dir(args.out) as tmp:
        run_lift(scene, Path(args.poses) if args.poses else None, Path(args.gaussians),
                 Path(args.labels) if args.labels else None, tmp, params)


def _cmd_extract(args: argparse.Namespace) -> None:
    from .extract import parse_point, run_extract
    from .io import atomic_dir
    from .params import load_params_arg
    from .scene import Scene

    params = load_params_arg(args.params)
    if args.view:
        params["view"] = args.view
    if args.point:
        params["point"] = list(parse_point(args.point))
    scene = Scene.read(args.scene)
    with atomic_dir(args.out) as tmp:
        run_extract(scene, Path(args.poses) if args.poses else None, Path(args.gaussians), Path(args.lift), tmp,
                    params)


def _cmd_segment(args: argparse.Namespace) -> None:
    from .io import atomic_dir
    from .params import from_mapping, load_params_arg
    from .scene import Scene
    from .segment import SegmentParams, run_segment

    params = load_params_arg(args.params)
    from_mapping(SegmentParams, params, "segment params")  # refuse bad parameters before reading anything heavy
    scene = Scene.read(args.scene)
    with atomic_dir(args.out) as tmp:
        run_segment(scene, Path(args.poses) if args.poses else None, Path(args.gaussians), Path(args.lift), tmp,
                    params)


def _parse_size(text: str) -> tuple[int, int]:
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.isdigit() and int(p) > 0 for p in parts):
        raise Trace3DError(f"bench: --size must look like 160x120, got {text!r}.")
    return int(parts[0]), int(parts[1])


def _cmd_bench(args: argparse.Namespace) -> None:
    if args.name == "render":
        from .bench.render import run_bench

        result = run_bench(quick=args.quick)
    elif args.name == "synthetic":
        from .bench.synthetic import run_bench

        result = run_bench(quick=args.quick)
    elif args.name == "fit":
        from .bench.fit import run_rounds

        sizes = [_parse_size(text) for text in args.size] if args.size else None
        if args.rounds < 1:
            raise Trace3DError(f"bench fit: --rounds must be >= 1, got {args.rounds}.")
        result = run_rounds(args.rounds, quick=args.quick, sizes=sizes, iterations=args.iterations,
                            baseline=Path(args.baseline) if args.baseline else None)
    elif args.name == "fit-sweep":
        from .bench.fit import run_sweep

        if args.merge:
            from .bench.fit import merge_sweeps

            result = merge_sweeps([Path(f) for f in args.merge], Path(args.plot) if args.plot else None)
        else:
            if not args.room_list:
                raise Trace3DError("bench fit-sweep: give at least one --rooms folder (a fitted room's results "
                                   "folder), or --merge earlier sweeps' JSON files.")
            result = run_sweep([Path(r) for r in args.room_list], [int(b) for b in args.budgets],
                               [float(x) for x in args.scales], Path(args.plot) if args.plot else None)
    elif args.name == "trace":
        from .bench.trace import run_bench

        result = run_bench(Path(args.room), quick=args.quick)
    elif args.name == "lift":
        from .bench.lift import run_bench
        from .params import load_params_arg

        result = run_bench(Path(args.room), quick=args.quick, params=load_params_arg(args.params))
    elif args.name == "prompts":
        from .bench.prompts import run_bench

        result = run_bench(Path(args.room), views=4 if args.quick else 16)
    elif args.name == "evaluate":
        from .bench.evaluate import run_bench
        from .params import load_params_arg

        result = run_bench(Path(args.room), variant=args.variant, params=load_params_arg(args.params),
                           repeats=args.rounds)
    elif args.name == "lift-forms":
        from .bench.lift import compare_forms

        result = compare_forms(Path(args.room), iterations=300 if args.quick else 1500)
    else:  # argparse restricts choices; kept for clarity
        raise Trace3DError(f"unknown benchmark {args.name!r}.")
    text = json.dumps(result, indent=2)
    if args.out:
        from .io import atomic_file

        with atomic_file(args.out) as tmp:
            tmp.write_text(text + "\n")
    print(text)


def _cmd_summary(args: argparse.Namespace) -> None:
    from .report.summary import write_scene_table

    write_scene_table([Path(p) for p in args.scenes], Path(args.out))


def _cmd_reconstruction_table(args: argparse.Namespace) -> None:
    from .report.summary import write_reconstruction_table

    write_reconstruction_table(
        [Path(p) for p in args.poses], [Path(g) for g in args.gaussians], Path(args.out),
        Path(args.plot) if args.plot else None,
    )


def _cmd_tracing_table(args: argparse.Namespace) -> None:
    from .report.tracing import write_tracing_table

    write_tracing_table([Path(p) for p in args.merge], [Path(p) for p in args.refine] if args.refine else None,
                        Path(args.out), Path(args.plot) if args.plot else None)


# ----------------------------------------------------------------------------------------------
# parser
# ----------------------------------------------------------------------------------------------


def build_parser(help_step: str | None = None) -> argparse.ArgumentParser:
    """The ``trace3d`` parser; ``help_step``'s help lists its parameters (imports that step's modules)."""
    parser = argparse.ArgumentParser(
        prog="trace3d",
        description="Trace3D pipeline steps. Each step reads files, writes one output folder atomically.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("--threads", type=int, metavar="N",
                        help="CPU threads for torch, numba, OpenMP and COLMAP (default: all cores)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="STEP")
    if help_step is not None:  # `trace3d <step> --help` lists the step's parameters (trace3d.schema)
        add_parser = sub.add_parser

        def add_with_parameters(name, **kwargs):
            if name == help_step:
                from .schema import help_text

                text = help_text(name)
                if text:
                    kwargs["epilog"] = "--params keys = their defaults (null: the preset's value):\n" + text
                    kwargs["formatter_class"] = argparse.RawDescriptionHelpFormatter
            return add_parser(name, **kwargs)

        sub.add_parser = add_with_parameters

    params_help = "parameter overrides: inline JSON/YAML mapping, or @file.yaml"

    p = sub.add_parser("scene", help="build a canonical scene folder (synthetic room or an importer)")
    p.add_argument("kind", choices=["synthetic", "replica", "nvos", "llff", "canonical", "images", "transforms"])
    p.add_argument("--out", required=True, help="output scene folder")
    p.add_argument("--source", help="data set folder (importers only; images: a folder of photos; transforms: "
                                    "the folder of a transforms.json capture, or the .json file)")
    p.add_argument("--params", help=params_help)
    p.set_defaults(func=_cmd_scene)

    p = sub.add_parser("masks", help="2D instance masks per view (simulated | files | sam | graph)")
    p.add_argument("--scene", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--source", default="simulated", choices=["simulated", "files", "sam", "graph"])
    p.add_argument("--params", help=params_help)
    p.set_defaults(func=_cmd_masks)

    p = sub.add_parser("masks-stats", help="statistics of a masks folder (calibration: docs/masks_calibration.md)")
    p.add_argument("--scene", required=True)
    p.add_argument("--masks", required=True, help="a `trace3d masks` output folder")
    p.add_argument("--patch-params", help="patch step parameters for the patch statistics (" + params_help + ")")
    p.add_argument("--out", help="also write the statistics to this JSON file")
    p.set_defaults(func=_cmd_masks_stats)

    p = sub.add_parser("patches", help="overlap masks into disjoint primitive patches + hierarchy")
    p.add_argument("--scene", required=True)
    p.add_argument("--masks", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--params", help=params_help)
    p.set_defaults(func=_cmd_patches)

    p = sub.add_parser("overlay", help="overlay each view's masks into one label per pixel (baselines without patches)")
    p.add_argument("--scene", required=True)
    p.add_argument("--masks", required=True)
    p.add_argument("--out", required=True)
    p.set_defaults(func=_cmd_overlay)

    p = sub.add_parser("poses", help="camera poses by pycolmap structure-from-motion (or the data set's)")
    p.add_argument("--scene", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--params", help=params_help)
    p.set_defaults(func=_cmd_poses)

    p = sub.add_parser("gaussians", help="fit a 2D Gaussian Splatting scene")
    p.add_argument("--scene", required=True)
    p.add_argument("--poses", help="poses folder (cameras.json, points3D.ply); default: the scene's cameras")
    p.add_argument("--out", required=True)
    p.add_argument("--params", help=params_help)
    p.set_defaults(func=_cmd_gaussians)

    p = sub.add_parser("trace", help="GIT: trace every training view's label map through the fitted scene")
    p.add_argument("--scene", required=True)
    p.add_argument("--poses", help="poses folder whose cameras the fitted scene lives with")
    p.add_argument("--gaussians", required=True, help="fitted scene folder (point_cloud.ply)")
    p.add_argument("--labels", required=True, help="label maps <frame>.png (16-bit): the patches folder")
    p.add_argument("--out", required=True)
    p.add_argument("--params", help=params_help)
    p.set_defaults(func=_cmd_trace)

    p = sub.add_parser("merge", help="consistent instance maps: merge patches by majority vote over views")
    p.add_argument("--scene", required=True)
    p.add_argument("--git", required=True, help="trace step folder (git.npz)")
    p.add_argument("--patches", required=True, help="patches folder (maps and hierarchy JSON)")
    p.add_argument("--out", required=True)
    p.add_argument("--params", help=params_help)
    p.set_defaults(func=_cmd_merge)

    p = sub.add_parser("refine", help="GIT-guided density control: split / prune ambiguous Gaussians while retraining")
    p.add_argument("--scene", required=True)
    p.add_argument("--poses", help="poses folder whose cameras the fitted scene lives with")
    p.add_argument("--gaussians", required=True, help="fitted scene folder (point_cloud.ply, config.json)")
    p.add_argument("--labels", required=True, help="instance maps <frame>.png: merge/instances (or raw patches)")
    p.add_argument("--out", required=True)
    p.add_argument("--params", help=params_help)
    p.set_defaults(func=_cmd_refine)

    p = sub.add_parser("evaluate", help="3D object extraction and novel-view segmentation of a lifted scene")
    p.add_argument("--scene", required=True)
    p.add_argument("--poses", help="poses folder whose cameras the fitted scene lives with")
    p.add_argument("--gaussians", required=True, help="the Gaussians the lifting used (point_cloud.ply)")
    p.add_argument("--lift", required=True, help="lift step folder (lift.json names the method)")
    p.add_argument("--out", required=True)
    p.add_argument("--params", help=params_help)
    p.add_argument("--label", help="JSON mapping copied into metrics.json as \"variant\" (name and settings)")
    p.add_argument("--objects", help="folder for the objects' PLY + turntable files (default: <out>/objects)")
    p.set_defaults(func=_cmd_evaluate)

    p = sub.add_parser("evaluate-nvos", help="NVOS (Table 4): scribbles on the reference view -> the target view's mask")
    p.add_argument("--scene", required=True, help="an NVOS scene folder (trace3d scene nvos)")
    p.add_argument("--poses", help="poses folder whose cameras the fitted scene lives with")
    p.add_argument("--gaussians", required=True, help="the Gaussians the lifting used (point_cloud.ply)")
    p.add_argument("--lift", required=True, help="lift step folder")
    p.add_argument("--labels", required=True, help="the instance maps the lifting used (the scribbles select instances there)")
    p.add_argument("--out", required=True)
    p.add_argument("--label", help="JSON mapping copied into metrics.json as \"variant\" (name and settings)")
    p.set_defaults(func=_cmd_evaluate_nvos)

    p = sub.add_parser("tables", help="paper-layout Tables 2, 3 and 5 from results/<scene>/<variant>/eval/metrics.json")
    p.add_argument("--results", required=True, help="results folder")
    p.add_argument("--out", required=True, help="output folder (results/tables)")
    p.add_argument("--evals", nargs="+", help="only these evaluate folders (<results>/<scene>/<variant>/eval)")
    p.set_defaults(func=_cmd_tables)

    p = sub.add_parser("robustness", help="object / NVS mIoU per variant against the simulated mask inconsistency")
    p.add_argument("--spec", required=True,
                   help="JSON/YAML (or @file): {runs: [{scene, level, variant, eval}], merges: [{scene, level, merge}]}")
    p.add_argument("--out", required=True, help="Markdown table (results/tables/robustness.md; a CSV beside it)")
    p.add_argument("--plot", help="PNG of the curves (results/plots/robustness.png)")
    p.set_defaults(func=_cmd_robustness)

    p = sub.add_parser("effects", help="every variant under every mask model and seed: 95 %% CIs, paired effects, "
                                       "share of the raw-to-oracle gap")
    p.add_argument("--spec", required=True,
                   help="JSON/YAML (or @file): {runs: [{room, masks, variant, seed, eval}], oracle: [variants], raw}")
    p.add_argument("--out", required=True, help="Markdown table (results/tables/effects.md; CSVs beside it)")
    p.add_argument("--plot", help="PNG of the means and intervals (results/plots/effects.png)")
    p.set_defaults(func=_cmd_effects)


    p = sub.add_parser("lift", help="lift the instance maps into the scene: contrastive features or self-prompting")
    p.add_argument("--scene", required=True)
    p.add_argument("--poses", help="poses folder whose cameras the fitted scene lives with")
    p.add_argument("--gaussians", required=True, help="fitted (or refined) scene folder (point_cloud.ply)")
    p.add_argument("--labels", help="instance maps <frame>.png (16-bit, 0 = unlabelled): merge/instances or patches")
    p.add_argument("--out", required=True)
    p.add_argument("--params", help=params_help + " (method: contrastive | self_prompt, preset: paper | official)")
    p.set_defaults(func=_cmd_lift)

    p = sub.add_parser("extract", help="one object out by a click: its Gaussians (PLY) and renders, from a "
                                       "contrastive lift")
    p.add_argument("--scene", required=True)
    p.add_argument("--poses", help="poses folder whose cameras the fitted scene lives with")
    p.add_argument("--gaussians", required=True, help="the Gaussians the lifting used (point_cloud.ply)")
    p.add_argument("--lift", required=True, help="contrastive lift folder (features.npy, lift.json)")
    p.add_argument("--view", help="the training view clicked on (frame name)")
    p.add_argument("--point", metavar="X,Y", help="the clicked pixel: column,row of the view's image (0-based)")
    p.add_argument("--out", required=True, help="output folder: object.ply, object.png, turntable.png, extract.json")
    p.add_argument("--params", help=params_help + " (view, point: [x, y], threshold_steps, ...; the flags win)")
    p.set_defaults(func=_cmd_extract)

    p = sub.add_parser("segment", help="the objects a contrastive lift separates, without ground truth: per-object "
                                       "PLYs, turntable renders and a contact sheet")
    p.add_argument("--scene", required=True)
    p.add_argument("--poses", help="poses folder whose cameras the fitted scene lives with")
    p.add_argument("--gaussians", required=True, help="the Gaussians the lifting used (point_cloud.ply)")
    p.add_argument("--lift", required=True, help="contrastive lift folder (features.npy, lift.json)")
    p.add_argument("--out", required=True, help="output folder: objects/<k>.ply, objects/<k>.png, contact_sheet.png, "
                                                "segment.json")
    p.add_argument("--params", help=params_help + " (samples, min_share, seed, min_gaussians, min_pixels, ...)")
    p.set_defaults(func=_cmd_segment)

    p = sub.add_parser("summary", help="write the per-scene summary table (results/scenes.md)")
    p.add_argument("scenes", nargs="+", help="scene folders")
    p.add_argument("--out", required=True)
    p.set_defaults(func=_cmd_summary)

    p = sub.add_parser("reconstruction-table", help="write the reconstruction table (poses + 2DGS fit per scene)")
    p.add_argument("--poses", nargs="+", required=True, help="poses folders, one per scene")
    p.add_argument("--gaussians", nargs="+", required=True, help="gaussians folders, same order")
    p.add_argument("--out", required=True, help="Markdown table (a CSV is written beside it)")
    p.add_argument("--plot", help="PNG bar plot of test PSNR and minutes per scene")
    p.set_defaults(func=_cmd_reconstruction_table)

    p = sub.add_parser("tracing-table", help="write the merge / refine table (results/tracing.md)")
    p.add_argument("--merge", nargs="+", required=True, help="merge folders, one per scene")
    p.add_argument("--refine", nargs="+", help="refine folders, same order")
    p.add_argument("--out", required=True, help="Markdown table (a CSV is written beside it)")
    p.add_argument("--plot", help="PNG bars of the merge quality before / after")
    p.set_defaults(func=_cmd_tracing_table)

    p = sub.add_parser("bench", help="benchmarks; print one JSON object")
    p.add_argument("name", choices=["render", "synthetic", "trace", "lift", "lift-forms", "fit", "fit-sweep",
                                    "prompts", "evaluate"])
    p.add_argument("--room", default="results/room0",
                   help="trace, lift: a fitted room's results folder (scene/, poses/, gaussians/, patches/ or "
                        "merge-paper/instances); prompts: a room's results folder or canonical scene with ground "
                        "truth (the prompt sources' answers scored against it, docs/masks.md)")
    p.add_argument("--params", help="lift: the lift step's parameters (JSON/YAML or @file) whose wall time is measured; "
                                    "evaluate: the evaluate step's (default {\"protocol\": \"standard\"})")
    p.add_argument("--variant", default="full", help="evaluate: the variant folder under --room whose lift is evaluated")
    p.add_argument("--quick", action="store_true", help="smaller sizes (smoke run)")
    p.add_argument("--size", action="append", metavar="WxH",
                   help="fit: frame size to measure (repeatable; default 160x120 and 504x378)")
    p.add_argument("--iterations", type=int, help="fit: timed iterations per size (default 200)")
    p.add_argument("--baseline", metavar="CHECKOUT",
                   help="fit: also run this checkout's fit benchmark first (e.g. a git worktree of the previous "
                        "main) and report both side by side")
    p.add_argument("--rounds", type=int, default=1,
                   help="fit: run the benchmark this many times (alternating with --baseline's) and report the "
                        "median round per size, every round's time and, with --baseline, each round pair's "
                        "speedup and their median (default 1); evaluate: evaluations in a row (the first may "
                        "compile kernels)")
    p.add_argument("--rooms", dest="room_list", nargs="+", help="fit-sweep: rooms' results folders (scene/, poses/)")
    p.add_argument("--budgets", nargs="+", default=["20000", "40000", "80000"],
                   help="fit-sweep: Gaussian budgets (max_gaussians)")
    p.add_argument("--scales", nargs="+", default=["0.05", "0.1"],
                   help="fit-sweep: schedule scales (0.1 = 3,000 iterations)")
    p.add_argument("--merge", nargs="+", metavar="JSON",
                   help="fit-sweep: no fitting; merge these earlier sweeps' --out files (rows in order) and plot them")
    p.add_argument("--plot", help="fit-sweep: PNG of test PSNR against minutes")
    p.add_argument("--out", help="also write the JSON here")
    p.set_defaults(func=_cmd_bench)
    return parser


def _help_step(argv: list[str]) -> str | None:
    """The step whose ``--help`` is asked for (its parameter list is added to that help only, so that
    other commands do not import the step modules)."""
    if not any(a in ("-h", "--help") for a in argv):
        return None
    steps = [a for a in argv if not a.startswith("-")]
    return steps[0] if steps else None


class _Interrupted(KeyboardInterrupt):
    """SIGTERM (Snakemake stopping a job, ``kill``) raised as an interruption, so that the temporary
    output is removed on the way out as for Ctrl-C."""


def _on_sigterm(signum, frame):  # noqa: ARG001 - signal handler signature
    raise _Interrupted()


def _interrupted(exc: BaseException) -> KeyboardInterrupt | None:
    """The KeyboardInterrupt behind ``exc`` (numba's compiled code reports one as a SystemError)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def main(argv: list[str] | None = None) -> int:
    _entry_point_environment()
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(_help_step(argv))
    args = parser.parse_args(argv)
    _command_environment(args)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    from .io import TempPathFilter
    from .threads import limit_threads

    for handler in logging.getLogger().handlers:
        if not any(isinstance(f, TempPathFilter) for f in handler.filters):
            handler.addFilter(TempPathFilter())
    import signal
    import threading

    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        with limit_threads(args.threads):
            if args.command not in NO_KERNEL_COMMANDS:
                from .compiling import compile_seconds, install

                install()
            args.func(args)
            if args.command not in NO_KERNEL_COMMANDS and compile_seconds() > 0:
                log.info("compiled kernels for %.1f min (cached for later runs)", compile_seconds() / 60)
    except Trace3DError as exc:
        sentence = " ".join(str(exc).split())  # one line, whatever a wrapped library message held
        print(f"trace3d {args.command}: error: {sentence}", file=sys.stderr)
        return 2
    except BaseException as exc:  # noqa: BLE001 - an interruption is reported in one line, anything else re-raised
        stop = _interrupted(exc)
        if stop is None:
            raise
        # objects torn down half-built by the interruption (a progress bar) would print "Exception ignored"
        # tracebacks on the way out: the one line below is the whole report
        sys.unraisablehook = lambda unraisable: None
        how = "stopped (SIGTERM)" if isinstance(stop, _Interrupted) else "interrupted"
        print(f"trace3d {args.command}: {how}; nothing was written (an earlier output, if any, is unchanged).",
              file=sys.stderr)
        return 143 if isinstance(stop, _Interrupted) else 130
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    return 0


if __name__ == "__main__":
    sys.exit(main())
