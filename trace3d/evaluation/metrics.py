"""Mask and image metrics of the evaluation (definitions in docs/evaluation.md).

All masks are [H, W] bool; images are [H, W, 3] floats in [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MAX_PSNR = 100.0  # dB, reported when the two images agree exactly inside the box


@dataclass(frozen=True)
class Confusion:
    """Pixel counts of a predicted mask against a ground-truth mask."""

    tp: int
    fp: int
    fn: int
    tn: int

    @property
    def pixels(self) -> int:
        return self.tp + self.fp + self.fn + self.tn

    @property
    def iou(self) -> float:
        """|P & G| / |P | G|; 1 when both masks are empty."""
        union = self.tp + self.fp + self.fn
        return self.tp / union if union else 1.0

    @property
    def accuracy(self) -> float:
        """(TP + TN) / pixels: the pixel accuracy SA3D and GaussianCut report as mAcc."""
        return (self.tp + self.tn) / self.pixels if self.pixels else 1.0

    @property
    def precision(self) -> float:
        """TP / (TP + FP): what the released Trace3D code reports as "mAcc"; 0 for an empty prediction."""
        predicted = self.tp + self.fp
        return self.tp / predicted if predicted else 0.0


def confusion(pred: np.ndarray, truth: np.ndarray) -> Confusion:
    """Counts of ``pred`` [H, W] bool against ``truth`` [H, W] bool."""
    pred = np.asarray(pred, bool)
    truth = np.asarray(truth, bool)
    if pred.shape != truth.shape:
        raise ValueError(f"confusion: prediction {pred.shape} and ground truth {truth.shape} differ in shape.")
    tp = int(np.count_nonzero(pred & truth))
    fp = int(np.count_nonzero(pred & ~truth))
    fn = int(np.count_nonzero(~pred & truth))
    return Confusion(tp, fp, fn, int(pred.size) - tp - fp - fn)


def iou(pred: np.ndarray, truth: np.ndarray) -> float:
    return confusion(pred, truth).iou


def grown_box(truth: np.ndarray, margin: int) -> tuple[int, int, int, int]:
    """(y0, y1, x0, x1), half-open, of ``truth``'s bounding box grown by ``margin`` pixels on every
    side and clipped to the image. Raises on an empty mask."""
    ys, xs = np.nonzero(np.asarray(truth, bool))
    if ys.size == 0:
        raise ValueError("grown_box: the ground-truth mask is empty.")
    h, w = truth.shape
    return (max(0, int(ys.min()) - margin), min(h, int(ys.max()) + 1 + margin),
            max(0, int(xs.min()) - margin), min(w, int(xs.max()) + 1 + margin))


def psnr(image: np.ndarray, reference: np.ndarray, box: tuple[int, int, int, int] | None = None) -> float:
    """PSNR in dB of ``image`` against ``reference`` ([H, W, 3] in [0, 1]) over ``box`` (all channels);
    :data:`MAX_PSNR` when they agree exactly."""
    image = np.asarray(image, np.float64)
    reference = np.asarray(reference, np.float64)
    if image.shape != reference.shape:
        raise ValueError(f"psnr: image {image.shape} and reference {reference.shape} differ in shape.")
    if box is not None:
        y0, y1, x0, x1 = box
        image, reference = image[y0:y1, x0:x1], reference[y0:y1, x0:x1]
    mse = float(np.mean((image - reference) ** 2)) if image.size else 0.0
    if mse <= 10.0 ** (-MAX_PSNR / 10.0):
        return MAX_PSNR
    return float(-10.0 * np.log10(mse))


def mean_or_none(values) -> float | None:
    """Mean of a sequence, None when empty (JSON null, left out of later means)."""
    values = [v for v in values if v is not None]
    return float(np.mean(values)) if values else None


def std_or_none(values) -> float | None:
    values = [v for v in values if v is not None]
    return float(np.std(values)) if values else None
