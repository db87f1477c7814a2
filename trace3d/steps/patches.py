"""``trace3d patches``: see :data:`trace3d.steps.STEPS`."""

from __future__ import annotations

import argparse
from pathlib import Path


def run(args: argparse.Namespace) -> None:
    from ..io import atomic_dir
    from ..params import load_params_arg
    from ..scene import Scene

    scene = Scene.read(args.scene)
    from ..masks.patches import run_patches

    with atomic_dir(args.out) as tmp:
        run_patches(scene, Path(args.masks), tmp, load_params_arg(args.params))
