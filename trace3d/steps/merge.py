"""``trace3d merge``: see :data:`trace3d.steps.STEPS`."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import Trace3DError


def run(args: argparse.Namespace) -> None:
    from ..io import atomic_dir
    from ..params import from_mapping, load_params_arg
    from ..scene import Scene
    from ..tracing.merge import MergeParams, run_merge

    params = load_params_arg(args.params)
    from_mapping(MergeParams, params, "merge params")  # refuse bad parameters before reading anything heavy
    scene = Scene.read(args.scene)
    _check_patch_maps(scene, Path(args.git), Path(args.patches))
    with atomic_dir(args.out) as tmp:
        run_merge(scene, Path(args.git), Path(args.patches), tmp, params)


def _check_patch_maps(scene, git_dir: Path, patches_dir: Path) -> None:
    """The merge's inputs agree with the scene: every traced view's patch map has its image's size, and
    some view has a patch (with none, there is nothing to merge)."""
    import numpy as np

    from ..scene import read_u16
    from ..tracing.git import GITStats

    frames = GITStats.load_frames(git_dir / "git.npz")  # not the [G, V] table: run_merge reads what it needs
    known = {c.name: c for c in scene.cameras}
    any_patch = False
    for frame in frames:
        if frame not in known:
            raise Trace3DError(f"{git_dir / 'git.npz'}: traced view '{frame}' is not a view of the scene "
                               f"{scene.root}; rerun the trace step on this scene.")
        cam = known[frame]
        patch_map = read_u16(patches_dir / f"{frame}.png", "patch map", (cam.width, cam.height))
        any_patch = any_patch or bool(np.any(patch_map))
    if frames and not any_patch:
        raise Trace3DError(f"{patches_dir}: no view has a patch (every patch map is empty), so there is nothing "
                           f"to merge; check the masks step's output.")
