"""``trace3d tracing-table``: see :data:`trace3d.steps.STEPS`."""

from __future__ import annotations

import argparse
from pathlib import Path


def run(args: argparse.Namespace) -> None:
    from ..report.tracing import write_tracing_table

    write_tracing_table([Path(p) for p in args.merge], [Path(p) for p in args.refine] if args.refine else None,
                        Path(args.out), Path(args.plot) if args.plot else None)
