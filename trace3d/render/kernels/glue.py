"""Fused numba forward/backward kernels for the per-Gaussian work around the tile kernels.

Three differentiable functions replace chains of small torch operations (each allocating [N, 3, 3] or
[N, 16, 3] temporaries, and each with its own autograd node) by one parallel pass over the Gaussians
forward and one backward:

- :func:`camera_points`: world centres to camera space, depth and projected centre (``means2d``),
  the top of :func:`trace3d.render.projection.project`; its torch twin is :func:`camera_points_torch`.
- :func:`splat_frames`: from quaternions, tangent scales, projected centres and centre depths to the
  ray transforms T, the kernel coefficients (A, B, D) and the camera-facing normals — the part of
  :func:`trace3d.render.projection.project` below the projected centre.  Its torch twin is
  :func:`splat_frames_torch` (the former code path, kept as the reference the tests compare with).
- :func:`sh_colors`: view-dependent RGB from spherical harmonics, ``max(SH(d) + 0.5, 0)`` with
  d the unit direction from the camera centre, differentiable w.r.t. the coefficients and the
  means.  Its torch twin is :func:`trace3d.render.sh.eval_sh` (what ``GaussianModel.colors`` ran
  before).

All work per Gaussian, so every worker writes only its own rows: race-free and deterministic.
The backward passes skip Gaussians whose upstream gradients are all zero (those the view did not
render, usually most of them): their gradients are exactly zero.
Internally float64, inputs and outputs in the caller's dtype (float32 or float64).  CPU only: CUDA
tensors take the torch twins (``use_fused`` decides).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from ...geometry import quat_to_rotmat

_enabled = True


def set_fused(enabled: bool) -> None:
    """Switch the fused kernels on or off (off: the torch twins everywhere; used by benchmarks)."""
    global _enabled
    _enabled = bool(enabled)


def fused_enabled() -> bool:
    return _enabled


def use_fused(*tensors: Tensor) -> bool:
    """Whether the fused kernels apply: enabled, every tensor on the CPU in float32 or float64."""
    return _enabled and all(t.device.type == "cpu" and t.dtype in (torch.float32, torch.float64) for t in tensors)


def _np(t: Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().numpy())


# ----------------------------------------------------------------------------------------------
# Camera points: means -> camera-space centre, depth, projected centre
# ----------------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def _camera_point(means, g, K, R, t, near):
    """Gaussian g's camera-space centre (p0, p1, p2), safe depth (1 when not in front of ``near``) and
    projected centre (m0, m1), in float64."""
    x, y, z = float(means[g, 0]), float(means[g, 1]), float(means[g, 2])
    p0 = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z + t[0]
    p1 = R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + t[1]
    p2 = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + t[2]
    zs = p2 if p2 > near else 1.0
    return (p0, p1, p2, zs, (K[0, 0] * p0 + K[0, 1] * p1 + K[0, 2] * p2) / zs,
            (K[1, 0] * p0 + K[1, 1] * p1 + K[1, 2] * p2) / zs)


@njit(parallel=True, cache=True)
def _points_forward(means, K, R, t, near, p_cam, z_safe, m2d):
    n = means.shape[0]
    for g in prange(n):
        p0, p1, p2, zs, m0, m1 = _camera_point(means, g, K, R, t, near)
        p_cam[g, 0], p_cam[g, 1], p_cam[g, 2] = p0, p1, p2
        z_safe[g] = zs
        m2d[g, 0] = m0
        m2d[g, 1] = m1


@njit(parallel=True, cache=True)
def _points_backward(p_cam, z_safe, K, R, near, g_m2d, g_zs, g_means):
    n = p_cam.shape[0]
    for g in prange(n):
        a0, a1, gz = float(g_m2d[g, 0]), float(g_m2d[g, 1]), float(g_zs[g])
        if a0 == 0 and a1 == 0 and gz == 0:
            g_means[g, 0] = g_means[g, 1] = g_means[g, 2] = 0.0
            continue
        p0, p1, p2 = float(p_cam[g, 0]), float(p_cam[g, 1]), float(p_cam[g, 2])
        zs = float(z_safe[g])
        h0 = K[0, 0] * p0 + K[0, 1] * p1 + K[0, 2] * p2
        h1 = K[1, 0] * p0 + K[1, 1] * p1 + K[1, 2] * p2
        d0 = a0 / zs
        d1 = a1 / zs
        dzs = gz - (a0 * h0 + a1 * h1) / (zs * zs)
        # p_cam gradient: K's first two rows against d, plus the depth's where it was used
        q0 = K[0, 0] * d0 + K[1, 0] * d1
        q1 = K[0, 1] * d0 + K[1, 1] * d1
        q2 = K[0, 2] * d0 + K[1, 2] * d1
        if p2 > near:
            q2 += dzs
        g_means[g, 0] = R[0, 0] * q0 + R[1, 0] * q1 + R[2, 0] * q2
        g_means[g, 1] = R[0, 1] * q0 + R[1, 1] * q1 + R[2, 1] * q2
        g_means[g, 2] = R[0, 2] * q0 + R[1, 2] * q1 + R[2, 2] * q2


class _CameraPoints(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, K, R, t, near):
        n = means.shape[0]
        dt = np.float64 if means.dtype == torch.float64 else np.float32
        p_cam, z_safe, m2d = np.empty((n, 3), dt), np.empty(n, dt), np.empty((n, 2), dt)
        if n:
            _points_forward(_np(means), K, R, t, near, p_cam, z_safe, m2d)
        ctx.saved = (p_cam, z_safe, K, R, near)
        p_cam_t = torch.from_numpy(p_cam)
        ctx.mark_non_differentiable(p_cam_t)
        return p_cam_t, torch.from_numpy(z_safe), torch.from_numpy(m2d)

    @staticmethod
    def backward(ctx, g_pcam, g_zs, g_m2d):
        p_cam, z_safe, K, R, near = ctx.saved
        n, dt = p_cam.shape[0], p_cam.dtype

        def grad(t, shape):
            return np.zeros(shape, dt) if t is None else np.ascontiguousarray(t.detach().numpy().astype(dt, copy=False))

        g_means = np.empty((n, 3), dt)
        if n:
            _points_backward(p_cam, z_safe, K, R, near, grad(g_m2d, (n, 2)), grad(g_zs, (n,)), g_means)
        return torch.from_numpy(g_means), None, None, None, None


def camera_points(means: Tensor, K: Tensor, rot_cw: Tensor, t_cw: Tensor, near: float
                  ) -> tuple[Tensor, Tensor, Tensor]:
    """Camera-space centres, safe depths and projected centres of world points.

    Args:
        means: [N, 3] world centres; K: [3, 3] intrinsics (last row 0, 0, 1); rot_cw [3, 3], t_cw [3]:
            world to camera; near: centres with camera z <= near get depth 1 in ``z_safe`` (culled later).
    Returns:
        p_cam [N, 3] (not differentiable), z_safe [N] and means2d [N, 2] = (K p_cam)[:2] / z_safe,
        both differentiable w.r.t. ``means`` (numba on the CPU, else :func:`camera_points_torch`).
    """
    if not use_fused(means):
        return camera_points_torch(means, K, rot_cw, t_cw, near)
    as64 = lambda a: np.ascontiguousarray(a.detach().cpu().double().numpy())  # noqa: E731
    return _CameraPoints.apply(means, as64(K), as64(rot_cw), as64(t_cw), float(near))


def camera_points_torch(means: Tensor, K: Tensor, rot_cw: Tensor, t_cw: Tensor, near: float
                        ) -> tuple[Tensor, Tensor, Tensor]:
    """The torch twin of :func:`camera_points` (plain autograd)."""
    p_cam = means @ rot_cw.T + t_cw
    z = p_cam[:, 2]
    z_safe = torch.where(z > near, z, torch.ones_like(z))
    pix_h = p_cam @ K.T  # third component is z (K's last row is 0, 0, 1)
    return p_cam.detach(), z_safe, pix_h[:, :2] / z_safe[:, None]


# ----------------------------------------------------------------------------------------------
# Splat frames: (quats, scales, means2d, z) -> ray transforms, coefficients, normals
# ----------------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def _rotation(qw, qx, qy, qz):
    norm = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    inv = 1.0 / max(norm, 1e-12)
    w, x, y, z = qw * inv, qx * inv, qy * inv, qz * inv
    return (w, x, y, z, inv,
            1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
            2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
            2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y))


@njit(cache=True, inline="always")
def _camera_axes(quats, R, pcam, g):
    """Gaussian g's rotation (as :func:`_rotation`), its camera-space axes t_u, t_v, t_w (columns of
    R @ Rq) and the sign that turns t_w towards the camera."""
    return _camera_axes_at(quats, R, g, float(pcam[g, 0]), float(pcam[g, 1]), float(pcam[g, 2]))


@njit(cache=True, inline="always")
def _camera_axes_at(quats, R, g, pc0, pc1, pc2):
    """:func:`_camera_axes` with the camera-space centre given as numbers."""
    w, x, y, z, inv, q00, q01, q02, q10, q11, q12, q20, q21, q22 = _rotation(
        float(quats[g, 0]), float(quats[g, 1]), float(quats[g, 2]), float(quats[g, 3]))
    au0 = R[0, 0] * q00 + R[0, 1] * q10 + R[0, 2] * q20
    au1 = R[1, 0] * q00 + R[1, 1] * q10 + R[1, 2] * q20
    au2 = R[2, 0] * q00 + R[2, 1] * q10 + R[2, 2] * q20
    av0 = R[0, 0] * q01 + R[0, 1] * q11 + R[0, 2] * q21
    av1 = R[1, 0] * q01 + R[1, 1] * q11 + R[1, 2] * q21
    av2 = R[2, 0] * q01 + R[2, 1] * q11 + R[2, 2] * q21
    aw0 = R[0, 0] * q02 + R[0, 1] * q12 + R[0, 2] * q22
    aw1 = R[1, 0] * q02 + R[1, 1] * q12 + R[1, 2] * q22
    aw2 = R[2, 0] * q02 + R[2, 1] * q12 + R[2, 2] * q22
    sign = 1.0
    if aw0 * pc0 + aw1 * pc1 + aw2 * pc2 > 0:
        sign = -1.0
    return (w, x, y, z, inv, q00, q01, q02, q10, q11, q12, q20, q21, q22, au0, au1, au2, av0, av1, av2,
            aw0, aw1, aw2, sign)


@njit(cache=True, inline="always")
def _ray_rows(K, au0, au1, au2, av0, av1, av2, su, sv, z_, mx, my):
    """The rows T_x, T_y, T_w of T = [K s_u t_u | K s_v t_v | z (means2d, 1)] from the camera-space
    axes t_u, t_v, the scales, the centre depth and the projected centre (float64)."""
    u0, u1, u2 = au0 * su, au1 * su, au2 * su
    v0, v1, v2 = av0 * sv, av1 * sv, av2 * sv
    return (K[0, 0] * u0 + K[0, 1] * u1 + K[0, 2] * u2, K[0, 0] * v0 + K[0, 1] * v1 + K[0, 2] * v2, z_ * mx,
            K[1, 0] * u0 + K[1, 1] * u1 + K[1, 2] * u2, K[1, 0] * v0 + K[1, 1] * v1 + K[1, 2] * v2, z_ * my,
            u2, v2, z_)


@njit(parallel=True, cache=True)
def _frames_forward(quats, scales, m2d, zs, pcam, K, R, ray_t, coeffs, normals):
    n = quats.shape[0]
    for g in prange(n):
        # camera-space axes (columns of R @ Rq) and the normal's side
        (w, x, y, z, inv, q00, q01, q02, q10, q11, q12, q20, q21, q22, au0, au1, au2, av0, av1, av2, aw0, aw1, aw2,
         sign) = _camera_axes(quats, R, pcam, g)
        normals[g, 0] = sign * aw0
        normals[g, 1] = sign * aw1
        normals[g, 2] = sign * aw2
        tx0, tx1, tx2, ty0, ty1, ty2, tw0, tw1, tw2 = _ray_rows(
            K, au0, au1, au2, av0, av1, av2, float(scales[g, 0]), float(scales[g, 1]), float(zs[g]),
            float(m2d[g, 0]), float(m2d[g, 1]))
        ray_t[g, 0, 0], ray_t[g, 0, 1], ray_t[g, 0, 2] = tx0, tx1, tx2
        ray_t[g, 1, 0], ray_t[g, 1, 1], ray_t[g, 1, 2] = ty0, ty1, ty2
        ray_t[g, 2, 0], ray_t[g, 2, 1], ray_t[g, 2, 2] = tw0, tw1, tw2
        # A = T_x x T_y, B = T_y x T_w, D = T_w x T_x
        coeffs[g, 0] = tx1 * ty2 - tx2 * ty1
        coeffs[g, 1] = tx2 * ty0 - tx0 * ty2
        coeffs[g, 2] = tx0 * ty1 - tx1 * ty0
        coeffs[g, 3] = ty1 * tw2 - ty2 * tw1
        coeffs[g, 4] = ty2 * tw0 - ty0 * tw2
        coeffs[g, 5] = ty0 * tw1 - ty1 * tw0
        coeffs[g, 6] = tw1 * tx2 - tw2 * tx1
        coeffs[g, 7] = tw2 * tx0 - tw0 * tx2
        coeffs[g, 8] = tw0 * tx1 - tw1 * tx0


@njit(parallel=True, cache=True)
def _frames_backward(quats, scales, m2d, zs, pcam, K, R, g_ray, g_coeffs, g_normals,
                     g_quats, g_scales, g_m2d, g_zs):
    n = quats.shape[0]
    k00, k01, k02, k10, k11, k12 = K[0, 0], K[0, 1], K[0, 2], K[1, 0], K[1, 1], K[1, 2]
    for g in prange(n):
        # a Gaussian the view did not render gets no upstream gradient: its gradients are zero
        nonzero = False
        for i in range(9):
            nonzero |= g_coeffs[g, i] != 0
        for i in range(3):
            nonzero |= (g_normals[g, i] != 0) | (g_ray[g, 0, i] != 0) | (g_ray[g, 1, i] != 0) | (g_ray[g, 2, i] != 0)
        if not nonzero:
            g_quats[g, 0] = g_quats[g, 1] = g_quats[g, 2] = g_quats[g, 3] = 0.0
            g_scales[g, 0] = g_scales[g, 1] = g_m2d[g, 0] = g_m2d[g, 1] = g_zs[g] = 0.0
            continue
        (w, x, y, z, inv, q00, q01, q02, q10, q11, q12, q20, q21, q22, au0, au1, au2, av0, av1, av2, aw0, aw1, aw2,
         sign) = _camera_axes(quats, R, pcam, g)
        su = float(scales[g, 0])
        sv = float(scales[g, 1])
        z_ = float(zs[g])
        mx = float(m2d[g, 0])
        my = float(m2d[g, 1])
        tx0, tx1, tx2, ty0, ty1, ty2, tw0, tw1, tw2 = _ray_rows(K, au0, au1, au2, av0, av1, av2, su, sv, z_, mx, my)
        # gradients of the rows of T: direct, then through the three cross products
        gx0, gx1, gx2 = float(g_ray[g, 0, 0]), float(g_ray[g, 0, 1]), float(g_ray[g, 0, 2])
        gy0, gy1, gy2 = float(g_ray[g, 1, 0]), float(g_ray[g, 1, 1]), float(g_ray[g, 1, 2])
        gw0, gw1, gw2 = float(g_ray[g, 2, 0]), float(g_ray[g, 2, 1]), float(g_ray[g, 2, 2])
        ga0, ga1, ga2 = float(g_coeffs[g, 0]), float(g_coeffs[g, 1]), float(g_coeffs[g, 2])
        gb0, gb1, gb2 = float(g_coeffs[g, 3]), float(g_coeffs[g, 4]), float(g_coeffs[g, 5])
        gd0, gd1, gd2 = float(g_coeffs[g, 6]), float(g_coeffs[g, 7]), float(g_coeffs[g, 8])
        # A = Tx x Ty: dTx = Ty x gA, dTy = gA x Tx
        gx0 += ty1 * ga2 - ty2 * ga1
        gx1 += ty2 * ga0 - ty0 * ga2
        gx2 += ty0 * ga1 - ty1 * ga0
        gy0 += ga1 * tx2 - ga2 * tx1
        gy1 += ga2 * tx0 - ga0 * tx2
        gy2 += ga0 * tx1 - ga1 * tx0
        # B = Ty x Tw: dTy = Tw x gB, dTw = gB x Ty
        gy0 += tw1 * gb2 - tw2 * gb1
        gy1 += tw2 * gb0 - tw0 * gb2
        gy2 += tw0 * gb1 - tw1 * gb0
        gw0 += gb1 * ty2 - gb2 * ty1
        gw1 += gb2 * ty0 - gb0 * ty2
        gw2 += gb0 * ty1 - gb1 * ty0
        # D = Tw x Tx: dTw = Tx x gD, dTx = gD x Tw
        gw0 += tx1 * gd2 - tx2 * gd1
        gw1 += tx2 * gd0 - tx0 * gd2
        gw2 += tx0 * gd1 - tx1 * gd0
        gx0 += gd1 * tw2 - gd2 * tw1
        gx1 += gd2 * tw0 - gd0 * tw2
        gx2 += gd0 * tw1 - gd1 * tw0
        # third column z (m, 1)
        g_m2d[g, 0] = z_ * gx2
        g_m2d[g, 1] = z_ * gy2
        g_zs[g] = mx * gx2 + my * gy2 + gw2
        # first two columns K (s t): h = K^T (column gradient)
        hu0 = k00 * gx0 + k10 * gy0
        hu1 = k01 * gx0 + k11 * gy0
        hu2 = k02 * gx0 + k12 * gy0 + gw0
        hv0 = k00 * gx1 + k10 * gy1
        hv1 = k01 * gx1 + k11 * gy1
        hv2 = k02 * gx1 + k12 * gy1 + gw1
        g_scales[g, 0] = au0 * hu0 + au1 * hu1 + au2 * hu2
        g_scales[g, 1] = av0 * hv0 + av1 * hv1 + av2 * hv2
        # gradients of the camera-space axes; the normal's sign is piecewise constant
        cu0, cu1, cu2 = su * hu0, su * hu1, su * hu2
        cv0, cv1, cv2 = sv * hv0, sv * hv1, sv * hv2
        cw0 = sign * float(g_normals[g, 0])
        cw1 = sign * float(g_normals[g, 1])
        cw2 = sign * float(g_normals[g, 2])
        # G = R^T [cu | cv | cw], the gradient of the quaternion's rotation matrix
        G00 = R[0, 0] * cu0 + R[1, 0] * cu1 + R[2, 0] * cu2
        G10 = R[0, 1] * cu0 + R[1, 1] * cu1 + R[2, 1] * cu2
        G20 = R[0, 2] * cu0 + R[1, 2] * cu1 + R[2, 2] * cu2
        G01 = R[0, 0] * cv0 + R[1, 0] * cv1 + R[2, 0] * cv2
        G11 = R[0, 1] * cv0 + R[1, 1] * cv1 + R[2, 1] * cv2
        G21 = R[0, 2] * cv0 + R[1, 2] * cv1 + R[2, 2] * cv2
        G02 = R[0, 0] * cw0 + R[1, 0] * cw1 + R[2, 0] * cw2
        G12 = R[0, 1] * cw0 + R[1, 1] * cw1 + R[2, 1] * cw2
        G22 = R[0, 2] * cw0 + R[1, 2] * cw1 + R[2, 2] * cw2
        gqw = 2.0 * (-z * G01 + y * G02 + z * G10 - x * G12 - y * G20 + x * G21)
        gqx = 2.0 * (y * G01 + z * G02 + y * G10 - 2.0 * x * G11 - w * G12 + z * G20 + w * G21 - 2.0 * x * G22)
        gqy = 2.0 * (-2.0 * y * G00 + x * G01 + w * G02 + x * G10 + z * G12 - w * G20 + z * G21 - 2.0 * y * G22)
        gqz = 2.0 * (-2.0 * z * G00 - w * G01 + x * G02 + w * G10 - 2.0 * z * G11 + y * G12 + x * G20 + y * G21)
        # normalisation q / |q|
        dot = w * gqw + x * gqx + y * gqy + z * gqz
        g_quats[g, 0] = (gqw - w * dot) * inv
        g_quats[g, 1] = (gqx - x * dot) * inv
        g_quats[g, 2] = (gqy - y * dot) * inv
        g_quats[g, 3] = (gqz - z * dot) * inv


class _SplatFrames(torch.autograd.Function):
    @staticmethod
    def forward(ctx, quats, scales, means2d, z, p_cam, K, R):
        n = quats.shape[0]
        dt = quats.dtype
        ray_t = np.empty((n, 3, 3), dtype=np.float64 if dt == torch.float64 else np.float32)
        coeffs = np.empty((n, 9), ray_t.dtype)
        normals = np.empty((n, 3), ray_t.dtype)
        inputs = (_np(quats), _np(scales), _np(means2d), _np(z), _np(p_cam), K, R)
        if n:
            _frames_forward(*inputs, ray_t, coeffs, normals)
        ctx.inputs = inputs
        return torch.from_numpy(ray_t), torch.from_numpy(coeffs), torch.from_numpy(normals)

    @staticmethod
    def backward(ctx, g_ray, g_coeffs, g_normals):
        quats, scales, m2d, z, p_cam, K, R = ctx.inputs
        n = quats.shape[0]
        dt = quats.dtype

        def grad(t, shape):
            return np.zeros(shape, dt) if t is None else np.ascontiguousarray(t.detach().numpy().astype(dt, copy=False))

        out = (np.empty((n, 4), dt), np.empty((n, 2), dt), np.empty((n, 2), dt), np.empty(n, dt))
        if n:
            _frames_backward(quats, scales, m2d, z, p_cam, K, R, grad(g_ray, (n, 3, 3)), grad(g_coeffs, (n, 9)),
                             grad(g_normals, (n, 3)), *out)
        return tuple(torch.from_numpy(a) for a in out) + (None, None, None)


def splat_frames(quats: Tensor, scales: Tensor, means2d: Tensor, z: Tensor, p_cam: Tensor, K: Tensor,
                 rot_cw: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Ray transforms [N, 3, 3], coefficients (A, B, D) [N, 9] and camera-facing normals [N, 3].

    Args:
        quats: [N, 4] rotations (w, x, y, z), any non-zero norm; scales: [N, 2] tangent scales;
        means2d: [N, 2] projected centres; z: [N] centre depths (the third column of T is
            ``z (means2d, 1)``); p_cam: [N, 3] camera-space centres (only the normal's side);
        K: [3, 3] intrinsics (last row 0, 0, 1); rot_cw: [3, 3] world-to-camera rotation.
    Differentiable w.r.t. quats, scales, means2d and z (numba on the CPU, else
    :func:`splat_frames_torch`).
    """
    if not use_fused(quats, scales, means2d, z):
        return splat_frames_torch(quats, scales, means2d, z, p_cam, K, rot_cw)
    dt = quats.dtype
    Kn = np.ascontiguousarray(K.detach().cpu().double().numpy())
    Rn = np.ascontiguousarray(rot_cw.detach().cpu().double().numpy())
    return _SplatFrames.apply(quats, scales.to(dt), means2d.to(dt), z.to(dt), p_cam.detach().to(dt), Kn, Rn)


def splat_frames_torch(quats: Tensor, scales: Tensor, means2d: Tensor, z: Tensor, p_cam: Tensor, K: Tensor,
                       rot_cw: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The torch twin of :func:`splat_frames` (plain autograd)."""
    axes = rot_cw @ quat_to_rotmat(quats)  # [N, 3, 3] columns t_u^c, t_v^c, t_w^c
    normal = axes[:, :, 2]
    facing = (normal * p_cam.detach()).sum(-1, keepdim=True) > 0
    normal = torch.where(facing, -normal, normal)
    col_u = (axes[:, :, 0] * scales[:, 0:1]) @ K.T
    col_v = (axes[:, :, 1] * scales[:, 1:2]) @ K.T
    col_p = torch.cat([means2d * z[:, None], z[:, None]], dim=-1)
    ray_t = torch.stack([col_u, col_v, col_p], dim=-1)  # [N, 3, 3], rows T_x, T_y, T_w
    tx, ty, tw = ray_t[:, 0], ray_t[:, 1], ray_t[:, 2]
    coeffs = torch.cat([torch.linalg.cross(tx, ty), torch.linalg.cross(ty, tw), torch.linalg.cross(tw, tx)], dim=-1)
    return ray_t, coeffs, normal


# ----------------------------------------------------------------------------------------------
# Spherical-harmonic colours
# ----------------------------------------------------------------------------------------------

_C0 = 0.28209479177387814
_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
       1.445305721320277, -0.5900435899266435)
_SH_CHUNK = 512


@njit(cache=True, inline="always")
def _sh_basis(x, y, z, degree, b, db, want_grad):
    """Fill b[16] with the basis at unit direction (x, y, z) and, when asked, db[16, 3] with its
    derivatives (entries past the degree's count are left alone)."""
    b[0] = _C0
    if degree < 1:
        return
    b[1] = -_C1 * y
    b[2] = _C1 * z
    b[3] = -_C1 * x
    if want_grad:
        for i in range(1, 4):
            db[i, 0] = 0.0
            db[i, 1] = 0.0
            db[i, 2] = 0.0
        db[1, 1] = -_C1
        db[2, 2] = _C1
        db[3, 0] = -_C1
    if degree < 2:
        return
    xx, yy, zz = x * x, y * y, z * z
    b[4] = _C2[0] * x * y
    b[5] = _C2[1] * y * z
    b[6] = _C2[2] * (2.0 * zz - xx - yy)
    b[7] = _C2[3] * x * z
    b[8] = _C2[4] * (xx - yy)
    if want_grad:
        db[4, 0], db[4, 1], db[4, 2] = _C2[0] * y, _C2[0] * x, 0.0
        db[5, 0], db[5, 1], db[5, 2] = 0.0, _C2[1] * z, _C2[1] * y
        db[6, 0], db[6, 1], db[6, 2] = -2.0 * _C2[2] * x, -2.0 * _C2[2] * y, 4.0 * _C2[2] * z
        db[7, 0], db[7, 1], db[7, 2] = _C2[3] * z, 0.0, _C2[3] * x
        db[8, 0], db[8, 1], db[8, 2] = 2.0 * _C2[4] * x, -2.0 * _C2[4] * y, 0.0
    if degree < 3:
        return
    b[9] = _C3[0] * y * (3.0 * xx - yy)
    b[10] = _C3[1] * x * y * z
    b[11] = _C3[2] * y * (4.0 * zz - xx - yy)
    b[12] = _C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
    b[13] = _C3[4] * x * (4.0 * zz - xx - yy)
    b[14] = _C3[5] * z * (xx - yy)
    b[15] = _C3[6] * x * (xx - 3.0 * yy)
    if want_grad:
        db[9, 0], db[9, 1], db[9, 2] = _C3[0] * 6.0 * x * y, _C3[0] * (3.0 * xx - 3.0 * yy), 0.0
        db[10, 0], db[10, 1], db[10, 2] = _C3[1] * y * z, _C3[1] * x * z, _C3[1] * x * y
        db[11, 0], db[11, 1], db[11, 2] = (-2.0 * _C3[2] * x * y, _C3[2] * (4.0 * zz - xx - 3.0 * yy),
                                           8.0 * _C3[2] * y * z)
        db[12, 0], db[12, 1], db[12, 2] = (-6.0 * _C3[3] * x * z, -6.0 * _C3[3] * y * z,
                                           _C3[3] * (6.0 * zz - 3.0 * xx - 3.0 * yy))
        db[13, 0], db[13, 1], db[13, 2] = (_C3[4] * (4.0 * zz - 3.0 * xx - yy), -2.0 * _C3[4] * x * y,
                                           8.0 * _C3[4] * x * z)
        db[14, 0], db[14, 1], db[14, 2] = 2.0 * _C3[5] * x * z, -2.0 * _C3[5] * y * z, _C3[5] * (xx - yy)
        db[15, 0], db[15, 1], db[15, 2] = _C3[6] * (3.0 * xx - 3.0 * yy), -6.0 * _C3[6] * x * y, 0.0


@njit(cache=True, inline="always")
def _direction(means, g, cx, cy, cz):
    dx = float(means[g, 0]) - cx
    dy = float(means[g, 1]) - cy
    dz = float(means[g, 2]) - cz
    norm = math.sqrt(dx * dx + dy * dy + dz * dz)
    inv = 1.0 / max(norm, 1e-12)
    return dx * inv, dy * inv, dz * inv, inv


@njit(cache=True, inline="always")
def _sh_values(sh_dc, sh_rest, g, b, count):
    """The three channels' SH sums of Gaussian g (before the + 0.5 and the clamp), each in coefficient
    order: the three chains of additions are interleaved, so that they overlap instead of waiting
    for each other (the same values as one channel after the other)."""
    v0 = _C0 * float(sh_dc[g, 0, 0])
    v1 = _C0 * float(sh_dc[g, 0, 1])
    v2 = _C0 * float(sh_dc[g, 0, 2])
    for i in range(1, count):
        bi = b[i]
        v0 += bi * float(sh_rest[g, i - 1, 0])
        v1 += bi * float(sh_rest[g, i - 1, 1])
        v2 += bi * float(sh_rest[g, i - 1, 2])
    return v0, v1, v2


@njit(parallel=True, cache=True)
def _sh_forward(means, sh_dc, sh_rest, center, degree, rows, colors):
    """colors[j] = the SH colour of Gaussian rows[j]."""
    n = rows.shape[0]
    count = (degree + 1) * (degree + 1)
    cx, cy, cz = center[0], center[1], center[2]
    for chunk in prange((n + _SH_CHUNK - 1) // _SH_CHUNK):
        b = np.zeros(16)
        db = np.zeros((16, 3))
        for j in range(chunk * _SH_CHUNK, min(n, (chunk + 1) * _SH_CHUNK)):
            g = rows[j]
            x, y, z, inv = _direction(means, g, cx, cy, cz)
            _sh_basis(x, y, z, degree, b, db, False)
            v0, v1, v2 = _sh_values(sh_dc, sh_rest, g, b, count)
            colors[j, 0] = max(v0 + 0.5, 0.0)
            colors[j, 1] = max(v1 + 0.5, 0.0)
            colors[j, 2] = max(v2 + 0.5, 0.0)


@njit(parallel=True, cache=True)
def _sh_backward(means, sh_dc, sh_rest, center, degree, slot, g_colors, g_means, g_dc, g_rest):
    """Gradients of the selected colours into g_means, g_dc and g_rest (uninitialised [N, ...] arrays,
    every row written here): row g's colour gradient is g_colors[slot[g]], or zero where slot[g] < 0
    (not selected) or the colour gradient is zero (not rendered in the view). Writing the zero rows
    in the same parallel pass spares a separate single-threaded clearing of the arrays."""
    n = means.shape[0]
    k_rest = sh_rest.shape[1]
    count = (degree + 1) * (degree + 1)
    cx, cy, cz = center[0], center[1], center[2]
    for chunk in prange((n + _SH_CHUNK - 1) // _SH_CHUNK):
        b = np.zeros(16)
        db = np.zeros((16, 3))
        for g in range(chunk * _SH_CHUNK, min(n, (chunk + 1) * _SH_CHUNK)):
            j = slot[g]
            if j < 0 or (g_colors[j, 0] == 0 and g_colors[j, 1] == 0 and g_colors[j, 2] == 0):
                for c in range(3):
                    g_means[g, c] = 0.0
                    g_dc[g, 0, c] = 0.0
                    for i in range(k_rest):
                        g_rest[g, i, c] = 0.0
                continue
            x, y, z, inv = _direction(means, g, cx, cy, cz)
            _sh_basis(x, y, z, degree, b, db, True)
            gdx = 0.0
            gdy = 0.0
            gdz = 0.0
            v0, v1, v2 = _sh_values(sh_dc, sh_rest, g, b, count)
            for c in range(3):
                v = v0 if c == 0 else (v1 if c == 1 else v2)
                gv = float(g_colors[j, c]) if v + 0.5 >= 0.0 else 0.0  # clamp_min passes ties
                g_dc[g, 0, c] = _C0 * gv
                for i in range(1, count):
                    r = float(sh_rest[g, i - 1, c])
                    g_rest[g, i - 1, c] = b[i] * gv
                    gdx += gv * r * db[i, 0]
                    gdy += gv * r * db[i, 1]
                    gdz += gv * r * db[i, 2]
                for i in range(count - 1, k_rest):  # coefficients beyond the degree
                    g_rest[g, i, c] = 0.0
            # direction = (mean - centre) / |mean - centre|
            dot = x * gdx + y * gdy + z * gdz
            g_means[g, 0] = (gdx - x * dot) * inv
            g_means[g, 1] = (gdy - y * dot) * inv
            g_means[g, 2] = (gdz - z * dot) * inv


class _ShColors(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, sh_dc, sh_rest, center, degree, rows):
        colors = np.empty((rows.shape[0], 3), np.float64 if means.dtype == torch.float64 else np.float32)
        inputs = (_np(means), _np(sh_dc), _np(sh_rest), center)
        if rows.shape[0]:
            _sh_forward(*inputs, degree, rows, colors)
        ctx.inputs = inputs
        ctx.degree = degree
        ctx.rows = rows
        return torch.from_numpy(colors)

    @staticmethod
    def backward(ctx, g_colors):
        means, sh_dc, sh_rest, center = ctx.inputs
        n, rows = means.shape[0], ctx.rows
        g_means = np.empty(means.shape, means.dtype)
        g_dc = np.empty(sh_dc.shape, sh_dc.dtype)
        g_rest = np.empty(sh_rest.shape, sh_rest.dtype)
        if n:
            slot = np.full(n, -1, np.int64)
            slot[rows] = np.arange(rows.shape[0])
            _sh_backward(means, sh_dc, sh_rest, center, ctx.degree, slot,
                         np.ascontiguousarray(g_colors.detach().numpy().astype(means.dtype, copy=False)),
                         g_means, g_dc, g_rest)
        return torch.from_numpy(g_means), torch.from_numpy(g_dc), torch.from_numpy(g_rest), None, None, None


def sh_colors(means: Tensor, sh_dc: Tensor, sh_rest: Tensor, center: Tensor, degree: int,
              rows: Tensor | None = None) -> Tensor:
    """``max(SH_degree(d) + 0.5, 0)`` per Gaussian: [N, 3], or [R, 3] for the Gaussians ``rows``.

    Args:
        means: [N, 3]; sh_dc: [N, 1, 3]; sh_rest: [N, K, 3] with K >= (degree + 1)^2 - 1 (extra
            coefficients ignored, their gradient zero); center: [3] camera centre; degree: 1..3;
            rows: optional [R] distinct int64 indices: only those Gaussians' colours (a render needs
            only the Gaussians its view sees), gradients zero for the others.
    Differentiable w.r.t. means, sh_dc and sh_rest (numba on the CPU, else the torch twin
    :func:`sh_colors_torch`).
    """
    if not 1 <= degree <= 3 or sh_rest.shape[1] < (degree + 1) ** 2 - 1:
        raise ValueError(f"sh_colors: degree {degree} needs {(degree + 1) ** 2 - 1} rest coefficients, "
                         f"got {sh_rest.shape[1]}")
    if not use_fused(means, sh_dc, sh_rest) or not (means.dtype == sh_dc.dtype == sh_rest.dtype):
        if rows is not None:
            means, sh_dc, sh_rest = means[rows], sh_dc[rows], sh_rest[rows]
        return sh_colors_torch(means, sh_dc, sh_rest, center, degree)
    c = np.ascontiguousarray(torch.as_tensor(center).detach().cpu().double().numpy().reshape(3))
    index = (np.arange(means.shape[0], dtype=np.int64) if rows is None
             else np.ascontiguousarray(rows.detach().cpu().numpy().astype(np.int64, copy=False)))
    return _ShColors.apply(means, sh_dc, sh_rest, c, int(degree), index)


def sh_colors_torch(means: Tensor, sh_dc: Tensor, sh_rest: Tensor, center: Tensor, degree: int) -> Tensor:
    """The torch twin of :func:`sh_colors`."""
    import torch.nn.functional as F

    from ..sh import eval_sh, num_sh_rest

    coeffs = torch.cat([sh_dc, sh_rest[:, : num_sh_rest(degree)]], dim=1)
    center = torch.as_tensor(center).to(dtype=means.dtype, device=means.device)
    directions = F.normalize(means - center[None], dim=-1)
    return (eval_sh(degree, coeffs, directions) + 0.5).clamp_min(0.0)
