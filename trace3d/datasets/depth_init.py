"""Initial points from a scene's dataset depth (``init: depth``): the one home of depth-map back-projection.

COLMAP struggles on Replica's texture-poor rooms, so the 2DGS fit can start instead from the
dataset's own depth maps, back-projected into world space.  Works for any canonical scene with a
``depth/`` folder (z-depth, 16-bit millimetres, 0 = invalid).

- :func:`backproject_depth` / :func:`depth_points`: numpy world points (and colours) of a strided
  pixel grid; :func:`_backproject_depth_reference` is the per-pixel test oracle.
- :func:`depth_points_and_normals`: torch points, colours and depth-map normals of the train views,
  what :func:`trace3d.gaussians.init_from_depth` places its disks on.

The pixel-to-point formulas themselves live in :mod:`trace3d.geometry`.  Pixel convention: pixel
(i, j) has its centre at (i + 0.5, j + 0.5) in the coordinates that ``K`` maps to (see
:mod:`trace3d.scene`).
"""

from __future__ import annotations

import logging

import numpy as np
import torch
from tqdm import tqdm

from ..errors import SceneFormatError, Trace3DError
from ..geometry import backproject_pixels, depth_to_normal, depth_to_points
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
    return backproject_pixels(camera, rows, cols, z), np.stack([rows, cols], axis=1)


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


def depth_points_and_normals(
    scene: Scene,
    cameras=None,
    stride: int = 4,
    max_points: int | None = 100_000,
    seed: int = 0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Back-project ground-truth depth maps on a pixel grid of the given cameras.

    Args:
        scene: a scene with ``depth/`` maps.
        cameras: cameras to use (default: the scene's train cameras). Their names index the
            scene's images and depth maps, their poses place the points.
        stride: take every ``stride``-th pixel in x and y.
        max_points: randomly (seeded) keep at most this many points.
    Returns:
        points [P, 3] world, colours [P, 3] float in [0, 1], normals [P, 3] world (facing the
        camera that saw the point; zero where the depth gradient is undefined).
    """
    if not scene.has_depth:
        raise Trace3DError(f"{scene.root}: init 'depth' needs depth maps, but the scene has no depth/ folder.")
    if stride < 1:
        raise Trace3DError(f"depth init: stride must be >= 1, got {stride}.")
    cameras = scene.train_cameras if cameras is None else cameras
    all_points, all_colors, all_normals = [], [], []
    for cam in cameras:
        depth = torch.from_numpy(scene.depth(cam.name)).double()
        if depth.shape != (cam.height, cam.width):
            raise SceneFormatError(
                f"{scene.depth_path(cam.name)}: depth map is {depth.shape[1]}x{depth.shape[0]}, "
                f"camera is {cam.width}x{cam.height}."
            )
        rgb = torch.from_numpy(scene.image(cam.name)).double() / 255.0
        points_cam = depth_to_points(depth, cam.K)
        normals_cam = depth_to_normal(depth, cam.K)
        sel = torch.zeros_like(depth, dtype=torch.bool)
        sel[stride // 2 :: stride, stride // 2 :: stride] = True
        sel &= depth > 0
        # the finite-difference normal is undefined next to invalid depth
        valid = depth > 0
        neighbours_valid = torch.zeros_like(valid)
        neighbours_valid[1:-1, 1:-1] = valid[:-2, 1:-1] & valid[2:, 1:-1] & valid[1:-1, :-2] & valid[1:-1, 2:]
        normals_cam = normals_cam * neighbours_valid[..., None]
        c2w = torch.from_numpy(cam.camera_to_world)
        rot, trans = c2w[:3, :3], c2w[:3, 3]
        all_points.append(points_cam[sel] @ rot.T + trans)
        all_colors.append(rgb[sel])
        all_normals.append(normals_cam[sel] @ rot.T)
    points = torch.cat(all_points).float()
    colors = torch.cat(all_colors).float()
    normals = torch.cat(all_normals).float()
    if points.shape[0] == 0:
        raise Trace3DError(f"{scene.root}: depth init found no valid depth pixels in the train views.")
    if max_points is not None and points.shape[0] > max_points:
        generator = torch.Generator().manual_seed(int(seed))
        keep = torch.randperm(points.shape[0], generator=generator)[:max_points]
        points, colors, normals = points[keep], colors[keep], normals[keep]
    return points, colors, normals
