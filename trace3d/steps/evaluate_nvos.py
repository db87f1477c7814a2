"""``trace3d evaluate-nvos``: see :data:`trace3d.steps.STEPS`."""

from __future__ import annotations

import argparse
from pathlib import Path

from ._common import json_arg


def run(args: argparse.Namespace) -> None:
    from ..evaluation.nvos import run_evaluate_nvos
    from ..io import atomic_dir

    label = json_arg(args.label, "--label")
    with atomic_dir(args.out) as tmp:
        run_evaluate_nvos(Path(args.scene), Path(args.poses) if args.poses else None, Path(args.gaussians),
                          Path(args.lift), Path(args.labels), tmp, label)
