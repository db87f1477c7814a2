"""``trace3d extract``: see :data:`trace3d.steps.STEPS`."""

from __future__ import annotations

import argparse
from pathlib import Path


def run(args: argparse.Namespace) -> None:
    from ..extract import parse_point, run_extract
    from ..io import atomic_dir
    from ..params import load_params_arg
    from ..scene import Scene

    params = load_params_arg(args.params)
    if args.view:
        params["view"] = args.view
    if args.point:
        params["point"] = list(parse_point(args.point))
        if not all(float(v).is_integer() for v in params["point"]):  # ExtractParams.point: fractions are floored
            import logging
            import math

            logging.getLogger("trace3d").warning("extract: --point %s is read as the pixel %d,%d (fractions are "
                                                 "floored)", args.point, *(math.floor(v) for v in params["point"]))
    scene = Scene.read(args.scene)
    with atomic_dir(args.out) as tmp:
        run_extract(scene, Path(args.poses) if args.poses else None, Path(args.gaussians), Path(args.lift), tmp,
                    params)
