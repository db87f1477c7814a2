"""``trace3d tables``: see :data:`trace3d.steps.STEPS`."""

from __future__ import annotations

import argparse
from pathlib import Path


def run(args: argparse.Namespace) -> None:
    from ..report.tables import write_tables

    write_tables(Path(args.results), Path(args.out), [Path(e) for e in args.evals] if args.evals else None)
