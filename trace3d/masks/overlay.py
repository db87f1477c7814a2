"""Overlaid label maps: every view's mask stack painted into one label per pixel (topmost wins).

This is how lifting methods without patches consume SAM-style masks (EgoLifter-style baseline):
the masks of a view are painted largest first, so a smaller mask lying on a larger one is on top
and wins its pixels (the usual way automatic SAM masks are drawn). Label ``k + 1`` is mask ``k`` of
the view's stack; 0 is no mask. Labels mean nothing across views: that inconsistency is what
the baseline is exposed to, where Trace3D merges patches first.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..errors import SceneFormatError
from ..io import write_json
from ..scene import Scene, write_u16
from .files import read_mask_npz

log = logging.getLogger(__name__)


def overlay_masks(masks: np.ndarray) -> np.ndarray:
    """One label per pixel from a mask stack.

    Args:
        masks: [M, H, W] bool.
    Returns:
        [H, W] uint16: ``k + 1`` where mask ``k`` is the smallest mask covering the pixel (ties: the
        later mask in the stack), 0 where no mask covers it.
    """
    masks = np.asarray(masks, dtype=bool)
    if masks.ndim != 3:
        raise ValueError(f"overlay_masks: masks must be [M, H, W], got shape {masks.shape}.")
    if len(masks) >= 65535:
        raise ValueError(f"overlay_masks: {len(masks)} masks do not fit 16-bit labels.")
    labels = np.zeros(masks.shape[1:], dtype=np.uint16)
    areas = masks.reshape(len(masks), -1).sum(axis=1)
    # Largest first; among equal areas the later mask is painted last (stable sort of -area).
    for k in np.argsort(-areas, kind="stable"):
        labels[masks[k]] = k + 1
    return labels


def run_overlay(scene: Scene, masks_dir: Path, out_dir: Path) -> dict:
    """The ``overlay`` step: ``<frame>.png`` (16-bit overlaid labels) for every training view of
    ``scene`` from the mask stacks in ``masks_dir``, and ``overlay.json``."""
    masks_dir, out_dir = Path(masks_dir), Path(out_dir)
    if not masks_dir.is_dir():
        raise SceneFormatError(f"{masks_dir}: masks folder does not exist (run the masks step first).")
    out_dir.mkdir(parents=True, exist_ok=True)
    covered, counts = [], []
    for cam in scene.train_cameras:
        masks, _ = read_mask_npz(masks_dir / f"{cam.name}.npz", cam.height, cam.width)
        labels = overlay_masks(masks)
        write_u16(out_dir / f"{cam.name}.png", labels)
        covered.append(float((labels > 0).mean()))
        counts.append(int(len(np.unique(labels[labels > 0]))))
    report = {"views": len(covered), "mean_labelled_fraction": float(np.mean(covered)) if covered else 0.0,
              "mean_labels_per_view": float(np.mean(counts)) if counts else 0.0,
              "rule": "masks painted largest first: the smallest covering mask wins a pixel"}
    write_json(out_dir / "overlay.json", report)
    log.info("overlay: %d views, %.1f labels per view, %.1f %% of pixels labelled", report["views"],
             report["mean_labels_per_view"], 100 * report["mean_labelled_fraction"])
    return report
