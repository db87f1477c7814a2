"""Novel-view 2D instance segmentation (paper Tables 3 and 4): the lifted scene's masks of the
queried object at the scored views against the ground-truth masks; IoU and mAcc (pixel accuracy
(TP+TN)/pixels, or precision TP/(TP+FP) under the ``official`` protocol)."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..lifting import LiftedScene, ObjectQuery
from ..scene import Camera
from .metrics import confusion


def evaluate_nvs(lifted: LiftedScene, query: ObjectQuery, cameras: Sequence[Camera], truths: Sequence[np.ndarray],
                 accuracy: str) -> tuple[list[dict], list[np.ndarray]]:
    """Per-view scores and the predicted masks [H, W] bool, one per camera."""
    preds = lifted.object_masks(query, cameras) if cameras else []
    out = []
    for cam, pred, truth in zip(cameras, preds, truths):
        pred = np.asarray(pred, bool)
        if pred.shape != truth.shape:
            raise ValueError(f"nvs: the lifted scene returned a {pred.shape} mask for view {cam.name!r} of "
                             f"{truth.shape}.")
        c = confusion(pred, truth)
        out.append({"frame": cam.name, "iou": c.iou, "acc": c.accuracy if accuracy == "accuracy" else c.precision,
                    "pixels": int(truth.sum()), "predicted_pixels": int(pred.sum())})
    return out, [np.asarray(p, bool) for p in preds]
