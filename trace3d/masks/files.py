"""The ``files`` mask source: masks computed elsewhere, read from the scene's ``masks/`` folder.

Per frame, either

* ``masks/<frame>.npz`` with ``"masks"`` [M, H, W] (bool, or integers / floats that are all 0 or 1)
  and optionally ``"scores"`` [M]; or
* ``masks/<frame>/<k>.png``, one binary PNG per mask (any non-zero pixel is inside), ``k`` an
  integer giving the order (0.png, 1.png, ...); every mask then gets ``default_score``.

If both exist for a frame the npz wins.  Every stack is validated against the image size.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from ..errors import SceneFormatError
from ..scene import Scene

log = logging.getLogger(__name__)


@dataclasses.dataclass
class FilesParams:
    """Parameters of the ``files`` mask source.

    Attributes:
        folder: folder holding the per-frame masks; default: the scene's ``masks/``.
        default_score: score given to masks that come without one (PNG masks, npz without scores).
    """

    folder: str | None = None
    default_score: float = 1.0


def read_mask_npz(
    path: str | Path, height: int, width: int, default_score: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """Read and validate one mask stack.

    Args:
        path: ``.npz`` with ``"masks"`` [M, H, W] and optional ``"scores"`` [M].
        height, width: the image size the stack must match.
    Returns:
        masks [M, H, W] bool and scores [M] float32 (``default_score`` where absent).
    Raises:
        SceneFormatError naming ``path`` when missing, unreadable or inconsistent.
    """
    path = Path(path)
    if not path.is_file():
        raise SceneFormatError(f"{path}: mask file is missing.")
    try:
        with np.load(path, allow_pickle=False) as data:
            if "masks" not in data.files:
                raise SceneFormatError(f"{path}: mask file has no 'masks' array (found {sorted(data.files)}).")
            masks = data["masks"]
            scores = data["scores"] if "scores" in data.files else None
    except SceneFormatError:
        raise
    except Exception as exc:  # zipfile / numpy raise several types for corrupt files
        raise SceneFormatError(f"{path}: mask file is corrupt or not an npz archive ({exc}).") from exc
    masks = _as_bool_stack(masks, path)
    if masks.shape[1:] != (height, width):
        raise SceneFormatError(
            f"{path}: mask stack is {masks.shape[2]}x{masks.shape[1]} but the image is {width}x{height}."
        )
    if scores is None:
        scores = np.full(len(masks), default_score, dtype=np.float32)
    else:
        scores = np.asarray(scores)
        if scores.shape != (len(masks),) or not np.issubdtype(scores.dtype, np.number):
            raise SceneFormatError(
                f"{path}: 'scores' must be {len(masks)} numbers (one per mask), got shape {scores.shape}."
            )
        scores = scores.astype(np.float32)
        if not np.isfinite(scores).all():
            raise SceneFormatError(f"{path}: 'scores' contains non-finite values.")
    return masks, scores


def _as_bool_stack(masks: np.ndarray, path: Path) -> np.ndarray:
    """[M, H, W] bool from a bool or 0/1 numeric array; raises naming ``path`` otherwise."""
    masks = np.asarray(masks)
    if masks.ndim != 3:
        raise SceneFormatError(f"{path}: 'masks' must be a [M, H, W] stack, got shape {masks.shape}.")
    if masks.dtype == bool:
        return masks
    if not np.issubdtype(masks.dtype, np.number):
        raise SceneFormatError(f"{path}: 'masks' has dtype {masks.dtype}; expected bool or 0/1 numbers.")
    if masks.size and not np.isin(masks, (0, 1)).all():
        raise SceneFormatError(f"{path}: 'masks' holds values other than 0 and 1; expected a binary stack.")
    return masks.astype(bool)


def read_mask_pngs(folder: str | Path, height: int, width: int) -> np.ndarray:
    """Read ``folder/<k>.png`` binary masks in the order of ``k`` as [M, H, W] bool."""
    folder = Path(folder)
    files = sorted(p for p in folder.iterdir() if not p.name.startswith("."))
    indexed = []
    for f in files:
        if f.suffix.lower() != ".png" or not f.stem.isdigit():
            raise SceneFormatError(f"{f}: unexpected file in a mask folder; masks must be named <k>.png, k an integer.")
        indexed.append((int(f.stem), f))
    indexed.sort()
    masks = np.zeros((len(indexed), height, width), dtype=bool)
    for i, (_, f) in enumerate(indexed):
        img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise SceneFormatError(f"{f}: mask PNG is corrupt or not an image.")
        if img.shape != (height, width):
            raise SceneFormatError(
                f"{f}: mask is {img.shape[1]}x{img.shape[0]} but the image is {width}x{height}."
            )
        masks[i] = img > 0
    return masks


def iter_file_masks(scene: Scene, params: FilesParams) -> Iterator[tuple[str, np.ndarray, np.ndarray]]:
    """Yield (frame name, masks [M, H, W] bool, scores [M] float32) for every frame of ``scene``."""
    folder = Path(params.folder) if params.folder else scene.root / "masks"
    if not folder.is_dir():
        raise SceneFormatError(
            f"{folder}: mask folder does not exist; the `files` mask source needs per-frame masks there "
            f"(<frame>.npz or <frame>/<k>.png)."
        )
    for cam in scene.cameras:
        npz = folder / f"{cam.name}.npz"
        png_dir = folder / cam.name
        if npz.is_file():
            masks, scores = read_mask_npz(npz, cam.height, cam.width, params.default_score)
        elif png_dir.is_dir():
            masks = read_mask_pngs(png_dir, cam.height, cam.width)
            scores = np.full(len(masks), params.default_score, dtype=np.float32)
        else:
            raise SceneFormatError(
                f"{npz}: mask file is missing for frame {cam.name!r} (expected {npz.name} or a folder "
                f"{png_dir.name}/ of <k>.png masks in {folder})."
            )
        yield cam.name, masks, scores
