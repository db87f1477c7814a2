"""``trace3d reconstruction-table``: see :data:`trace3d.steps.STEPS`."""

from __future__ import annotations

import argparse
from pathlib import Path


def run(args: argparse.Namespace) -> None:
    from ..report.summary import write_reconstruction_table

    write_reconstruction_table(
        [Path(p) for p in args.poses], [Path(g) for g in args.gaussians], Path(args.out),
        Path(args.plot) if args.plot else None,
    )
