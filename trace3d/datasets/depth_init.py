"""Initial points from a scene's dataset depth (``init: depth``).

COLMAP struggles on Replica's texture-poor rooms, so the 2DGS fit can start instead from the
dataset's own depth maps, back-projected into world space.  Works for any canonical scene with a
``depth/`` folder (z-depth, 16-bit millimetres, 0 = invalid).

Pixel convention: pixel (i, j) has its centre at (i + 0.5, j + 0.5) in the coordinates that ``K``
maps to (see :mod:`trace3d.scene`).
"""

from __future__ import annotations

import logging

import numpy as np
from tqdm import tqdm

from ..errors import SceneFormatError
from ..scene import Camera, Scene

log = logging.getLogger(__name__)


def backproject_depth(camera: Camera, depth: np.ndarray, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """World points of one depth map, sampled every ``stride`` pixels in x and y.

    Args:
        camera: the view (OpenCV convention).
        depth: [H, W] z-depth in scene units, 0 (or non-finite) where invalid.
        stride: keep pixels whose row and column are multiples of ``stride``.
    Returns:
        xyz [P, 3] float64 world points and pixel indices [P, 2] int64 as (row, col) of the kept pixels.
    """
    if depth.shape != (camera.height, camera.width):
        raise ValueError(f"depth {depth.shape} does not match camera {camera.height}x{camera.width}")
    rows, cols = np.mgrid[0 : camera.height : stride, 0 : camera.width : stride]
    rows, cols = rows.ravel(), cols.ravel()
    z = depth[rows, cols].astype(np.float64)
    keep = np.isfinite(z) & (z > 0)
    rows, cols, z = rows[keep], cols[keep], z[keep]
    pixels_h = np.stack([cols + 0.5, rows + 0.5, np.ones_like(z)], axis=1)  # [P, 3]
    cam_points = (pixels_h @ np.linalg.inv(camera.K).T) * z[:, None]  # [P, 3], camera z == depth
    c2w = camera.camera_to_world
    xyz = cam_points @ c2w[:3, :3].T + c2w[:3, 3]
    return xyz, np.stack([rows, cols], axis=1)


def _backproject_depth_reference(camera: Camera, depth: np.ndarray, stride: int = 1) -> np.ndarray:
    """Slow per-pixel twin of :func:`backproject_depth` (test oracle): [P, 3] world points."""
    out = []
    fx, fy, cx, cy = camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]
    skew = camera.K[0, 1]
    R, t = camera.rotation, camera.translation
    for row in range(0, camera.height, stride):
        for col in range(0, camera.width, stride):
            z = float(depth[row, col])
            if not np.isfinite(z) or z <= 0:
                continue
            y_cam = (row + 0.5 - cy) / fy * z
            x_cam = ((col + 0.5 - cx) - skew * y_cam / z) / fx * z
            p_cam = np.array([x_cam, y_cam, z])
            out.append(R.T @ (p_cam - t))  # world = R^T (p_cam - t)
    return np.array(out, dtype=np.float64).reshape(-1, 3)


def depth_points(
    scene: Scene,
    stride: int = 8,
    split: str | None = "train",
    max_points: int | None = None,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Back-project the dataset depth of a scene's views into one coloured point cloud.

    Args:
        scene: a canonical scene with ``depth/``.
        stride: pixel step in x and y within each view (8 on 640x480 gives 4800 points per view).
        split: use only the views of this split (``"train"`` by default so test views never leak
            into the fit); ``None`` uses every view.
        max_points: if set, a seeded uniform subsample of at most this many points.
        seed: seed of that subsample.
    Returns:
        xyz [P, 3] float32 world points and rgb [P, 3] uint8 colours of the source pixels.
    """
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    if not scene.has_depth:
        raise SceneFormatError(
            f"{scene.root / 'depth'}: the scene has no depth folder, so `init: depth` cannot be used "
            "(use `init: sfm`)."
        )
    cameras = scene.cameras if split is None else scene.split(split)
    if not cameras:
        raise SceneFormatError(f"{scene.root / 'cameras.json'}: no views in split {split!r} to back-project.")
    all_xyz, all_rgb = [], []
    for cam in tqdm(cameras, desc="depth points", unit="view", disable=len(cameras) < 20):
        depth = scene.depth(cam.name)
        if depth.shape != (cam.height, cam.width):
            raise SceneFormatError(
                f"{scene.depth_path(cam.name)}: depth map is {depth.shape[1]}x{depth.shape[0]} "
                f"but the camera is {cam.width}x{cam.height}."
            )
        xyz, pix = backproject_depth(cam, depth, stride)
        rgb = scene.image(cam.name)[pix[:, 0], pix[:, 1]]
        all_xyz.append(xyz.astype(np.float32))
        all_rgb.append(rgb.astype(np.uint8))
    xyz = np.concatenate(all_xyz, axis=0)
    rgb = np.concatenate(all_rgb, axis=0)
    if xyz.shape[0] == 0:
        raise SceneFormatError(f"{scene.root / 'depth'}: every depth value is 0 (invalid); no points to start from.")
    if max_points is not None and xyz.shape[0] > max_points:
        keep = np.sort(np.random.default_rng(seed).choice(xyz.shape[0], size=max_points, replace=False))
        xyz, rgb = xyz[keep], rgb[keep]
    log.info("depth init: %d points from %d views (stride %d)", xyz.shape[0], len(cameras), stride)
    return xyz, rgb
