"""``trace3d bench mask-cues``: can the ``geometry`` mask source's cues tell objects apart? (a room with ground truth)

The geometry source (:mod:`trace3d.masks.geometry`) cuts and merges regions by the cues of neighbouring
pixel pairs: the relative depth jump across the pair (on the fitted scene's rendered depth), the crease
angle between the rendered normals, and the colour difference. Its coarse masks can only hold whole
objects where those cues are stronger across an object's outline than across the borders *inside* the
object. This benchmark measures that on a room with ground truth, without running the source:

* every 4-neighbour pixel pair of every ``stride``-th view that touches an evaluated object is classed by
  the ground truth as **within a part** (both pixels on one leaf), **between parts** of one object (two
  leaves of one object: a drawer and its cabinet, a shade and its stem) or an **object boundary** (two
  objects, or an object and the room: the lamp on the cabinet, the sofa against the wall);
* for each cue, the AUC of separating object boundaries from the pairs between parts and from the pairs
  within a part (0.5: no information; 1: a threshold separates them perfectly), and the share of each
  class above the source's own thresholds (``depth_edge``, ``crease_cut``);
* the depth jump twice: from the fitted scene's render (what the source sees) and from the scene's true
  depth (``depth/``, when the scene has it): the gap between the two is what the fit's blurred
  occlusions cost;
* for every masks folder given, the best IoU any one mask of a view reaches with each evaluated object
  visible in that view (at least ``min_pixels``): how often a view has a mask that *is* the object.

Reads the ground truth only to class and score; nothing here changes a mask.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from ..errors import Trace3DError
from ..scene import Scene

log = logging.getLogger(__name__)

CLASSES = ("within_part", "between_parts", "object_boundary")


def auc(positive: np.ndarray, negative: np.ndarray) -> float:
    """P(a positive score > a negative score) + P(equal) / 2 (Mann-Whitney, by ranks; nan if a side is empty)."""
    from scipy.stats import rankdata

    positive = np.asarray(positive, np.float64)
    negative = np.asarray(negative, np.float64)
    if len(positive) == 0 or len(negative) == 0:
        return float("nan")
    ranks = rankdata(np.concatenate([positive, negative]))
    n = len(positive)
    return float((ranks[:n].sum() - n * (n + 1) / 2) / (n * len(negative)))


def classify_pairs(leaf: np.ndarray, obj: np.ndarray, evaluated: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The class of every 4-neighbour pair (horizontal pairs first, then vertical; as
    :func:`trace3d.masks.geometry.pixel_pairs` orders them) and whether it counts.

    Args:
        leaf: [H, W] leaf ids (0: no object); obj: [H, W] the leaves' object ids; evaluated: [H, W] bool.
    Returns:
        class [E] int (index into :data:`CLASSES`) and use [E] bool (both pixels on something, at least one
        of them on an evaluated object).
    """
    classes, use = [], []
    for axis in (1, 0):
        size = leaf.shape[axis]
        lo, hi = np.arange(size - 1), np.arange(1, size)

        def take(a, i, axis=axis):
            return np.take(a, i, axis=axis)

        la, lb, oa, ob = take(leaf, lo), take(leaf, hi), take(obj, lo), take(obj, hi)
        cls = np.where(oa != ob, 2, np.where(la != lb, 1, 0))
        classes.append(cls.ravel())
        use.append(((la > 0) & (lb > 0) & (take(evaluated, lo) | take(evaluated, hi))).ravel())
    return np.concatenate(classes), np.concatenate(use)


def depth_jumps(depth: np.ndarray, empty: np.ndarray, reach: int) -> np.ndarray:
    """[E] the relative depth jump of every 4-neighbour pair (pair order of :func:`classify_pairs`); inf where
    either pixel is empty (the geometry source counts such a pair as a depth edge)."""
    from ..masks.geometry import inverse_depth_jump

    inv = np.where(empty, 0.0, 1.0 / np.maximum(depth, 1e-12))
    out = []
    for axis in (1, 0):
        size = depth.shape[axis]
        jump = inverse_depth_jump(inv, axis, reach)
        either = np.take(empty, np.arange(size - 1), axis=axis) | np.take(empty, np.arange(1, size), axis=axis)
        out.append(np.where(either, np.inf, jump).ravel())
    return np.concatenate(out)


def best_mask_iou(masks: np.ndarray, truth: np.ndarray) -> float:
    """The best IoU of any mask [M, H, W] with ``truth`` [H, W] (0 without masks)."""
    if len(masks) == 0:
        return 0.0
    inter = (masks & truth).sum(axis=(1, 2)).astype(np.float64)
    union = masks.sum(axis=(1, 2)) + truth.sum() - inter
    return float(np.max(inter / np.maximum(union, 1)))


def run_bench(room: Path, masks: list[Path] | None = None, stride: int = 4, min_pixels: int = 50) -> dict:
    """The cues' separability and the masks' object recall on ``room`` (module docstring).

    Args:
        room: a fitted room's results folder: scene/ (with instances/ and objects.json), gaussians/, and
            poses/ when the fit used estimated poses.
        masks: masks folders (``<frame>.npz``, any source) scored against the objects.
        stride: every ``stride``-th view of the scene.
    """
    from skimage.color import rgb2lab

    from ..masks import read_mask_npz
    from ..masks.geometry import GeometryParams, pixel_pairs, render_geometry
    from ..tracing.git import load_fitted

    start = time.process_time()
    root = Path(room)
    if not (root / "scene" / "cameras.json").is_file() or not (root / "gaussians" / "point_cloud.ply").is_file():
        raise Trace3DError(f"{root}: bench mask-cues needs a fitted room's results folder (scene/ and "
                           "gaussians/point_cloud.ply).")
    if stride < 1:
        raise Trace3DError(f"bench mask-cues: --stride must be >= 1, got {stride}.")
    scene = Scene.read(root / "scene")
    if not scene.has_instances or scene.objects is None:
        raise Trace3DError(f"{root / 'scene'}: bench mask-cues needs a scene with ground truth (instances/ and "
                           "objects.json).")
    poses = root / "poses" if (root / "poses").is_dir() else None
    model, cameras = load_fitted(scene, poses, root / "gaussians")
    params = GeometryParams()
    lookup = scene.objects.lookup("object")
    is_evaluated = np.zeros(len(lookup), bool)
    is_evaluated[[i for i in scene.objects.evaluated_ids() if i < len(lookup)]] = True
    cues: dict[str, list[np.ndarray]] = {"render_depth_jump": [], "true_depth_jump": [], "crease_deg": [],
                                         "colour": []}
    classes: list[np.ndarray] = []
    mask_dirs = [Path(m) for m in (masks or [])]
    recall: dict[str, list[float]] = {m.name if m.name != "masks" else m.parent.name + "/masks": []
                                      for m in mask_dirs}
    views = cameras[::stride]
    for cam in views:
        leaf = scene.instances(cam.name).astype(np.int64)
        leaf = np.where(leaf < len(lookup), leaf, 0)
        obj = lookup[leaf]
        evaluated = is_evaluated[obj]
        cls, use = classify_pairs(leaf, obj, evaluated)
        depth, normal, alpha = render_geometry(model, cam, params.near)
        empty = (alpha < params.min_alpha) | (depth <= 0)
        lab = rgb2lab(scene.image(cam.name))
        pairs = pixel_pairs(lab, depth, normal, alpha, cam.K, params)
        classes.append(cls[use])
        cues["render_depth_jump"].append(depth_jumps(depth, empty, params.depth_reach)[use])
        cues["crease_deg"].append(np.degrees(pairs.crease_near)[use])
        cues["colour"].append(pairs.colour[use])
        if scene.has_depth:
            true = scene.depth(cam.name).astype(np.float64)
            cues["true_depth_jump"].append(depth_jumps(true, true <= 0, params.depth_reach)[use])
        for folder, name in zip(mask_dirs, recall):
            path = folder / f"{cam.name}.npz"
            if not path.is_file():
                raise Trace3DError(f"{path}: missing; give bench mask-cues a masks folder of this room.")
            m, _ = read_mask_npz(path, cam.height, cam.width)
            for o in np.unique(obj[evaluated]):
                truth = obj == o
                if truth.sum() >= min_pixels:
                    recall[name].append(best_mask_iou(m, truth))
    cls = np.concatenate(classes)
    counts = {name: int((cls == k).sum()) for k, name in enumerate(CLASSES)}
    thresholds = {"render_depth_jump": params.depth_edge, "true_depth_jump": params.depth_edge,
                  "crease_deg": params.crease_cut, "colour": None}
    out_cues = {}
    for name, parts in cues.items():
        if not parts:
            continue
        values = np.concatenate(parts)
        by = [values[cls == k] for k in range(3)]
        entry = {"auc_boundary_vs_between_parts": auc(by[2], by[1]),
                 "auc_boundary_vs_within_part": auc(by[2], by[0]),
                 "median": {c: float(np.median(v)) if len(v) else None for c, v in zip(CLASSES, by)}}
        if thresholds[name] is not None:
            entry["threshold"] = thresholds[name]
            entry["share_above_threshold"] = {c: float(np.mean(v > thresholds[name])) if len(v) else None
                                              for c, v in zip(CLASSES, by)}
        out_cues[name] = entry
    result = {
        "room": str(root), "views": len(views), "stride": stride, "pairs": counts, "cues": out_cues,
        "masks": {name: {"object_views": len(v), "best_iou_mean": float(np.mean(v)) if v else None,
                         "share_iou_0.5": float(np.mean(np.array(v) >= 0.5)) if v else None,
                         "share_iou_0.8": float(np.mean(np.array(v) >= 0.8)) if v else None}
                  for name, v in recall.items()},
        "cpu_seconds": round(time.process_time() - start, 2),
    }
    log.info("bench mask-cues: %d views, %s pairs", len(views), counts)
    return result


def plot_cues(results: list[dict], path: Path) -> None:
    """Bars: each cue's AUC (object boundary vs between parts, vs within a part) per room."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..io import atomic_file

    names = sorted({c for r in results for c in r["cues"]})
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.2), sharey=True)
    for ax, key, title in zip(axes, ("auc_boundary_vs_between_parts", "auc_boundary_vs_within_part"),
                              ("object boundary vs between parts", "object boundary vs within a part")):
        width = 0.8 / max(len(results), 1)
        for i, r in enumerate(results):
            values = [r["cues"].get(n, {}).get(key, np.nan) for n in names]
            ax.bar(np.arange(len(names)) + i * width, values, width, label=Path(r["room"]).name)
        ax.axhline(0.5, color="k", lw=0.8, ls="--")
        ax.set_xticks(np.arange(len(names)) + 0.4 - width / 2, [n.replace("_", " ") for n in names], fontsize=7)
        ax.set_title(title, fontsize=9)
        ax.set_ylim(0.3, 1.0)
    axes[0].set_ylabel("AUC (0.5: no information)")
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    with atomic_file(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
