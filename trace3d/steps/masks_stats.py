"""``trace3d masks-stats``: see :data:`trace3d.steps.STEPS`."""

from __future__ import annotations

import argparse
from pathlib import Path


def run(args: argparse.Namespace) -> None:
    import json

    from ..io import write_json
    from ..params import from_mapping, load_params_arg
    from ..scene import Scene

    scene = Scene.read(args.scene)
    from ..masks.patches import PatchParams
    from ..masks.stats import scene_statistics

    patch_params = from_mapping(PatchParams, load_params_arg(args.patch_params), "patches params")
    result = scene_statistics(scene, Path(args.masks), patch_params)
    if args.out:
        write_json(Path(args.out), result)
    print(json.dumps(result, indent=2))
