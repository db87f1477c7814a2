"""Helpers shared by the importers (replica.py, llff.py, images.py): image listing, resampling,
intrinsics scaling and the every-n-th-view test split."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..errors import Trace3DError

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")


def list_images(folder: Path) -> list[Path]:
    """The .png/.jpg/.jpeg files of ``folder`` sorted by name; their stems must be unique."""
    folder = Path(folder)
    if not folder.is_dir():
        raise Trace3DError(f"{folder}: image folder is missing (set images_factor to a folder that exists).")
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS)
    if not files:
        raise Trace3DError(f"{folder}: contains no .png/.jpg images.")
    stems = [p.stem for p in files]
    if len(set(stems)) != len(stems):
        dup = sorted({s for s in stems if stems.count(s) > 1})
        raise Trace3DError(f"{folder}: image names are not unique without their extension ({', '.join(dup)}).")
    return files


def every_nth_split(names: list[str], test_every: int) -> dict[str, str]:
    """Split by position: 0, n, 2n ... are ``test`` (n = ``test_every``; 0 = all ``train``)."""
    return {name: "test" if test_every and k % test_every == 0 else "train" for k, name in enumerate(names)}


def downscale_rgb(rgb: np.ndarray, factor: int) -> np.ndarray:
    """[H, W, 3] -> [H // f, W // f, 3] by block averaging (right/bottom remainder cropped)."""
    if factor == 1:
        return rgb
    h, w = rgb.shape[0] // factor, rgb.shape[1] // factor
    return cv2.resize(rgb[: h * factor, : w * factor], (w, h), interpolation=cv2.INTER_AREA)


def scale_intrinsics(K: np.ndarray, scale: float) -> np.ndarray:
    """[3, 3] intrinsics of the image resized by ``scale`` (pixel centres at +0.5, origin kept)."""
    out = np.array(K, dtype=np.float64)
    out[:2] *= scale
    return out
