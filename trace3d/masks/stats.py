"""Statistics of mask sets, for calibrating simulated masks against published descriptions of SAM.

:func:`view_statistics` measures one view's masks; :func:`mask_set_statistics` averages them over
the views of a scene; ``trace3d masks-stats`` prints them for a masks folder beside the calibration
targets :data:`CALIBRATION_TARGETS` (docs/masks_calibration.md gives their sources).  Nothing here reads a method's output or score: only masks, the patches made from
them by the patch step's defaults, and (for the per-object counts) the ground-truth instance maps.

Per view:

* ``masks``: number of masks;
* ``multi_covered``: share of pixels under >= 2 masks;
* ``uncovered``: share of pixels under no mask;
* ``nested``: share of masks that lie at least 90 % inside a larger mask (SAM's multimask output
  nests subpart / part / whole);
* ``enclosed_fine``: share of the finest masks (masks containing no other mask at 90 %) that have an
  enclosing larger mask;
* ``masks_per_object``: masks divided by visible ground-truth objects (object level, >= 32 px);
* ``patches``: patches after :func:`.patches.masks_to_patches` with :class:`.patches.PatchParams`
  defaults;
* ``patches_per_object``: patches whose pixels lie mostly in an object, per visible object;
* ``whole_fraction``: share of visible objects that some mask matches at IoU >= 0.5;
* ``objects``: visible ground-truth objects.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..errors import SceneFormatError
from ..scene import ObjectTable, Scene
from .files import read_mask_npz
from .nested import pairwise_intersections
from .patches import PatchParams, masks_to_patches, select_masks

log = logging.getLogger(__name__)

STATISTICS = (
    "masks", "multi_covered", "uncovered", "nested", "enclosed_fine", "masks_per_object", "patches",
    "patches_per_object", "whole_fraction", "objects",
)

# Calibration targets of the nested model on the default rooms (docs/masks_calibration.md gives the
# source of each): statistic -> (target, lowest accepted, highest accepted), means over views.
CALIBRATION_TARGETS: dict[str, tuple[float, float, float]] = {
    "masks_per_object": (4.0, 3.0, 5.0),
    "multi_covered": (0.50, 0.35, 0.65),
    "uncovered": (0.03, 0.01, 0.08),
    "nested": (0.60, 0.50, 0.75),
    "patches_per_object": (3.0, 2.5, 4.0),
    "whole_fraction": (0.85, 0.75, 0.92),
}


def check_targets(stats: dict[str, dict[str, float]], targets=None) -> dict[str, dict]:
    """Each calibration target beside the measured mean: {name: {target, low, high, measured, ok}}."""
    out = {}
    for name, (target, low, high) in (targets or CALIBRATION_TARGETS).items():
        measured = stats[name]["mean"]
        out[name] = {"target": target, "low": low, "high": high, "measured": measured,
                     "ok": bool(low <= measured <= high)}
    return out


def _containment(masks: np.ndarray) -> np.ndarray:
    """[M, M] bool: entry (a, b) true when mask a lies at least 90 % inside the larger mask b."""
    inter = pairwise_intersections(masks)
    area = np.diag(inter)
    inside = inter >= 0.9 * np.maximum(area[:, None], 1)
    larger = area[None, :] > area[:, None]
    return inside & larger


def view_statistics(
    masks: np.ndarray,
    instance_map: np.ndarray | None = None,
    objects: ObjectTable | None = None,
    patch_params: PatchParams | None = None,
    min_object_pixels: int = 32,
) -> dict[str, float]:
    """The statistics of one view's masks (module docstring).

    Args:
        masks: [M, H, W] bool.
        instance_map: [H, W] leaf ids (None: the per-object statistics are left out).
        objects: hierarchy (None: ids are objects).
        patch_params: the patch step's parameters (default: its defaults).
        min_object_pixels: objects with fewer visible pixels are not counted.
    """
    masks = np.asarray(masks, dtype=bool)
    M, H, W = masks.shape
    p = patch_params or PatchParams()
    cover = masks.sum(axis=0)
    out: dict[str, float] = {
        "masks": float(M),
        "multi_covered": float((cover >= 2).mean()),
        "uncovered": float((cover == 0).mean()),
    }
    if M:
        contained = _containment(masks)
        has_parent = contained.any(axis=1)
        has_child = contained.any(axis=0)
        out["nested"] = float(has_parent.mean())
        finest = ~has_child
        out["enclosed_fine"] = float(has_parent[finest].mean()) if finest.any() else 0.0
    else:
        out["nested"] = out["enclosed_fine"] = 0.0
    selected, _ = select_masks(masks, np.ones(len(masks), np.float32), p)
    patch_map, hierarchy = masks_to_patches(selected, p.min_patch_pixels, min_patch_width=p.min_patch_width,
                                            split_disconnected=p.split_disconnected)
    out["patches"] = float(hierarchy.num_patches)
    if instance_map is not None:
        leaf = np.asarray(instance_map).astype(np.int64)
        if objects is not None and len(objects):
            lut = np.arange(max(int(leaf.max()) + 1, 1), dtype=np.int64)
            table = objects.lookup("object")
            lut[: len(table)] = table[: len(lut)]
            obj = lut[leaf]
        else:
            obj = leaf.copy()
        obj[leaf == 0] = 0
        ids, inverse = np.unique(obj.ravel(), return_inverse=True)
        counts = np.bincount(inverse)
        visible = [(k, int(i)) for k, i in enumerate(ids) if i > 0 and counts[k] >= min_object_pixels]
        n = len(visible)
        out["objects"] = float(n)
        out["masks_per_object"] = float(M / n) if n else 0.0
        # patches per object: each patch goes to the object holding most of its pixels
        P = hierarchy.num_patches
        if P and n:
            joint = np.bincount(patch_map.ravel().astype(np.int64) * len(ids) + inverse,
                                minlength=(P + 1) * len(ids)).reshape(P + 1, len(ids))
            owner = joint[1:].argmax(axis=1)
            owned = np.bincount(owner, minlength=len(ids))
            out["patches_per_object"] = float(np.mean([owned[k] for k, _ in visible]))
        else:
            out["patches_per_object"] = 0.0
        flat = masks.reshape(M, -1)
        whole = 0
        for k, _ in visible:
            obj_pixels = inverse == k
            if M:
                inter = flat[:, obj_pixels].sum(axis=1)
                iou = inter / np.maximum(flat.sum(axis=1) + counts[k] - inter, 1)
                whole += bool(iou.max() >= 0.5)
        out["whole_fraction"] = float(whole / n) if n else 0.0
    return out


def mask_set_statistics(per_view: list[dict[str, float]]) -> dict[str, dict[str, float]]:
    """Mean, standard deviation, min and max over views of every statistic in ``per_view``."""
    keys = [k for k in STATISTICS if all(k in v for v in per_view)] if per_view else []
    out = {}
    for k in keys:
        values = np.array([v[k] for v in per_view], dtype=np.float64)
        out[k] = {"mean": float(values.mean()), "std": float(values.std()),
                  "min": float(values.min()), "max": float(values.max())}
    return out


def scene_statistics(scene: Scene, masks_dir: str | Path, patch_params: PatchParams | None = None) -> dict:
    """Statistics of a masks folder (``trace3d masks`` output) over every view of ``scene``.

    Returns:
        {"views": number of views, "statistics": :func:`mask_set_statistics` of the views}.
    """
    masks_dir = Path(masks_dir)
    if not masks_dir.is_dir():
        raise SceneFormatError(f"{masks_dir}: masks folder does not exist (run `trace3d masks` first).")
    per_view = []
    for cam in scene.cameras:
        masks, _ = read_mask_npz(masks_dir / f"{cam.name}.npz", cam.height, cam.width)
        inst = scene.instances(cam.name) if scene.has_instances else None
        per_view.append(view_statistics(masks, inst, scene.objects, patch_params))
    stats = mask_set_statistics(per_view)
    log.info("masks-stats: %d views, %.1f masks per view", len(per_view), stats.get("masks", {}).get("mean", 0.0))
    result = {"views": len(per_view), "statistics": stats}
    if all(name in stats for name in CALIBRATION_TARGETS):
        result["targets"] = check_targets(stats)
    return result
