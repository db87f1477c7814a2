"""``trace3d scene``: see :data:`trace3d.steps.STEPS`."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from ..errors import Trace3DError

log = logging.getLogger("trace3d")


def run(args: argparse.Namespace) -> None:
    from ..io import atomic_dir
    from ..params import load_params_arg

    params = load_params_arg(args.params)
    source = _need_source(args) if args.kind != "synthetic" else None
    out = Path(args.out)
    with atomic_dir(out) as tmp:
        if args.kind == "synthetic":
            from ..datasets import synthetic

            synthetic.generate_scene(tmp, synthetic.params_from(params))
        elif args.kind == "replica":
            from ..datasets import replica

            replica.import_replica(source, tmp, replica.params_from(params))
        elif args.kind == "nvos":
            from ..datasets import llff

            llff.import_nvos(source, tmp, llff.params_from(params))
        elif args.kind == "llff":
            from ..datasets import llff

            llff.import_llff(source, tmp, llff.params_from(params))
        elif args.kind == "images":
            from ..datasets import images

            images.import_images(source, tmp, images.params_from(params))
        elif args.kind == "transforms":
            from ..datasets import transforms

            transforms.import_transforms(source, tmp, transforms.params_from(params))
        elif args.kind == "canonical":
            from ..scene import Scene

            import shutil

            scene = Scene.read(source)
            shutil.copytree(scene.root, tmp, dirs_exist_ok=True)
        from ..preview import scene_preview
        from ..scene import Scene

        scene_preview(Scene.read(tmp), tmp / "preview.png")
    log.info("wrote scene %s", out)


def _need_source(args: argparse.Namespace) -> Path:
    if not args.source:
        raise Trace3DError(f"`trace3d scene {args.kind}` needs --source pointing at the data set folder.")
    return Path(args.source)
