"""The ``sam`` mask source: Segment Anything's automatic mask generator, as the official code runs it.

Runs ``segment_anything.SamAutomaticMaskGenerator`` (optional package, imported inside
:func:`iter_sam_masks` only) with the stability-score threshold 0.9, then post-processes each view
the way the public Trace3D / OmniSeg3D preprocessing does:

1. masks whose stability score is below the threshold are dropped (the generator already does
   this; repeated here so that records from any generator are treated alike);
2. masks of at most ``max_small_pixels`` = 96 pixels are dropped;
3. masks are sorted by area, smallest first, and a mask that is at least ``nest_coverage`` = 90 %
   covered by a later (larger) one is merged into it: the larger mask is extended to contain it
   completely, so that nearly nested masks become exactly nested (clean patch hierarchies).

Steps 1-3 are pure functions on mask stacks and are tested without SAM.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np
from tqdm import tqdm

from ..errors import Trace3DError
from ..scene import Scene

log = logging.getLogger(__name__)

MODEL_TYPES = ("default", "vit_h", "vit_l", "vit_b")
ALTERNATIVES = (
    "use the `simulated` mask source (from ground truth) or the `files` source (masks computed elsewhere) instead"
)


@dataclasses.dataclass
class SamParams:
    """Parameters of the ``sam`` mask source.

    Attributes:
        checkpoint: path of the SAM checkpoint (e.g. ``sam_vit_h_4b8939.pth``); required.
        model_type: ``vit_h`` | ``vit_l`` | ``vit_b`` | ``default`` (= vit_h), matching the checkpoint.
        device: torch device for the model.
        points_per_side, points_per_batch, pred_iou_thresh, box_nms_thresh, crop_n_layers:
            SamAutomaticMaskGenerator settings (its defaults).
        stability_score_thresh: masks below this stability score are dropped.
        max_small_pixels: masks with at most this many pixels are dropped.
        nest_coverage: a mask covered at least this much by a later (larger) one is merged into it.
    """

    checkpoint: str | None = None
    model_type: str = "vit_h"
    device: str = "cpu"
    points_per_side: int = 32
    points_per_batch: int = 64
    pred_iou_thresh: float = 0.88
    stability_score_thresh: float = 0.9
    box_nms_thresh: float = 0.7
    crop_n_layers: int = 0
    max_small_pixels: int = 96
    nest_coverage: float = 0.9

    # each field's range: refused on input and in the config schema (trace3d.params.check_ranges)
    RANGES = {"nest_coverage": "(0, 1]"}

    def __post_init__(self) -> None:
        if self.model_type not in MODEL_TYPES:
            raise ValueError(f"model_type must be one of {list(MODEL_TYPES)}, got {self.model_type!r}")
        if not 0.0 < self.nest_coverage <= 1.0:
            raise ValueError(f"nest_coverage must be in (0, 1], got {self.nest_coverage}")


# ----------------------------------------------------------------------------------------------
# Pure post-processing
# ----------------------------------------------------------------------------------------------


def records_to_stack(records: Sequence[dict], height: int, width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """SamAutomaticMaskGenerator output (``binary_mask`` mode) to arrays.

    Args:
        records: dicts with "segmentation" [H, W] bool, "predicted_iou", "stability_score".
    Returns:
        masks [M, H, W] bool, predicted_iou [M] float32, stability [M] float32.
    """
    if not records:
        return np.zeros((0, height, width), bool), np.zeros(0, np.float32), np.zeros(0, np.float32)
    masks = np.stack([np.asarray(r["segmentation"], dtype=bool) for r in records])
    iou = np.array([float(r["predicted_iou"]) for r in records], dtype=np.float32)
    stability = np.array([float(r["stability_score"]) for r in records], dtype=np.float32)
    return masks, iou, stability


def filter_stability(stability: np.ndarray, threshold: float) -> np.ndarray:
    """[M] bool keep-flags: stability score >= ``threshold``."""
    return np.asarray(stability) >= threshold


def filter_small(masks: np.ndarray, max_small_pixels: int) -> np.ndarray:
    """[M] bool keep-flags: more than ``max_small_pixels`` pixels (masks [M, H, W])."""
    return masks.sum(axis=(1, 2)) > max_small_pixels


def nest_covered_masks(masks: np.ndarray, coverage: float = 0.9) -> tuple[np.ndarray, np.ndarray]:
    """Sort by area (smallest first) and merge each mask into every later mask covering it.

    For masks in ascending-area order, mask ``m`` is OR-ed into each later mask ``l`` with
    ``|m & l| > coverage * |m|`` (the later masks as already extended by earlier merges).

    Args:
        masks: [M, H, W] bool.
    Returns:
        nested masks [M, H, W] bool (ascending original area) and order [M] (indices into the input).
    """
    M = len(masks)
    if M == 0:
        return masks.copy(), np.zeros(0, dtype=np.int64)
    order = np.argsort(masks.sum(axis=(1, 2)), kind="stable")
    out = masks[order].copy()
    flat = out.reshape(M, -1)
    for m in range(M - 1):
        area = flat[m].sum()
        if area == 0:
            continue
        overlap = (flat[m + 1:] & flat[m]).sum(axis=1)
        covering = np.nonzero(overlap > coverage * area)[0] + m + 1
        if len(covering):
            flat[covering] |= flat[m]
    return out, order


def _nest_covered_masks_reference(masks: np.ndarray, coverage: float = 0.9) -> np.ndarray:
    """Loop twin of :func:`nest_covered_masks` (returns the nested stack only)."""
    items = sorted(range(len(masks)), key=lambda i: (int(masks[i].sum()), i))
    out = [masks[i].copy() for i in items]
    for m in range(len(out)):
        for later in range(m + 1, len(out)):
            if out[m].sum() and (out[m] & out[later]).sum() > coverage * out[m].sum():
                out[later] = out[later] | out[m]
    return np.stack(out) if out else masks.copy()


def postprocess(
    masks: np.ndarray, predicted_iou: np.ndarray, stability: np.ndarray, params: SamParams
) -> tuple[np.ndarray, np.ndarray]:
    """Stability filter, small-mask filter, nesting (module docstring).

    Returns:
        masks [M', H, W] bool (ascending area) and scores [M'] float32 (predicted IoU).
    """
    keep = filter_stability(stability, params.stability_score_thresh) & filter_small(masks, params.max_small_pixels)
    masks, predicted_iou = masks[keep], predicted_iou[keep]
    nested, order = nest_covered_masks(masks, params.nest_coverage)
    return nested, predicted_iou[order].astype(np.float32)


# ----------------------------------------------------------------------------------------------
# Running SAM
# ----------------------------------------------------------------------------------------------


def check_available(params: SamParams) -> None:
    """Raise one Trace3DError naming everything missing for the ``sam`` source (package, checkpoint)."""
    problems = []
    try:
        import segment_anything  # noqa: F401
    except ImportError:
        problems.append(
            "the `segment_anything` package is not installed "
            "(pip install git+https://github.com/facebookresearch/segment-anything.git)"
        )
    if params.checkpoint is None:
        problems.append("no SAM checkpoint is configured (set masks params `checkpoint` to e.g. sam_vit_h_4b8939.pth)")
    elif not Path(params.checkpoint).is_file():
        problems.append(f"the SAM checkpoint file {params.checkpoint} does not exist")
    if problems:
        raise Trace3DError(f"the `sam` mask source cannot run: {' and '.join(problems)}; {ALTERNATIVES}.")


def iter_sam_masks(scene: Scene, params: SamParams) -> Iterator[tuple[str, np.ndarray, np.ndarray]]:
    """Yield (frame name, masks [M, H, W] bool, scores [M] float32) for every frame, from SAM."""
    check_available(params)
    from segment_anything import SamAutomaticMaskGenerator, sam_model_registry

    log.info("loading SAM %s from %s on %s", params.model_type, params.checkpoint, params.device)
    model = sam_model_registry[params.model_type](checkpoint=params.checkpoint)
    model.to(device=params.device)
    generator = SamAutomaticMaskGenerator(
        model,
        points_per_side=params.points_per_side,
        points_per_batch=params.points_per_batch,
        pred_iou_thresh=params.pred_iou_thresh,
        stability_score_thresh=params.stability_score_thresh,
        box_nms_thresh=params.box_nms_thresh,
        crop_n_layers=params.crop_n_layers,
        output_mode="binary_mask",
    )
    for cam in tqdm(scene.cameras, desc="SAM masks", unit="view"):
        records = generator.generate(scene.image(cam.name))
        masks, iou, stability = records_to_stack(records, cam.height, cam.width)
        masks, scores = postprocess(masks, iou, stability, params)
        yield cam.name, masks, scores
