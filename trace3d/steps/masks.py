"""``trace3d masks``: see :data:`trace3d.steps.STEPS`."""

from __future__ import annotations

import argparse


def run(args: argparse.Namespace) -> None:
    from ..io import atomic_dir
    from ..params import load_params_arg
    from ..scene import Scene

    scene = Scene.read(args.scene)
    from ..masks import run_masks

    with atomic_dir(args.out) as tmp:
        run_masks(scene, tmp, args.source, load_params_arg(args.params))
