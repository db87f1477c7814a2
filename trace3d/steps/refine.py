"""``trace3d refine``: see :data:`trace3d.steps.STEPS`."""

from __future__ import annotations

import argparse
from pathlib import Path


def run(args: argparse.Namespace) -> None:
    from ..io import atomic_dir
    from ..params import load_params_arg
    from ..scene import Scene
    from ..params import from_mapping
    from ..tracing.refine import RefineParams, run_refine

    params = load_params_arg(args.params)
    from_mapping(RefineParams, params, "refine params")  # refuse bad parameters before reading anything heavy
    scene = Scene.read(args.scene)
    with atomic_dir(args.out) as tmp:
        run_refine(scene, Path(args.poses) if args.poses else None, Path(args.gaussians), Path(args.labels), tmp,
                   params)
