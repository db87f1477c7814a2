"""``trace3d segment``: see :data:`trace3d.steps.STEPS`."""

from __future__ import annotations

import argparse
from pathlib import Path


def run(args: argparse.Namespace) -> None:
    from ..io import atomic_dir
    from ..params import from_mapping, load_params_arg
    from ..scene import Scene
    from ..segment import SegmentParams, run_segment

    params = load_params_arg(args.params)
    from_mapping(SegmentParams, params, "segment params")  # refuse bad parameters before reading anything heavy
    scene = Scene.read(args.scene)
    with atomic_dir(args.out) as tmp:
        run_segment(scene, Path(args.poses) if args.poses else None, Path(args.gaussians), Path(args.lift), tmp,
                    params)
