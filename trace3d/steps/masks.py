"""``trace3d masks``: see :data:`trace3d.steps.STEPS`."""

from __future__ import annotations

import argparse


def run(args: argparse.Namespace) -> None:
    from ..io import atomic_dir
    from ..params import load_params_arg
    from ..scene import Scene

    scene = Scene.read(args.scene)
    from pathlib import Path

    from ..errors import Trace3DError
    from ..masks import FITTED_SOURCES, run_masks

    if args.source not in FITTED_SOURCES and (args.gaussians or args.poses):
        raise Trace3DError(f"trace3d masks: --gaussians and --poses are for the sources that render the fitted scene "
                           f"({', '.join(FITTED_SOURCES)}); the {args.source} source reads the images only.")
    with atomic_dir(args.out) as tmp:
        run_masks(scene, tmp, args.source, load_params_arg(args.params),
                  Path(args.gaussians) if args.gaussians else None, Path(args.poses) if args.poses else None)
