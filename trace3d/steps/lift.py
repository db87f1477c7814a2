"""``trace3d lift``: see :data:`trace3d.steps.STEPS`."""

from __future__ import annotations

import argparse
from pathlib import Path


def run(args: argparse.Namespace) -> None:
    from ..io import atomic_dir
    from ..lifting.step import parse_lift_params, run_lift
    from ..params import load_params_arg
    from ..scene import Scene

    params = load_params_arg(args.params)
    parse_lift_params(params)  # refuse bad parameters before reading anything heavy
    scene = Scene.read(args.scene)
    with atomic_dir(args.out) as tmp:
        run_lift(scene, Path(args.poses) if args.poses else None, Path(args.gaussians),
                 Path(args.labels) if args.labels else None, tmp, params)
