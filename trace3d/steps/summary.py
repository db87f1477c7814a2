"""``trace3d summary``: see :data:`trace3d.steps.STEPS`."""

from __future__ import annotations

import argparse
from pathlib import Path


def run(args: argparse.Namespace) -> None:
    from ..report.summary import write_scene_table

    write_scene_table([Path(p) for p in args.scenes], Path(args.out))
