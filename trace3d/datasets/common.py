"""Helpers shared by the importers (:mod:`.replica`, :mod:`.llff`): block downscaling of images, label
maps and depth maps, the matching intrinsics, and validated camera-to-world inversion."""

from __future__ import annotations

import cv2
import numpy as np

from ..errors import Trace3DError


def downscale_rgb(rgb: np.ndarray, factor: int) -> np.ndarray:
    """[H, W, 3] -> [H // f, W // f, 3] by block averaging (right/bottom remainder cropped)."""
    if factor == 1:
        return rgb
    h, w = rgb.shape[0] // factor, rgb.shape[1] // factor
    return cv2.resize(rgb[: h * factor, : w * factor], (w, h), interpolation=cv2.INTER_AREA)


def _blocks(array: np.ndarray, factor: int) -> np.ndarray:
    """[H, W] -> [H // f, W // f, f * f] non-overlapping blocks (right/bottom remainder cropped)."""
    h, w = array.shape[0] // factor, array.shape[1] // factor
    cropped = array[: h * factor, : w * factor]
    return cropped.reshape(h, factor, w, factor).transpose(0, 2, 1, 3).reshape(h, w, factor * factor)


def downscale_labels(labels: np.ndarray, factor: int) -> np.ndarray:
    """[H, W] ids -> [H // f, W // f]: the most frequent id of each f x f block.

    Ties go to the id met first in row-major order within the block.
    """
    if factor == 1:
        return labels
    blocks = _blocks(labels, factor)  # [h, w, f*f]
    counts = (blocks[..., :, None] == blocks[..., None, :]).sum(-1)  # [h, w, f*f]
    pick = np.argmax(counts, axis=-1)
    return np.take_along_axis(blocks, pick[..., None], -1)[..., 0]


def downscale_depth(depth: np.ndarray, factor: int, max_ratio: float = 1.1) -> np.ndarray:
    """[H, W] z-depth (0 = invalid) -> [H // f, W // f] depth at each block's centre.

    The block's harmonic mean (exact on planes, where 1 / z is affine in the pixel coordinates);
    a block with an invalid pixel or a depth edge (max / min > ``max_ratio``) becomes 0 (invalid)
    rather than a point floating between two surfaces.
    """
    if factor == 1:
        return depth
    blocks = _blocks(depth, factor).astype(np.float64)
    valid = (blocks > 0).all(-1)
    safe = np.where(blocks > 0, blocks, 1.0)
    smooth = safe.max(-1) <= safe.min(-1) * max_ratio
    out = factor * factor / (1.0 / safe).sum(-1)
    out = np.where(valid & smooth, out, 0.0)
    return np.round(out).astype(depth.dtype) if np.issubdtype(depth.dtype, np.integer) else out.astype(depth.dtype)


def scale_intrinsics(K: np.ndarray, scale: float) -> np.ndarray:
    """[3, 3] intrinsics of the image resized by ``scale`` (pixel centres at +0.5, origin kept)."""
    out = np.array(K, dtype=np.float64)
    out[:2] *= scale
    return out


def rigid_inverse(camera_to_world: np.ndarray, where: str, tol: float = 1e-2) -> np.ndarray:
    """[4, 4] world-to-camera of a [4, 4] (or [3, 4]) camera-to-world pose.

    The rotation is re-orthonormalised (nearest rotation, by SVD) so that text files written with
    few decimals still give exact rigid transforms; a matrix further than ``tol`` from a rotation,
    or a reflection, is refused.
    """
    pose = np.asarray(camera_to_world, dtype=np.float64)
    if pose.shape == (4, 4) and np.abs(pose[3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > 1e-6:
        raise Trace3DError(f"{where}: the pose's last row is {pose[3].tolist()}, not (0, 0, 0, 1).")
    rotation = np.asarray(camera_to_world, dtype=np.float64)[:3, :3]
    centre = np.asarray(camera_to_world, dtype=np.float64)[:3, 3]
    if not (np.isfinite(rotation).all() and np.isfinite(centre).all()):
        raise Trace3DError(f"{where}: the pose has non-finite values.")
    u, _, vt = np.linalg.svd(rotation)
    nearest = u @ vt
    if np.linalg.det(nearest) < 0 or np.abs(nearest - rotation).max() > tol:
        raise Trace3DError(
            f"{where}: the pose's 3x3 block is not a rotation (det {np.linalg.det(rotation):.4f}, "
            f"distance to the nearest rotation {np.abs(nearest - rotation).max():.2e})."
        )
    w2c = np.eye(4)
    w2c[:3, :3] = nearest.T
    w2c[:3, 3] = -nearest.T @ centre
    return w2c


# --- image folders (llff, images) ----------------------------------------------------------------

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")


def list_images(folder) -> list:
    """The .png/.jpg/.jpeg files (``Path``) of ``folder`` sorted by name; their stems must be unique."""
    from pathlib import Path

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
