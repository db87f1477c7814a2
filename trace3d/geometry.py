"""Small geometry shared across stages: quaternion rotations and depth back-projection.

Each helper has its one home here; the renderer (:mod:`trace3d.render.projection`), the Gaussian
container (:mod:`trace3d.gaussians`), the losses, the importers' depth initialisation
(:mod:`trace3d.datasets.depth_init`) and the dataset-pose mode of :mod:`trace3d.poses` import it.

Conventions: OpenCV cameras (x right, y down, z forward), pixel (row i, column j) has its centre at
(j + 0.5, i + 0.5) in the coordinates that ``K`` maps to, depth is camera z (not ray length).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from .scene import Camera


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices from quaternions.

    Args:
        quats: [..., 4] (w, x, y, z), any non-zero norm (normalised here).
    Returns:
        [..., 3, 3] rotations; for a splat its columns are the axes t_u, t_v, t_w.
    """
    q = F.normalize(quats, dim=-1)
    w, x, y, z = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]
    return torch.stack(rows, dim=-1).reshape(quats.shape[:-1] + (3, 3))


def depth_to_points(depth: Tensor, K: np.ndarray | Tensor) -> Tensor:
    """Back-project a depth map (camera z) to camera-space points.

    Args:
        depth: [H, W] depth along the optical axis.
        K: [3, 3] intrinsics (pixel centres at +0.5).
    Returns:
        [H, W, 3] points in camera space (OpenCV: x right, y down, z forward).
    """
    height, width = depth.shape
    K = torch.as_tensor(np.asarray(K) if not torch.is_tensor(K) else K, dtype=depth.dtype, device=depth.device)
    xs = torch.arange(width, dtype=depth.dtype, device=depth.device) + 0.5
    ys = torch.arange(height, dtype=depth.dtype, device=depth.device) + 0.5
    grid_y, grid_x = torch.meshgrid(ys, xs, indexing="ij")
    # K^-1 (x, y, 1) for a general upper-triangular K (with skew).
    fx, fy, cx, cy, skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    ray_y = (grid_y - cy) / fy
    ray_x = (grid_x - cx - skew * ray_y) / fx
    rays = torch.stack([ray_x, ray_y, torch.ones_like(ray_x)], dim=-1)
    return rays * depth[..., None]


def depth_to_normal(depth: Tensor, K: np.ndarray | Tensor) -> Tensor:
    """Surface normal of a depth map by central finite differences, in camera space.

    The normal is ``normalize(dP/dy x dP/dx)`` of the back-projected points P, which faces the camera
    (negative z for a fronto-parallel plane), matching the renderer's normal convention. The
    one-pixel border, where central differences are undefined, is zero.

    Args:
        depth: [H, W] depth along the optical axis.
        K: [3, 3] intrinsics.
    Returns:
        [H, W, 3] unit normals (zero on the border).
    """
    points = depth_to_points(depth, K)
    d_dx = points[1:-1, 2:] - points[1:-1, :-2]
    d_dy = points[2:, 1:-1] - points[:-2, 1:-1]
    normal = F.normalize(torch.cross(d_dy, d_dx, dim=-1), dim=-1)
    return F.pad(normal.permute(2, 0, 1), (1, 1, 1, 1)).permute(1, 2, 0)


def backproject_pixels(camera: Camera, rows: np.ndarray, cols: np.ndarray, z: np.ndarray) -> np.ndarray:
    """World points of the pixels (``rows``, ``cols``) [P] at camera depths ``z`` [P] (numpy).

    Returns:
        [P, 3] float64 world points ``c2w (z K^-1 (col + 0.5, row + 0.5, 1))``.
    """
    z = np.asarray(z, dtype=np.float64)
    pixels_h = np.stack([cols + 0.5, rows + 0.5, np.ones_like(z)], axis=1)  # [P, 3]
    cam_points = (pixels_h @ np.linalg.inv(camera.K).T) * z[:, None]  # [P, 3], camera z == depth
    c2w = camera.camera_to_world
    return cam_points @ c2w[:3, :3].T + c2w[:3, 3]
