"""``trace3d scale-table``: see :data:`trace3d.steps.STEPS`."""

from __future__ import annotations

import argparse
from pathlib import Path


def run(args: argparse.Namespace) -> None:
    from ..report.scale import write_scale_table

    write_scale_table(Path(args.results), args.small, args.large, Path(args.out))
