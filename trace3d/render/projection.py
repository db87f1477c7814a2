"""Per-Gaussian projection of 2D Gaussian splats (2DGS) into one camera, in plain torch.

Everything here is differentiable with torch autograd; both the dense reference renderer and the
numba tile kernels consume its output, so the two back ends share one definition of the geometry.

Conventions (the formulas are written out in ``docs/2dgs-math.md``): OpenCV camera (x right, y down, z forward),
pixel centres at integer + 0.5.  A splat k has centre p, rotation R = [t_u | t_v | t_w] from its
quaternion, scales (s_u, s_v), opacity o.  Its *ray transform* is

    T = K [ s_u t_u^c | s_v t_v^c | p_c ]        (3x3; rows T_x, T_y, T_w)

and the ray through pixel (x, y) meets the splat's plane at disk coordinates (u, v) = (c_0, c_1) / c_2
with ``c = (x T_w - T_x) x (y T_w - T_y)``.  Expanding the cross product, c is affine in the pixel:

    c = A + x B + y D,   A = T_x x T_y,   B = T_y x T_w,   D = T_w x T_x

so a kernel needs nine coefficients per splat instead of a cross product per pixel.  The third column
of T is built as ``z * (means2d, 1)`` (which equals ``K p_c``) so that ``means2d`` sits in the autograd
graph and its gradient is the screen-space positional gradient used by density control.

Low-pass filter: 2DGS clamps sigma = 1/2 min(u^2 + v^2, 2 |pixel - centre|^2); we use the projected
centre of the splat, ``means2d``, as that centre (the 2DGS CUDA code uses the centre of the projected
unit ellipse; the two agree for the distant, sub-pixel disks the filter exists for).
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from ..errors import Trace3DError
from ..geometry import quat_to_rotmat  # noqa: F401  (re-exported by trace3d.render)
from ..scene import Camera
from .glue_kernels import camera_points, splat_frames

ALPHA_MIN = 1.0 / 255.0  # skip a pair whose alpha is below this
ALPHA_MAX = 0.99  # clamp alpha
TRANSMITTANCE_MIN = 1e-4  # stop blending a pixel once the transmittance would fall below this
FILTER_INV_SQUARE = 2.0  # object-space low-pass filter: 1 / (sqrt(2)/2 px)^2
BOX_MARGIN = 0.5  # pixels of slack around the analytic footprint (float rounding)


class Splats(NamedTuple):
    """A set of 2D Gaussian splats (activated parameters).

    Attributes:
        means: [N, 3] world positions.
        quats: [N, 4] rotations (w, x, y, z); normalised inside.
        scales: [N, 2] positive tangent scales (s_u, s_v).
        opacities: [N] opacities in (0, 1).
    """

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor


@dataclasses.dataclass
class Projected:
    """Per-Gaussian quantities in one camera (differentiable tensors except where noted).

    Attributes:
        ray_transforms: [N, 3, 3] T = K [s_u t_u^c | s_v t_v^c | p_c]; rows T_x, T_y, T_w.
        coeffs: [N, 9] (A, B, D) with c = A + x B + y D (see the module docstring).
        means2d: [N, 2] projected centres (pixels); the low-pass filter's centre.
        normals: [N, 3] camera-space unit normals, facing the camera.
        depths: [N] camera-space z of the centres (detached; the sort key).
        opacities: [N] opacities.
        boxes: [N, 4] int64 numpy (x0, y0, x1, y1), half-open pixel ranges clipped to the image
            that contain every pixel where the splat can reach alpha >= 1/255; empty when culled.
        visible: [N] bool, in front of the near plane with a non-empty box inside the image.
    """

    ray_transforms: Tensor
    coeffs: Tensor
    means2d: Tensor
    normals: Tensor
    depths: Tensor
    opacities: Tensor
    boxes: np.ndarray
    visible: Tensor

    def select(self, rows: Tensor) -> "Projected":
        """The splats ``rows`` ([R] int64, ascending) only, differentiably (the gradients of the
        others are zero)."""
        return Projected(self.ray_transforms.index_select(0, rows), self.coeffs.index_select(0, rows),
                         self.means2d.index_select(0, rows), self.normals.index_select(0, rows),
                         self.depths.index_select(0, rows), self.opacities.index_select(0, rows),
                         self.boxes[rows.cpu().numpy()], self.visible.index_select(0, rows))


def camera_tensors(camera: Camera, device: torch.device, dtype: torch.dtype) -> tuple[Tensor, Tensor, Tensor]:
    """The camera as tensors: K [3, 3], world-to-camera rotation [3, 3], translation [3]."""
    K = np.asarray(camera.K, dtype=np.float64)
    if K.shape != (3, 3) or not np.allclose(K[2], [0.0, 0.0, 1.0]):
        raise Trace3DError(f"camera {camera.name!r}: the renderer needs K with last row (0, 0, 1), got {K[2].tolist()}.")
    w2c = np.asarray(camera.world_to_camera, dtype=np.float64)
    to = dict(device=device, dtype=dtype)
    return torch.as_tensor(K, **to), torch.as_tensor(w2c[:3, :3], **to), torch.as_tensor(w2c[:3, 3], **to)


def check_splats(splats: Splats) -> int:
    """Validate shapes and dtypes of ``splats``; return N."""
    n = splats.means.shape[0] if splats.means.dim() == 2 else -1
    shapes = {"means": (n, 3), "quats": (n, 4), "scales": (n, 2), "opacities": (n,)}
    for name, shape in shapes.items():
        t = getattr(splats, name)
        if not isinstance(t, Tensor) or tuple(t.shape) != shape or n < 0:
            got = tuple(t.shape) if isinstance(t, Tensor) else type(t).__name__
            raise Trace3DError(f"render: splats.{name} must have shape {shape} (N from means), got {got}.")
        if not t.is_floating_point():
            raise Trace3DError(f"render: splats.{name} must be a floating-point tensor, got {t.dtype}.")
    return n


def project(splats: Splats, camera: Camera, near: float = 0.01) -> Projected:
    """Project splats into ``camera``.

    Args:
        splats: N splats.
        camera: pinhole camera (K with last row (0, 0, 1)).
        near: splats whose centre has camera z <= near are culled; pixels whose ray meets a splat's
            plane closer than ``near`` are skipped by the renderers.
    Returns:
        a :class:`Projected`; tensors on the device and dtype of ``splats.means``.
    """
    check_splats(splats)
    means = splats.means
    K, rot_cw, t_cw = camera_tensors(camera, means.device, means.dtype)
    # camera-space centres (no gradient), depths (1 where culled) and projected centres; T's third
    # column is K p_c = z (means2d, 1)
    p_cam, z_safe, means2d = camera_points(means, K, rot_cw, t_cw, near)
    z = p_cam[:, 2]
    in_front = z > near
    ray_t, coeffs, normal = splat_frames(splats.quats, splats.scales, means2d, z_safe, p_cam, K, rot_cw)

    boxes = footprint_boxes_fast(ray_t.detach(), means2d.detach(), splats.opacities.detach(), in_front,
                                 camera.width, camera.height, near)
    visible = in_front & torch.as_tensor((boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1]),
                                         device=means.device)
    return Projected(ray_t, coeffs, means2d, normal, z, splats.opacities, boxes, visible)



def _clipped_disk_range(a0, a1, a2, w0, w1, w2, rho, near):
    """Range of the screen coordinate ``(a . (u, v, 1)) / (w . (u, v, 1))`` over the part of the disk
    ``u^2 + v^2 <= rho^2`` whose depth ``w . (u, v, 1)`` is at least ``near`` (a disk that crosses the
    camera plane; ``a`` is the row T_x or T_y, ``w`` the row T_w).

    The coordinate is linear-fractional with a positive denominator on that convex set, so its
    extremes lie on the boundary: at a critical point of the arc (``P cos t + Q sin t = S``) that is
    in front of ``near``, or at an end of the chord cut by the plane ``depth = near``.  Returns
    (lo, hi), or (inf, -inf) when no part of the disk is that far in front.  Plain Python, compiled
    by numba for :func:`_boxes_kernel` (the numpy twin calls it directly)."""
    lo = math.inf
    hi = -math.inf
    p_ = a1 * w2 - a2 * w1
    q_ = a2 * w0 - a0 * w2
    s_ = -rho * (a1 * w0 - a0 * w1)
    amp = math.sqrt(p_ * p_ + q_ * q_)
    if amp > 0.0 and abs(s_) <= amp:
        base = math.atan2(q_, p_)
        spread = math.acos(min(max(s_ / amp, -1.0), 1.0))
        for t in (base + spread, base - spread):
            u = rho * math.cos(t)
            v = rho * math.sin(t)
            z = w0 * u + w1 * v + w2
            if z >= near:
                f = (a0 * u + a1 * v + a2) / z
                lo = min(lo, f)
                hi = max(hi, f)
    tilt = math.sqrt(w0 * w0 + w1 * w1)
    if tilt > 0.0 and abs(near - w2) <= rho * tilt:
        base = math.atan2(w1, w0)
        spread = math.acos(min(max((near - w2) / (rho * tilt), -1.0), 1.0))
        for t in (base + spread, base - spread):
            u = rho * math.cos(t)
            v = rho * math.sin(t)
            f = (a0 * u + a1 * v + a2) / near
            lo = min(lo, f)
            hi = max(hi, f)
    return lo, hi


_clipped_disk_range_nb = njit(cache=True)(_clipped_disk_range)

def footprint_boxes(ray_t: Tensor, means2d: Tensor, opacities: Tensor, in_front: Tensor,
                    width: int, height: int, near: float = 0.01) -> np.ndarray:
    """Pixel boxes that contain every pixel where a splat can reach alpha >= 1/255.

    alpha >= 1/255 needs sigma <= L = ln(255 o).  Either the ray meets the disk of radius
    r = sqrt(2 L) (bounded exactly by the tangent lines of its projected ellipse, from the dual
    conic T diag(r^2, r^2, -1) T^T), or the pixel lies within sqrt(L) pixels of the centre (the
    low-pass filter).  A disk that crosses the camera plane (its projection is unbounded) is
    bounded by the part of it at depth >= ``near``, the only part the renderers blend
    (:func:`_clipped_disk_range`); before, such disks took the whole image, and in a fit's early
    iterations a few hundred of them (Gaussians beside the camera, centres a few centimetres in
    front of its plane) were nine tenths of the tile kernels' work.

    Args:
        ray_t: [N, 3, 3] ray transforms; means2d: [N, 2]; opacities: [N]; in_front: [N] bool.
    Returns:
        [N, 4] int64 (x0, y0, x1, y1), half-open, clipped to the image; x1 <= x0 when culled.
    """
    n = ray_t.shape[0]
    boxes = np.zeros((n, 4), dtype=np.int64)
    if n == 0:
        return boxes
    T = ray_t.cpu().double().numpy()
    m2d = means2d.cpu().double().numpy()
    op = np.clip(opacities.cpu().double().numpy(), 0.0, None)
    ok = in_front.cpu().numpy() & (op > ALPHA_MIN)
    with np.errstate(divide="ignore", invalid="ignore"):
        level = np.where(ok, np.log(np.maximum(op, 1e-30) * 255.0), 0.0)
        r2 = 2.0 * level
        diag = np.stack([r2, r2, -np.ones_like(r2)], axis=-1)  # [N, 3]
        t_diag = T * diag[:, None, :]  # [N, 3, 3]

        def dual(i: int, k: int) -> np.ndarray:  # entry (i, k) of T diag T^T, [N]
            return (t_diag[:, i, :] * T[:, k, :]).sum(-1)

        c22 = dual(2, 2)
        ellipse = c22 < 0
        lo = np.empty((n, 2))
        hi = np.empty((n, 2))
        for axis in range(2):
            c02 = dual(axis, 2)
            c00 = dual(axis, axis)
            disc = np.sqrt(np.maximum(c02 * c02 - c00 * c22, 0.0))
            a = (c02 + disc) / c22
            b = (c02 - disc) / c22
            lo[:, axis] = np.where(ellipse, np.minimum(a, b), np.inf)
            hi[:, axis] = np.where(ellipse, np.maximum(a, b), -np.inf)
        rho = np.sqrt(np.maximum(r2, 0.0))
        for k in np.nonzero(ok & ~ellipse)[0]:
            w = T[k, 2]
            for axis in range(2):
                a = T[k, axis]
                lo[k, axis], hi[k, axis] = _clipped_disk_range(a[0], a[1], a[2], w[0], w[1], w[2], rho[k], near)
        filt = np.sqrt(np.maximum(level, 0.0) / (FILTER_INV_SQUARE / 2.0))
        lo = np.minimum(lo, m2d - filt[:, None]) - BOX_MARGIN
        hi = np.maximum(hi, m2d + filt[:, None]) + BOX_MARGIN
    lo = np.nan_to_num(lo, nan=-np.inf)
    hi = np.nan_to_num(hi, nan=np.inf)
    size = np.array([width, height], dtype=np.float64)
    # pixel i is inside when its centre i + 0.5 lies in [lo, hi]
    first = np.clip(np.ceil(np.clip(lo - 0.5, -1.0, size + 1.0)), 0, size).astype(np.int64)
    last = np.clip(np.floor(np.clip(hi - 0.5, -1.0, size + 1.0)) + 1, 0, size).astype(np.int64)
    boxes[:, 0:2] = first
    boxes[:, 2:4] = last
    boxes[~ok] = 0
    return boxes


@njit(parallel=True, cache=True)
def _boxes_kernel(T, m2d, op, in_front, width, height, alpha_min, margin, filter_half, near):
    n = T.shape[0]
    boxes = np.zeros((n, 4), np.int64)
    size = (float(width), float(height))
    for k in prange(n):
        o = float(op[k])
        if not in_front[k] or not o > alpha_min:
            continue
        level = np.log(max(o, 1e-30) * 255.0)
        r2 = 2.0 * level
        t20 = float(T[k, 2, 0])
        t21 = float(T[k, 2, 1])
        t22 = float(T[k, 2, 2])
        c22 = (t20 * r2) * t20 + (t21 * r2) * t21 + (t22 * -1.0) * t22
        filt = np.sqrt(max(level, 0.0) / filter_half)
        for axis in range(2):
            ti0 = float(T[k, axis, 0])
            ti1 = float(T[k, axis, 1])
            ti2 = float(T[k, axis, 2])
            if c22 < 0:
                c02 = (ti0 * r2) * t20 + (ti1 * r2) * t21 + (ti2 * -1.0) * t22
                c00 = (ti0 * r2) * ti0 + (ti1 * r2) * ti1 + (ti2 * -1.0) * ti2
                disc = np.sqrt(max(c02 * c02 - c00 * c22, 0.0))
                a = (c02 + disc) / c22
                b = (c02 - disc) / c22
                lo = min(a, b)
                hi = max(a, b)
            else:
                lo, hi = _clipped_disk_range_nb(ti0, ti1, ti2, t20, t21, t22, np.sqrt(max(r2, 0.0)), near)
            m = float(m2d[k, axis])
            lo = min(lo, m - filt) - margin
            hi = max(hi, m + filt) + margin
            if lo != lo:
                lo = -np.inf
            if hi != hi:
                hi = np.inf
            first = np.ceil(min(max(lo - 0.5, -1.0), size[axis] + 1.0))
            last = np.floor(min(max(hi - 0.5, -1.0), size[axis] + 1.0)) + 1.0
            boxes[k, axis] = int(min(max(first, 0.0), size[axis]))
            boxes[k, axis + 2] = int(min(max(last, 0.0), size[axis]))
    return boxes


def footprint_boxes_fast(ray_t: Tensor, means2d: Tensor, opacities: Tensor, in_front: Tensor,
                         width: int, height: int, near: float = 0.01) -> np.ndarray:
    """:func:`footprint_boxes` as a numba kernel (the numpy version is its tested twin)."""
    n = ray_t.shape[0]
    if n == 0:
        return np.zeros((0, 4), dtype=np.int64)
    T = np.ascontiguousarray(ray_t.detach().cpu().numpy())
    m2d = np.ascontiguousarray(means2d.detach().cpu().numpy())
    op = np.ascontiguousarray(opacities.detach().cpu().numpy())
    front = np.ascontiguousarray(in_front.cpu().numpy())
    return _boxes_kernel(T, m2d, op, front, int(width), int(height), ALPHA_MIN, BOX_MARGIN,
                         FILTER_INV_SQUARE / 2.0, float(near))


def pixel_centres(width: int, height: int, device: torch.device, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """Pixel centre coordinates x [H*W], y [H*W] (row-major), at integer + 0.5."""
    ys, xs = torch.meshgrid(torch.arange(height, device=device, dtype=dtype),
                            torch.arange(width, device=device, dtype=dtype), indexing="ij")
    return xs.reshape(-1) + 0.5, ys.reshape(-1) + 0.5
