"""Writing a synthetic room as a canonical scene folder: :func:`generate_scene`."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ...errors import Trace3DError
from ...io import write_json
from ...params import to_dict
from ...scene import ObjectTable, SceneObject, write_cameras, write_frame
from .cameras import camera_trajectory
from .layout import RoomLayout
from .params import SyntheticParams
from .primitives import STRUCTURE_CATEGORIES
from .raycast import render_view
from .room import build_room

log = logging.getLogger(__name__)


def to_uint8(rgb: np.ndarray) -> np.ndarray:
    """[H, W, 3] linear radiance -> uint8 display values (clipped, mild gamma)."""
    return np.round(np.clip(rgb, 0.0, 1.0) ** (1 / 1.1) * 255.0).astype(np.uint8)


def _object_table(layout: RoomLayout, max_pixels: dict[int, int], min_visible_pixels: int) -> ObjectTable:
    """The hierarchy with ``evaluated`` = non-structural objects seen by >= min_visible_pixels in some view.

    ``max_pixels`` maps an object-level id to its largest per-view pixel count (parts summed).
    """
    objects = []
    for node in layout.nodes:
        oid = layout.key_to_id[node.key]
        evaluated = (
            node.level == "object"
            and node.category not in STRUCTURE_CATEGORIES
            and max_pixels.get(oid, 0) >= min_visible_pixels
        )
        parent = layout.key_to_id[node.parent] if node.parent is not None else None
        objects.append(SceneObject(id=oid, name=node.name, level=node.level, parent=parent, category=node.category,
                                   evaluated=bool(evaluated)))
    return ObjectTable(objects)


def generate_scene(out_dir: Path, params: SyntheticParams) -> None:
    """Build the room of ``params`` and write the canonical scene into ``out_dir`` (an empty folder)."""
    out_dir = Path(out_dir)
    layout = build_room(params)
    cameras = camera_trajectory(params)
    packed = layout.packed()
    table = _object_table(layout, {}, 0)
    object_lookup = table.lookup("object")
    log.info("synthetic room seed %d: %.1f x %.1f x %.1f m, %d primitives, %d views of %dx%d",
             params.seed, *layout.size, len(layout.primitives), len(cameras), params.width, params.height)
    max_pixels: dict[int, int] = {}
    views_seen: dict[int, int] = {}
    for cam in tqdm(cameras, desc=f"synthetic room {params.seed}", unit="view", leave=False):
        rgb, prim, depth = render_view(packed, cam, params.supersample, params.ambient, params.shadows)
        if (prim < 0).any():
            raise Trace3DError(f"{out_dir}: view {cam.name} sees outside the room; the camera path leaves the room.")
        leaf = packed.leaf_ids[prim]
        write_frame(out_dir, cam.name, to_uint8(rgb), leaf.astype(np.uint16), depth)
        ids, counts = np.unique(object_lookup[leaf], return_counts=True)
        for oid, count in zip(ids.tolist(), counts.tolist()):
            max_pixels[oid] = max(max_pixels.get(oid, 0), count)
            views_seen[oid] = views_seen.get(oid, 0) + 1
    table = _object_table(layout, max_pixels, params.min_visible_pixels)
    write_cameras(out_dir, cameras)
    write_json(out_dir / "objects.json", table.to_json())
    categories: dict[str, int] = {}
    for o in table:
        if o.level == "object":
            categories[o.category] = categories.get(o.category, 0) + 1
    meta = {
        "source": "synthetic",
        "params": to_dict(params),
        "room": {
            "size_m": [round(v, 4) for v in layout.size],
            "num_objects": sum(1 for o in table if o.level == "object" and o.category not in STRUCTURE_CATEGORIES),
            "num_evaluated": len(table.evaluated_ids()),
            "num_parts": sum(1 for o in table if o.level == "part"),
            "num_groups": sum(1 for o in table if o.level == "group"),
            "num_primitives": len(layout.primitives),
            "objects_per_category": dict(sorted(categories.items())),
            "lights": [[round(float(v), 4) for v in light] for light in layout.lights],
        },
        "views": {"train": sum(c.split == "train" for c in cameras), "test": sum(c.split == "test" for c in cameras)},
        "object_max_visible_pixels": {str(k): v for k, v in sorted(max_pixels.items())},
        "object_views_visible": {str(k): v for k, v in sorted(views_seen.items())},
    }
    write_json(out_dir / "meta.json", meta)
