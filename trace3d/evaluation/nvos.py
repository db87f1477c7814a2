"""NVOS evaluation (paper Table 4): scribbles on a reference view -> the lifted object's mask on the
one labelled target view, scored by IoU and pixel accuracy against the target mask.

An NVOS scene (``trace3d scene nvos``) keeps in ``meta.json["nvos"]`` the reference frame (a training
view), the target frame (the only test view), the target mask's file and point prompts sampled from
the positive and negative scribbles (as SA3D samples them). The method sees a scene through its 2D
instance maps, so the scribbles select instances there: on the reference view's map (the variant's
labels: consistent instance maps, patches or overlaid masks), every instance that a positive point
hits and no negative point hits is the object (if every hit instance is also hit by a negative, the
instances with more positive than negative hits). That mask is the query: the lifted scene's
:meth:`object_masks` gives the mask at the target view, scored against the ground truth with
IoU = TP / (TP + FP + FN) and accuracy = (TP + TN) / pixels, as SA3D and the paper report NVOS.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import cv2
import numpy as np

from ..errors import SceneFormatError, Trace3DError
from ..io import atomic_file, write_json
from ..scene import Scene, scene_name

log = logging.getLogger(__name__)


def scribble_mask(labels: np.ndarray, positive: np.ndarray, negative: np.ndarray) -> tuple[np.ndarray, list[int]]:
    """The reference mask the scribble points select on an instance map (module docstring).

    Args:
        labels: [H, W] int instance map (0 = unlabelled).
        positive, negative: [K, 2] (x, y) pixel coordinates.
    Returns:
        ([H, W] bool mask, the selected instance ids).
    """
    h, w = labels.shape

    def hits(points: np.ndarray) -> dict[int, int]:
        out: dict[int, int] = {}
        for x, y in np.asarray(points, np.float64).reshape(-1, 2):
            c, r = min(max(int(x), 0), w - 1), min(max(int(y), 0), h - 1)
            lab = int(labels[r, c])
            if lab > 0:
                out[lab] = out.get(lab, 0) + 1
        return out

    pos, neg = hits(positive), hits(negative)
    chosen = sorted(lab for lab in pos if lab not in neg)
    if not chosen:
        chosen = sorted(lab for lab, k in pos.items() if k > neg.get(lab, 0))
    return np.isin(labels, chosen) if chosen else np.zeros_like(labels, bool), chosen


def mask_scores(pred: np.ndarray, truth: np.ndarray) -> dict:
    """IoU and pixel accuracy of a predicted mask against the ground truth (both [H, W] bool)."""
    tp = int((pred & truth).sum())
    fp = int((pred & ~truth).sum())
    fn = int((~pred & truth).sum())
    tn = int(pred.size - tp - fp - fn)
    union = tp + fp + fn
    return {"iou": tp / union if union else 1.0, "accuracy": (tp + tn) / pred.size, "tp": tp, "fp": fp, "fn": fn,
            "tn": tn}


def run_evaluate_nvos(scene_dir: Path, poses_dir: Path | None, gaussians_dir: Path, lift_dir: Path, labels_dir: Path,
                      out_dir: Path, label: dict | None = None) -> dict:
    """Score the lifted scene of ``lift_dir`` on an NVOS scene; writes ``metrics.json`` and ``pictures.png``."""
    from ..lifting import ObjectQuery, load_lifted
    from .step import register_lifting_methods
    from ..tracing.git import load_fitted, load_label_maps

    start = time.perf_counter()
    scene = Scene.read(scene_dir)
    nvos = scene.meta.get("nvos")
    if not isinstance(nvos, dict):
        raise SceneFormatError(f"{Path(scene_dir) / 'meta.json'}: no 'nvos' entry; NVOS evaluation needs a scene "
                               f"imported with `trace3d scene nvos`.")
    for key in ("reference_frame", "target_frame", "target_mask", "positive_points", "negative_points"):
        if key not in nvos:
            raise SceneFormatError(f"{Path(scene_dir) / 'meta.json'}: nvos.{key} is missing.")
    mask_path = scene.root / nvos["target_mask"]
    truth = cv2.imread(str(mask_path), cv2.IMREAD_UNCHANGED)
    if truth is None:
        raise SceneFormatError(f"{mask_path}: the NVOS target mask is missing or unreadable.")
    truth = (truth if truth.ndim == 2 else truth[..., 0]) > 0
    model, cameras = load_fitted(scene, Path(poses_dir) if poses_dir else None, Path(gaussians_dir))
    by_name = {c.name: c for c in cameras}
    ref, target = nvos["reference_frame"], nvos["target_frame"]
    if ref not in by_name or target not in by_name:
        raise SceneFormatError(f"{scene.root}: NVOS reference {ref!r} or target {target!r} is not a camera of the scene.")
    if truth.shape != (by_name[target].height, by_name[target].width):
        raise SceneFormatError(f"{mask_path}: mask is {truth.shape[1]}x{truth.shape[0]}, the target view "
                               f"{by_name[target].width}x{by_name[target].height}.")
    train = [c for c in cameras if c.split == "train"]
    if ref not in {c.name for c in train}:
        raise Trace3DError(f"{scene.root}: the NVOS reference view {ref!r} is not a training view.")
    (ref_labels,) = load_label_maps(Path(labels_dir), [ref], "instance map")
    positive = np.asarray(nvos["positive_points"], np.float64).reshape(-1, 2)
    negative = np.asarray(nvos["negative_points"], np.float64).reshape(-1, 2)
    ref_mask, chosen = scribble_mask(ref_labels, positive, negative)
    register_lifting_methods()
    lifted = load_lifted(lift_dir, model, scene, train)
    lift_info = json.loads((Path(lift_dir) / "lift.json").read_text())
    if ref_mask.any():
        pred = lifted.object_masks(ObjectQuery(ref, ref_mask, 1), [by_name[target]])[0]
    else:  # the scribbles hit no instance: the method has nothing to lift, an empty prediction
        log.warning("nvos: the positive scribbles of %s hit no instance of the reference map", ref)
        pred = np.zeros_like(truth)
    scores = mask_scores(pred, truth)
    metrics = {
        "scene": scene_name(scene_dir, scene.meta),
        "variant": label or {},
        "protocol": "nvos",
        "lift": lift_info,
        "reference": ref,
        "target": target,
        "reference_instances": chosen,
        "reference_mask_pixels": int(ref_mask.sum()),
        "extraction": {"mIoU": None, "PSNR": None, "objects": 0, "views": 0},
        "nvs": {"mIoU": scores["iou"], "mAcc": scores["accuracy"], "mAcc_definition": "(TP+TN)/pixels",
                "objects": 1, "views": 1, **{k: scores[k] for k in ("tp", "fp", "fn", "tn")}},
        "seconds": time.perf_counter() - start,
    }
    out_dir = Path(out_dir)
    write_json(out_dir / "metrics.json", metrics)
    _picture(out_dir / "pictures.png", scene, ref, target, ref_mask, positive, negative, pred, truth, scores)
    log.info("nvos %s: reference %s (%d instances), target %s IoU %.3f, accuracy %.3f", metrics["scene"], ref,
             len(chosen), target, scores["iou"], scores["accuracy"])
    return metrics


def _picture(path: Path, scene: Scene, ref: str, target: str, ref_mask: np.ndarray, positive: np.ndarray,
             negative: np.ndarray, pred: np.ndarray, truth: np.ndarray, scores: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6))
    img = scene.image(ref).astype(np.float32) / 255.0
    img[ref_mask] = 0.5 * img[ref_mask] + 0.5 * np.array([1.0, 0.85, 0.0])
    axes[0].imshow(img)
    axes[0].scatter(positive[:, 0], positive[:, 1], s=6, c="lime", label="positive")
    axes[0].scatter(negative[:, 0], negative[:, 1], s=6, c="red", label="negative")
    axes[0].set_title(f"reference {ref}: scribble points, selected instances", fontsize=8)
    tgt = scene.image(target).astype(np.float32) / 255.0
    colour = np.zeros_like(tgt)
    colour[pred & truth] = (1.0, 0.85, 0.0)
    colour[pred & ~truth] = (1.0, 0.1, 0.1)
    colour[~pred & truth] = (0.1, 0.8, 0.1)
    hit = pred | truth
    tgt[hit] = 0.4 * tgt[hit] + 0.6 * colour[hit]
    axes[1].imshow(tgt)
    axes[1].set_title(f"target {target}: TP / FP / FN, IoU {scores['iou']:.3f}", fontsize=8)
    for ax in axes:
        ax.axis("off")
    fig.tight_layout()
    with atomic_file(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)
