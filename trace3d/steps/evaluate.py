"""``trace3d evaluate``: see :data:`trace3d.steps.STEPS`."""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path

from ..errors import Trace3DError
from ._common import json_arg


def run(args: argparse.Namespace) -> None:
    from ..evaluation.step import run_evaluate
    from ..io import atomic_dir
    from ..params import load_params_arg

    label = json_arg(args.label, "--label")
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
    from ..evaluation.params import EvaluateParams
    from ..params import from_mapping
    from ..scene import Scene

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
