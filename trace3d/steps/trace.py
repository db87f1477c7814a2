"""``trace3d trace``: see :data:`trace3d.steps.STEPS`."""

from __future__ import annotations

import argparse
from pathlib import Path


def run(args: argparse.Namespace) -> None:
    from ..io import atomic_dir
    from ..params import load_params_arg
    from ..scene import Scene
    from ..tracing.git import run_trace

    scene = Scene.read(args.scene)
    with atomic_dir(args.out) as tmp:
        run_trace(scene, Path(args.poses) if args.poses else None, Path(args.gaussians), Path(args.labels), tmp,
                  load_params_arg(args.params))
