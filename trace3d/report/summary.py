"""The per-scene summary table (``results/scenes.md``)."""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from ..io import atomic_file
from ..scene import Scene


def scene_row(scene_dir: Path) -> dict:
    """One table row describing the canonical scene in ``scene_dir``."""
    scene = Scene.read(scene_dir, check_files=False)
    sizes = sorted({(c.width, c.height) for c in scene.cameras})
    objects = scene.objects
    return {
        "scene": scene_dir.parent.name if scene_dir.name == "scene" else scene_dir.name,
        "source": scene.meta.get("source", "unknown"),
        "views": len(scene.cameras),
        "train": len(scene.train_cameras),
        "test": len(scene.test_cameras),
        "objects": sum(1 for o in objects if o.level == "object") if objects is not None else 0,
        "evaluated": len(objects.evaluated_ids()) if objects is not None else 0,
        "resolution": ", ".join(f"{w}x{h}" for w, h in sizes),
    }


def write_scene_table(scene_dirs: list[Path], out: Path) -> pd.DataFrame:
    """Write a Markdown table (and a CSV beside it) with one row per scene."""
    table = pd.DataFrame([scene_row(Path(d)) for d in scene_dirs])
    with atomic_file(out) as tmp:
        tmp.write_text("# Scenes\n\n" + table.to_markdown(index=False) + "\n")
    with atomic_file(Path(out).with_suffix(".csv")) as tmp:
        table.to_csv(tmp, index=False)
    return table
