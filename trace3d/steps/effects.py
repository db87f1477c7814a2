"""``trace3d effects``: see :data:`trace3d.steps.STEPS`."""

from __future__ import annotations

import argparse
from pathlib import Path


def run(args: argparse.Namespace) -> None:
    from ..params import load_params_arg
    from ..report.effects import write_effects

    write_effects(load_params_arg(args.spec), Path(args.out), Path(args.plot) if args.plot else None)
