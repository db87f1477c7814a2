"""``trace3d overlay``: see :data:`trace3d.steps.STEPS`."""

from __future__ import annotations

import argparse
from pathlib import Path


def run(args: argparse.Namespace) -> None:
    from ..io import atomic_dir
    from ..scene import Scene

    scene = Scene.read(args.scene)
    from ..masks.overlay import run_overlay

    with atomic_dir(args.out) as tmp:
        run_overlay(scene, Path(args.masks), tmp)
