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
import functools
import math
from typing import NamedTuple

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from ..errors import Trace3DError
from ..geometry import quat_to_rotmat  # noqa: F401  (re-exported by trace3d.render)
from ..scene import Camera
from .kernels.glue import _camera_axes_at, _camera_point, _ray_rows, camera_points, splat_frames, use_fused

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


def _check_intrinsics(K: np.ndarray, name: str) -> None:
    if K.shape != (3, 3) or not np.allclose(K[2], [0.0, 0.0, 1.0]):
        raise Trace3DError(f"camera {name!r}: the renderer needs K with last row (0, 0, 1), got {K[2].tolist()}.")


def camera_tensors(camera: Camera, device: torch.device, dtype: torch.dtype) -> tuple[Tensor, Tensor, Tensor]:
    """The camera as tensors: K [3, 3], world-to-camera rotation [3, 3], translation [3]."""
    K = np.asarray(camera.K, dtype=np.float64)
    _check_intrinsics(K, camera.name)
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


@njit(cache=True, inline="always")
def _axis_range(ti0, ti1, ti2, t20, t21, t22, c22, r2, m, filt, size, margin, near):
    """The half-open pixel range (first, last) of one axis of a splat's footprint box (the body of
    :func:`_boxes_kernel`, shared with :func:`_visibility_kernel`)."""
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
    lo = min(lo, m - filt) - margin
    hi = max(hi, m + filt) + margin
    if lo != lo:
        lo = -np.inf
    if hi != hi:
        hi = np.inf
    first = np.ceil(min(max(lo - 0.5, -1.0), size + 1.0))
    last = np.floor(min(max(hi - 0.5, -1.0), size + 1.0)) + 1.0
    return int(min(max(first, 0.0), size)), int(min(max(last, 0.0), size))


@njit(cache=True, inline="always")
def _box(t00, t01, t02, t10, t11, t12, t20, t21, t22, m0, m1, o, width, height, margin, filter_half, near):
    """(x0, y0, x1, y1) of a splat in front of the camera with opacity above the cut-off."""
    level = np.log(max(o, 1e-30) * 255.0)
    r2 = 2.0 * level
    c22 = (t20 * r2) * t20 + (t21 * r2) * t21 + (t22 * -1.0) * t22
    filt = np.sqrt(max(level, 0.0) / filter_half)
    x0, x1 = _axis_range(t00, t01, t02, t20, t21, t22, c22, r2, m0, filt, float(width), margin, near)
    y0, y1 = _axis_range(t10, t11, t12, t20, t21, t22, c22, r2, m1, filt, float(height), margin, near)
    return x0, y0, x1, y1


@njit(parallel=True, cache=True)
def _boxes_kernel(T, m2d, op, in_front, width, height, alpha_min, margin, filter_half, near):
    n = T.shape[0]
    boxes = np.zeros((n, 4), np.int64)
    for k in prange(n):
        o = float(op[k])
        if not in_front[k] or not o > alpha_min:
            continue
        x0, y0, x1, y1 = _box(float(T[k, 0, 0]), float(T[k, 0, 1]), float(T[k, 0, 2]), float(T[k, 1, 0]),
                              float(T[k, 1, 1]), float(T[k, 1, 2]), float(T[k, 2, 0]), float(T[k, 2, 1]),
                              float(T[k, 2, 2]), float(m2d[k, 0]), float(m2d[k, 1]), o, width, height, margin,
                              filter_half, near)
        boxes[k, 0] = x0
        boxes[k, 1] = y0
        boxes[k, 2] = x1
        boxes[k, 3] = y1
    return boxes


PREFILTER_MARGIN = 4.0  # pixels: > the low-pass filter's reach sqrt(ln 255) = 2.35 plus BOX_MARGIN, plus slack


def frustum_planes(K: np.ndarray, width: int, height: int, margin: float = PREFILTER_MARGIN) -> np.ndarray:
    """[4, 3] unit inward normals (camera space) of the four planes through the camera centre and the
    edges of the ``width`` x ``height`` image of intrinsics K widened by ``margin`` pixels on every
    side: a camera-space point in front of the camera projects inside that rectangle iff its dot
    product with every normal is >= 0."""
    lo_x, lo_y, hi_x, hi_y = -margin, -margin, width + margin, height + margin
    # the corners' rays K^-1 (u, v, 1), in order around the rectangle, and the centre's
    corners = np.array([[lo_x, hi_x, hi_x, lo_x, width / 2.0],
                        [lo_y, lo_y, hi_y, hi_y, height / 2.0],
                        [1.0, 1.0, 1.0, 1.0, 1.0]])
    rays = np.linalg.solve(np.asarray(K, np.float64), corners).T
    planes = np.cross(rays[:4], rays[[1, 2, 3, 0]])
    planes /= np.linalg.norm(planes, axis=1, keepdims=True)
    planes *= np.sign(planes @ rays[4])[:, None]
    return planes


@njit(cache=True, inline="always")
def _outside_frustum(p0, p1, p2, planes, radius):
    """Whether the ball of ``radius`` around camera-space (p0, p1, p2) lies wholly outside one of the
    planes (False for NaN: undecided)."""
    for i in range(4):
        if planes[i, 0] * p0 + planes[i, 1] * p1 + planes[i, 2] * p2 < -radius:
            return True
    return False


@njit(parallel=True, cache=True)
def _visibility_kernel(means, quats, scales, op, K, R, t, near, near32, width, height, alpha_min, margin,
                       filter_half, planes, visible):
    """``project(...).visible`` in one pass without its outputs: per Gaussian the camera point (as
    ``_points_forward``), the rows of T (as ``_frames_forward``) and the footprint box (as
    :func:`_boxes_kernel`), with every intermediate the projection stores rounded to the splats'
    float32 where it rounds it, so the answer is the projection's bit for bit (tested).

    Before the rows of T, a conservative test: the disk lies in the ball of radius
    sqrt(2 ln(255 o)) max(s_u, s_v) around its centre, and the low-pass filter reaches less than
    ``PREFILTER_MARGIN`` pixels from the projected centre, so a Gaussian whose ball lies wholly outside
    the frustum of the image widened by that margin (``planes``, :func:`frustum_planes`) cannot reach
    a pixel: it is not visible, and the exact test is skipped (most Gaussians a view does not see)."""
    for g in prange(means.shape[0]):
        _visibility_of(means, quats, scales, op, K, R, t, near, near32, width, height, alpha_min, margin,
                       filter_half, planes, visible, g)


@njit(cache=True, inline="always")
def _visibility_of(means, quats, scales, op, K, R, t, near, near32, width, height, alpha_min, margin, filter_half,
                   planes, visible, g):
    """visible[g] for :func:`_visibility_kernel`."""
    visible[g] = False
    p0, p1, p2, zs, m0, m1 = _camera_point(means, g, K, R, t, near)
    pz = np.float32(p2)
    o = float(op[g])
    if not pz > near32 or not o > alpha_min:  # in_front is the float32 depth against near
        return
    reach = np.sqrt(2.0 * max(np.log(max(o, 1e-30) * 255.0), 0.0)) * max(abs(float(scales[g, 0])),
                                                                         abs(float(scales[g, 1])))
    if _outside_frustum(p0, p1, p2, planes, reach * 1.001 + 1e-9 * (abs(p0) + abs(p1) + abs(p2))):
        return
    m0 = float(np.float32(m0))
    m1 = float(np.float32(m1))
    z_ = float(np.float32(zs))
    (w_, qx, qy, qz, inv, q00, q01, q02, q10, q11, q12, q20, q21, q22, au0, au1, au2, av0, av1, av2, aw0, aw1,
     aw2, sign) = _camera_axes_at(quats, R, g, float(np.float32(p0)), float(np.float32(p1)), float(pz))
    tx0, tx1, tx2, ty0, ty1, ty2, tw0, tw1, tw2 = _ray_rows(K, au0, au1, au2, av0, av1, av2, float(scales[g, 0]),
                                                           float(scales[g, 1]), z_, m0, m1)
    f = np.float32
    x0, y0, x1, y1 = _box(float(f(tx0)), float(f(tx1)), float(f(tx2)), float(f(ty0)), float(f(ty1)),
                          float(f(ty2)), float(f(tw0)), float(f(tw1)), float(f(tw2)), m0, m1, o, width, height,
                          margin, filter_half, near)
    visible[g] = x1 > x0 and y1 > y0


@functools.lru_cache(maxsize=256)
def _visibility_camera(name: str, width: int, height: int, k_bytes: bytes, w2c_bytes: bytes) -> tuple:
    """A camera's float64 arrays for :func:`_visibility_kernel`, K checked as :func:`camera_tensors`
    checks it: K, R, t rounded to float32 as :func:`camera_tensors` gives them to the float32
    projection, and the widened frustum's planes (cached: a fit renders the same few hundred views
    again and again)."""
    K = np.frombuffer(k_bytes, np.float64).reshape(3, 3)
    _check_intrinsics(K, name)
    w2c = np.frombuffer(w2c_bytes, np.float64).reshape(4, 4)
    r32 = lambda a: np.ascontiguousarray(a.astype(np.float32).astype(np.float64))  # noqa: E731
    return r32(K), r32(w2c[:3, :3]), r32(w2c[:3, 3]), frustum_planes(K, width, height)


def visible_mask(splats: Splats, camera: Camera, near: float = 0.01) -> Tensor:
    """[N] bool, ``project(splats, camera, near).visible`` (the splats whose footprint touches the
    image), without the projection's tensors: one numba pass for float32 CPU splats (the training
    loop's visibility test for compact gradients), else :func:`project` itself."""
    check_splats(splats)
    tensors = (splats.means, splats.quats, splats.scales, splats.opacities)
    if not (use_fused(*tensors) and all(t.dtype == torch.float32 for t in tensors)):
        return project(splats, camera, near).visible
    K, rot_cw, t_cw, planes = _visibility_camera(str(camera.name), int(camera.width), int(camera.height),
                                                 np.asarray(camera.K, np.float64).tobytes(),
                                                 np.asarray(camera.world_to_camera, np.float64).tobytes())
    arr = lambda a: np.ascontiguousarray(a.detach().numpy())  # noqa: E731
    visible = np.empty(splats.means.shape[0], np.bool_)
    _visibility_kernel(arr(splats.means), arr(splats.quats), arr(splats.scales), arr(splats.opacities), K, rot_cw,
                       t_cw, float(near), np.float32(near), int(camera.width), int(camera.height), ALPHA_MIN,
                       BOX_MARGIN, FILTER_INV_SQUARE / 2.0, planes, visible)
    return torch.from_numpy(visible)


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
