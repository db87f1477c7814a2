"""``trace3d gaussians``: see :data:`trace3d.steps.STEPS`."""

from __future__ import annotations

import argparse
from pathlib import Path


def run(args: argparse.Namespace) -> None:
    from ..io import atomic_dir
    from ..params import load_params_arg
    from ..scene import Scene

    scene = Scene.read(args.scene)
    from ..training import run_gaussians

    with atomic_dir(args.out) as tmp:
        run_gaussians(scene, Path(args.poses) if args.poses else None, tmp, load_params_arg(args.params))
