"""``trace3d poses``: see :data:`trace3d.steps.STEPS`."""

from __future__ import annotations

import argparse


def run(args: argparse.Namespace) -> None:
    from ..io import atomic_dir
    from ..params import load_params_arg
    from ..scene import Scene

    scene = Scene.read(args.scene)
    from ..poses.step import run_poses

    with atomic_dir(args.out) as tmp:
        run_poses(scene, tmp, load_params_arg(args.params))
