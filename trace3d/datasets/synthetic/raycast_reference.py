"""Slow reference twin of :mod:`.raycast` (numpy, vectorised over rays, written independently of the
kernels): the tests compare :func:`render_view_reference` with :func:`.raycast.render_view`."""

from __future__ import annotations

import numpy as np

from ...scene import Camera
from .primitives import (LIGHT_FALLOFF, PAT_CHECKER, PAT_NOISE, PAT_PLANKS, PAT_STRIPES, PAT_TILES, SHAPE_BOX,
                         SHAPE_ELLIPSOID, PackedScene)


def _ref_hash01(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray, seed: int) -> np.ndarray:
    mask = np.int64(0xFFFFFFFF)
    h = (ix * 374761393 + iy * 668265263 + iz * 1440662683 + np.int64(seed) * 1013904223) & mask
    h = ((h ^ (h >> 13)) * 1274126177) & mask
    h = h ^ (h >> 16)
    return h.astype(np.float64) / 4294967296.0


def _ref_value_noise(p: np.ndarray, seed: int) -> np.ndarray:
    """p: [R, 3] -> [R] value noise."""
    cell = np.floor(p)
    frac = p - cell
    weight = frac * frac * (3.0 - 2.0 * frac)
    cell = cell.astype(np.int64)
    out = np.zeros(len(p))
    for corner in range(8):
        offs = np.array([(corner >> 0) & 1, (corner >> 1) & 1, (corner >> 2) & 1])
        w = np.prod(np.where(offs == 1, weight, 1.0 - weight), axis=1)
        c = cell + offs
        out += w * _ref_hash01(c[:, 0], c[:, 1], c[:, 2], seed)
    return out


def _ref_fbm(p: np.ndarray, seed: int) -> np.ndarray:
    weights = [1.0, 0.5, 0.25]
    return sum(w * _ref_value_noise(p * 2.0**o, seed + 17 * o) for o, w in enumerate(weights)) / sum(weights)


def _ref_albedo(local: np.ndarray, tex_int: np.ndarray, tf: np.ndarray) -> np.ndarray:
    """local: [R, 3] points of one primitive -> [R, 3] albedo."""
    pattern, axis, seed = (int(v) for v in tex_int)
    p = local + tf[10:13]
    s = tf[6]
    a, b, c = p[:, axis], p[:, (axis + 1) % 3], p[:, (axis + 2) % 3]
    frac = lambda v: v - np.floor(v)  # noqa: E731
    if pattern == PAT_NOISE:
        t = 0.5 + 1.6 * (_ref_fbm(p / s, seed) - 0.5)
    elif pattern == PAT_STRIPES:
        t = 0.5 + 0.5 * np.tanh(3.0 * np.sin(2.0 * np.pi * a / s))
    elif pattern == PAT_CHECKER:
        t = (np.floor(p / s).astype(np.int64).sum(axis=1) % 2).astype(np.float64)
    elif pattern == PAT_PLANKS:
        row = np.floor(b / s).astype(np.int64)
        zero = np.zeros_like(row)
        length = 6.0 * s
        shifted = a + _ref_hash01(row, zero, zero, seed) * length
        col = np.floor(shifted / length).astype(np.int64)
        t = 0.55 * _ref_hash01(row, col, zero + 1, seed) + 0.45 * _ref_fbm(
            np.stack([a / (2 * s), b / (0.5 * s), c / (0.5 * s)], axis=1), seed + 3
        )
        t = np.where((frac(b / s) < 0.05) | (frac(shifted / length) < 0.01), 1.0, t)
    elif pattern == PAT_TILES:
        i = np.floor(b / s).astype(np.int64)
        j = np.floor(c / s).astype(np.int64)
        t = 0.4 * _ref_hash01(i, j, np.full_like(i, 2), seed)
        t = np.where((frac(b / s) < 0.06) | (frac(c / s) < 0.06), 1.0, t)
    else:
        r = np.hypot(b, c)
        t = 0.5 + 0.5 * np.sin(2.0 * np.pi * (r / s + 0.8 * _ref_fbm(p / (2 * s), seed)))
    t = np.clip(0.5 + (t - 0.5) * tf[7], 0.0, 1.0)
    bright = np.maximum(1.0 + tf[8] * 1.6 * (2.0 * _ref_fbm(p / tf[9], seed + 101) - 1.0), 0.0)
    return (tf[0:3] + (tf[3:6] - tf[0:3]) * t[:, None]) * bright[:, None]


def _ref_hit_box(o: np.ndarray, d: np.ndarray, half: np.ndarray, tmin: float) -> np.ndarray:
    """Brute force: intersect the six face planes and keep hits inside the face rectangles."""
    best = np.full(len(o), np.inf)
    for ax in range(3):
        u, v = (ax + 1) % 3, (ax + 2) % 3
        for sign in (-1.0, 1.0):
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (sign * half[ax] - o[:, ax]) / d[:, ax]
            pu = o[:, u] + t * d[:, u]
            pv = o[:, v] + t * d[:, v]
            ok = (t > tmin) & (np.abs(pu) <= half[u]) & (np.abs(pv) <= half[v]) & np.isfinite(t)
            best = np.where(ok & (t < best), t, best)
    return best


def _ref_hit_ellipsoid(o: np.ndarray, d: np.ndarray, axes: np.ndarray, tmin: float) -> np.ndarray:
    p, q = o / axes, d / axes
    a = (q * q).sum(1)
    b = 2.0 * (p * q).sum(1)
    c = (p * p).sum(1) - 1.0
    disc = b * b - 4 * a * c
    sq = np.sqrt(np.maximum(disc, 0.0))
    best = np.full(len(o), np.inf)
    for root in ((-b + sq) / (2 * a), (-b - sq) / (2 * a)):
        ok = (disc >= 0) & (root > tmin) & (root < best)
        best = np.where(ok, root, best)
    return best


def _ref_hit_frustum(o: np.ndarray, d: np.ndarray, size: np.ndarray, tmin: float) -> tuple[np.ndarray, np.ndarray]:
    """Side: radius(z) linear from r0 at -h to r1 at +h, solved as a quadratic in t; caps: discs."""
    r0, r1, h = size
    slope = (r1 - r0) / (2 * h)
    radius = lambda z: r0 + slope * (z + h)  # noqa: E731
    best = np.full(len(o), np.inf)
    face = np.zeros(len(o), dtype=np.int64)
    base = radius(o[:, 2])
    a = d[:, 0] ** 2 + d[:, 1] ** 2 - (slope * d[:, 2]) ** 2
    b = 2 * (o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1] - base * slope * d[:, 2])
    c = o[:, 0] ** 2 + o[:, 1] ** 2 - base**2
    with np.errstate(divide="ignore", invalid="ignore"):
        disc = b * b - 4 * a * c
        sq = np.sqrt(np.maximum(disc, 0.0))
        linear = np.abs(a) <= 1e-14
        roots = [np.where(linear, -c / b, (-b - sq) / (2 * a)), np.where(linear, np.inf, (-b + sq) / (2 * a))]
    for root in roots:
        z = o[:, 2] + root * d[:, 2]
        ok = (linear | (disc >= 0)) & (root > tmin) & (root < best) & (np.abs(z) <= h) & (radius(z) >= 0)
        best = np.where(ok, root, best)
        face = np.where(ok, 0, face)
    for code, zc, rc in ((1, -h, r0), (2, h, r1)):
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (zc - o[:, 2]) / d[:, 2]
        x, y = o[:, 0] + t * d[:, 0], o[:, 1] + t * d[:, 1]
        ok = np.isfinite(t) & (t > tmin) & (t < best) & (x * x + y * y <= rc * rc)
        best = np.where(ok, t, best)
        face = np.where(ok, code, face)
    return best, face


def cast_rays_reference(packed: PackedScene, o: np.ndarray, d: np.ndarray, tmin: float = 1e-6):
    """o, d: [R, 3] -> t [R], primitive [R] (-1 none), face [R], local hit points [R, 3], normals [R, 3]."""
    n = len(o)
    best = np.full(n, np.inf)
    prim = np.full(n, -1, dtype=np.int64)
    face = np.zeros(n, dtype=np.int64)
    for p in range(len(packed.shapes)):
        R = packed.rotations[p]
        lo = (o - packed.centers[p]) @ R
        ld = d @ R
        if packed.shapes[p] == SHAPE_BOX:
            t, f = _ref_hit_box(lo, ld, packed.sizes[p], tmin), np.zeros(n, dtype=np.int64)
        elif packed.shapes[p] == SHAPE_ELLIPSOID:
            t, f = _ref_hit_ellipsoid(lo, ld, packed.sizes[p], tmin), np.zeros(n, dtype=np.int64)
        else:
            t, f = _ref_hit_frustum(lo, ld, packed.sizes[p], tmin)
        closer = t < best
        best = np.where(closer, t, best)
        prim = np.where(closer, p, prim)
        face = np.where(closer, f, face)
    return best, prim, face


def _ref_normals(packed: PackedScene, prim: np.ndarray, face: np.ndarray, local: np.ndarray) -> np.ndarray:
    """Local unit normals [R, 3] at local hit points [R, 3] of primitives ``prim`` [R]."""
    normals = np.zeros_like(local)
    for p in np.unique(prim):
        m = prim == p
        size = packed.sizes[p]
        q = local[m]
        if packed.shapes[p] == SHAPE_BOX:
            ratio = np.abs(q) / size
            axis = np.argmax(ratio, axis=1)  # ties -> lowest axis, as in the kernel
            nrm = np.zeros_like(q)
            nrm[np.arange(len(q)), axis] = np.where(q[np.arange(len(q)), axis] >= 0, 1.0, -1.0)
        elif packed.shapes[p] == SHAPE_ELLIPSOID:
            nrm = q / size**2
        else:
            r0, r1, h = size
            slope = (r1 - r0) / (2 * h)
            nrm = np.stack([q[:, 0], q[:, 1], -slope * (r0 + slope * (q[:, 2] + h))], axis=1)
            f = face[m]
            nrm[f == 1] = (0.0, 0.0, -1.0)
            nrm[f == 2] = (0.0, 0.0, 1.0)
        normals[m] = nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
    return normals


def _ref_shade(packed: PackedScene, o: np.ndarray, d: np.ndarray, ambient: float, shadows: bool) -> np.ndarray:
    """Radiance [R, 3] of rays o, d [R, 3] (0 for rays that hit nothing)."""
    t, prim, face = cast_rays_reference(packed, o, d)
    out = np.zeros((len(o), 3))
    hit = prim >= 0
    o, d, t, prim, face = o[hit], d[hit], t[hit], prim[hit], face[hit]
    points = o + t[:, None] * d
    rot = packed.rotations[prim]  # [R, 3, 3]
    local = np.einsum("rji,rj->ri", rot, points - packed.centers[prim])
    normals = np.einsum("rij,rj->ri", rot, _ref_normals(packed, prim, face, local))
    normals *= np.where((normals * d).sum(1) > 0, -1.0, 1.0)[:, None]
    albedo = np.zeros((len(o), 3))
    for p in np.unique(prim):
        m = prim == p
        albedo[m] = _ref_albedo(local[m], packed.tex_int[p], packed.tex_float[p])
    light = ambient * (0.75 + 0.25 * normals[:, 2])
    for pos, power in zip(packed.lights, packed.light_power):
        to_light = pos - points
        dist = np.linalg.norm(to_light, axis=1)
        to_light /= dist[:, None]
        cos = (normals * to_light).sum(1)
        lit = cos > 0
        if shadows:
            ts, ps, _ = cast_rays_reference(packed, points + 1e-4 * normals, to_light)
            lit &= ~((ps >= 0) & (ts < dist))
        light += np.where(lit, power * cos / (1.0 + (dist / LIGHT_FALLOFF) ** 2), 0.0)
    out[hit] = albedo * light[:, None]
    return out


def render_view_reference(
    packed: PackedScene, camera: Camera, supersample: int = 2, ambient: float = 0.45, shadows: bool = True
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Slow numpy twin of :func:`render_view` (same outputs); for tests on tiny images."""
    W, H = camera.width, camera.height
    Kinv = np.linalg.inv(camera.K)
    c2w = camera.camera_to_world
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)

    def rays(offset_x: float, offset_y: float) -> np.ndarray:
        pix = np.stack([xs + offset_x, ys + offset_y, np.ones_like(xs)], axis=-1).reshape(-1, 3)
        return (pix @ Kinv.T) @ c2w[:3, :3].T  # camera-z-scaled directions [H*W, 3]

    origin = np.broadcast_to(c2w[:3, 3], (H * W, 3))
    t, prim, _ = cast_rays_reference(packed, origin, rays(0.5, 0.5))
    depth = np.where(prim >= 0, t, 0.0).reshape(H, W)
    rgb = np.zeros((H * W, 3))
    ss = int(supersample)
    for sy in range(ss):
        for sx in range(ss):
            rgb += _ref_shade(packed, origin, rays((sx + 0.5) / ss, (sy + 0.5) / ss), ambient, shadows)
    return (rgb / ss**2).reshape(H, W, 3), prim.reshape(H, W), depth
