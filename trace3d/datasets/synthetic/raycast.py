"""The numba ray caster: solid textures, ray-primitive intersection (:func:`cast_ray`), shading and the
per-view kernel behind :func:`render_view`.  Its slow numpy twin is :mod:`.raycast_reference`."""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from ...scene import Camera
from .primitives import LIGHT_FALLOFF, PackedScene


@njit(cache=True)
def _hash01(ix, iy, iz, seed):
    """Integer lattice point -> pseudo-random number in [0, 1)."""
    h = (ix * 374761393 + iy * 668265263 + iz * 1440662683 + seed * 1013904223) & 0xFFFFFFFF
    h = ((h ^ (h >> 13)) * 1274126177) & 0xFFFFFFFF
    h = h ^ (h >> 16)
    return h / 4294967296.0


@njit(cache=True)
def _value_noise(x, y, z, seed):
    """Trilinear value noise with smoothstep weights, in [0, 1]."""
    fx, fy, fz = math.floor(x), math.floor(y), math.floor(z)
    ix, iy, iz = np.int64(fx), np.int64(fy), np.int64(fz)
    tx, ty, tz = x - fx, y - fy, z - fz
    ux, uy, uz = tx * tx * (3.0 - 2.0 * tx), ty * ty * (3.0 - 2.0 * ty), tz * tz * (3.0 - 2.0 * tz)
    c00 = _hash01(ix, iy, iz, seed) * (1 - ux) + _hash01(ix + 1, iy, iz, seed) * ux
    c10 = _hash01(ix, iy + 1, iz, seed) * (1 - ux) + _hash01(ix + 1, iy + 1, iz, seed) * ux
    c01 = _hash01(ix, iy, iz + 1, seed) * (1 - ux) + _hash01(ix + 1, iy, iz + 1, seed) * ux
    c11 = _hash01(ix, iy + 1, iz + 1, seed) * (1 - ux) + _hash01(ix + 1, iy + 1, iz + 1, seed) * ux
    c0 = c00 * (1 - uy) + c10 * uy
    c1 = c01 * (1 - uy) + c11 * uy
    return c0 * (1 - uz) + c1 * uz


@njit(cache=True)
def _fbm(x, y, z, seed):
    """Three octaves of value noise, normalised to [0, 1]."""
    total = 0.0
    amp = 1.0
    freq = 1.0
    norm = 0.0
    for octave in range(3):
        total += amp * _value_noise(x * freq, y * freq, z * freq, seed + 17 * octave)
        norm += amp
        amp *= 0.5
        freq *= 2.0
    return total / norm


@njit(cache=True)
def _albedo(lx, ly, lz, pattern, axis, seed, tf):
    """RGB albedo of the texture ``tf`` [13] at local point (lx, ly, lz)."""
    x = lx + tf[10]
    y = ly + tf[11]
    z = lz + tf[12]
    s = tf[6]
    if axis == 0:
        a, b, c = x, y, z
    elif axis == 1:
        a, b, c = y, z, x
    else:
        a, b, c = z, x, y
    if pattern == 0:  # noise
        t = 0.5 + 1.6 * (_fbm(x / s, y / s, z / s, seed) - 0.5)
    elif pattern == 1:  # stripes across ``axis``
        t = 0.5 + 0.5 * math.tanh(3.0 * math.sin(2.0 * math.pi * a / s))
    elif pattern == 2:  # 3D checker
        parity = np.int64(math.floor(x / s)) + np.int64(math.floor(y / s)) + np.int64(math.floor(z / s))
        t = float(parity & 1)
    elif pattern == 3:  # planks: grain along ``axis``, rows across the next axis
        row = np.int64(math.floor(b / s))
        length = 6.0 * s
        shifted = a + _hash01(row, 0, 0, seed) * length
        col = np.int64(math.floor(shifted / length))
        tint = _hash01(row, col, 1, seed)
        grain = _fbm(a / (2.0 * s), b / (0.5 * s), c / (0.5 * s), seed + 3)
        t = 0.55 * tint + 0.45 * grain
        if b / s - math.floor(b / s) < 0.05 or shifted / length - math.floor(shifted / length) < 0.01:
            t = 1.0
    elif pattern == 4:  # tiles in the plane normal to ``axis``
        i = np.int64(math.floor(b / s))
        j = np.int64(math.floor(c / s))
        t = 0.4 * _hash01(i, j, 2, seed)
        if b / s - math.floor(b / s) < 0.06 or c / s - math.floor(c / s) < 0.06:
            t = 1.0
    else:  # rings around ``axis``
        r = math.sqrt(b * b + c * c)
        t = 0.5 + 0.5 * math.sin(2.0 * math.pi * (r / s + 0.8 * _fbm(x / (2 * s), y / (2 * s), z / (2 * s), seed)))
    t = 0.5 + (t - 0.5) * tf[7]
    t = min(max(t, 0.0), 1.0)
    ns = tf[9]
    bright = 1.0 + tf[8] * 1.6 * (2.0 * _fbm(x / ns, y / ns, z / ns, seed + 101) - 1.0)
    bright = max(bright, 0.0)
    r_ = (tf[0] + (tf[3] - tf[0]) * t) * bright
    g_ = (tf[1] + (tf[4] - tf[1]) * t) * bright
    b_ = (tf[2] + (tf[5] - tf[2]) * t) * bright
    return r_, g_, b_


@njit(cache=True)
def _slab(o, d, h, tnear, tfar):
    """Clip [tnear, tfar] by the slab |o + t d| <= h; returns the new interval (empty if tnear > tfar)."""
    if abs(d) < 1e-15:
        if abs(o) > h:
            return 1.0, 0.0
        return tnear, tfar
    t1 = (-h - o) / d
    t2 = (h - o) / d
    if t1 > t2:
        t1, t2 = t2, t1
    return max(tnear, t1), min(tfar, t2)


@njit(cache=True)
def _intersect_local(shape, sx, sy, sz, ox, oy, oz, dx, dy, dz, tmin):
    """Nearest t > tmin where the local ray o + t d meets the primitive, and a face code (inf if none)."""
    inf = np.inf
    if shape == 0:  # box
        tn, tf_ = _slab(ox, dx, sx, -inf, inf)
        tn, tf_ = _slab(oy, dy, sy, tn, tf_)
        tn, tf_ = _slab(oz, dz, sz, tn, tf_)
        if tn > tf_:
            return inf, 0
        if tn > tmin:
            return tn, 0
        if tf_ > tmin:
            return tf_, 0
        return inf, 0
    if shape == 1:  # ellipsoid
        px, py, pz = ox / sx, oy / sy, oz / sz
        qx, qy, qz = dx / sx, dy / sy, dz / sz
        a = qx * qx + qy * qy + qz * qz
        b = px * qx + py * qy + pz * qz
        c = px * px + py * py + pz * pz - 1.0
        disc = b * b - a * c
        if disc < 0.0:
            return inf, 0
        sq = math.sqrt(disc)
        t0 = (-b - sq) / a
        if t0 > tmin:
            return t0, 0
        t1 = (-b + sq) / a
        if t1 > tmin:
            return t1, 0
        return inf, 0
    # capped frustum around local z: radius sx at z = -sz, sy at z = +sz
    r0, r1, h = sx, sy, sz
    rm = 0.5 * (r0 + r1)
    k = (r1 - r0) / (2.0 * h)
    best = inf
    face = 0
    q = rm + k * oz
    a = dx * dx + dy * dy - k * k * dz * dz
    b = 2.0 * (ox * dx + oy * dy - k * dz * q)
    c = ox * ox + oy * oy - q * q
    # the side's roots: two of the quadratic, one where it degenerates to a linear equation, or none
    # (-inf never passes the tmin test)
    root_lo = root_hi = -math.inf
    if abs(a) > 1e-14:
        disc = b * b - 4.0 * a * c
        if disc >= 0.0:
            sq = math.sqrt(disc)
            root_lo = (-b - sq) / (2.0 * a)
            root_hi = (-b + sq) / (2.0 * a)
    elif abs(b) > 1e-14:
        root_lo = -c / b
    for root in (root_lo, root_hi):
        if tmin < root < best:
            zz = oz + root * dz
            if -h <= zz <= h and rm + k * zz >= 0.0:
                best = root
                face = 0
    if abs(dz) > 1e-15:
        for cap in range(2):
            zc = -h if cap == 0 else h
            rc = r0 if cap == 0 else r1
            tc = (zc - oz) / dz
            if tmin < tc < best:
                xx = ox + tc * dx
                yy = oy + tc * dy
                if xx * xx + yy * yy <= rc * rc:
                    best = tc
                    face = 1 + cap
    return best, face


@njit(cache=True)
def _normal_local(shape, sx, sy, sz, x, y, z, face):
    """Unit outward normal (local frame) at local surface point (x, y, z)."""
    if shape == 0:
        ax, ay, az = abs(x) / sx, abs(y) / sy, abs(z) / sz
        if ax >= ay and ax >= az:
            return (1.0 if x >= 0 else -1.0), 0.0, 0.0
        if ay >= az:
            return 0.0, (1.0 if y >= 0 else -1.0), 0.0
        return 0.0, 0.0, (1.0 if z >= 0 else -1.0)
    if shape == 1:
        nx, ny, nz = x / (sx * sx), y / (sy * sy), z / (sz * sz)
    elif face == 1:
        return 0.0, 0.0, -1.0
    elif face == 2:
        return 0.0, 0.0, 1.0
    else:
        rm = 0.5 * (sx + sy)
        k = (sy - sx) / (2.0 * sz)
        nx, ny, nz = x, y, -k * (rm + k * z)
    n = math.sqrt(nx * nx + ny * ny + nz * nz)
    if n == 0.0:
        return 0.0, 0.0, 1.0
    return nx / n, ny / n, nz / n


@njit(inline="always")
def _meets_sphere(ox, oy, oz, dx, dy, dz, dd, sx, sy, sz, radius, tmin, tmax):
    """Whether the ray o + t d (``dd`` = |d|^2) meets the sphere of centre s and ``radius`` at some
    tmin < t < tmax (a bounding-sphere test), and o - s."""
    cx = ox - sx
    cy = oy - sy
    cz = oz - sz
    b = cx * dx + cy * dy + cz * dz
    c = cx * cx + cy * cy + cz * cz - radius * radius
    disc = b * b - dd * c
    if disc < 0.0:
        return False, cx, cy, cz
    sq = math.sqrt(disc)
    return not ((-b + sq) / dd <= tmin or (-b - sq) / dd >= tmax), cx, cy, cz


@njit(cache=True)
def cast_ray(ox, oy, oz, dx, dy, dz, tmin, tmax, shapes, centers, rotations, sizes, radii, clusters, any_hit):
    """Nearest primitive hit by o + t d with tmin < t < tmax: (t, primitive index or -1, face).

    ``clusters`` [C, 6] rows (first primitive, end primitive, centre xyz, radius) group the primitives
    of one object under a bounding sphere; with ``any_hit`` the first hit found is returned.
    """
    best_t = tmax
    best = -1
    best_face = 0
    dd = dx * dx + dy * dy + dz * dz
    for k in range(clusters.shape[0]):
        # cluster (one object) bounding sphere first, then its primitives
        hit, _, _, _ = _meets_sphere(ox, oy, oz, dx, dy, dz, dd, clusters[k, 2], clusters[k, 3], clusters[k, 4],
                                     clusters[k, 5], tmin, best_t)
        if not hit:
            continue
        for p in range(np.int64(clusters[k, 0]), np.int64(clusters[k, 1])):
            hit, cx, cy, cz = _meets_sphere(ox, oy, oz, dx, dy, dz, dd, centers[p, 0], centers[p, 1], centers[p, 2],
                                            radii[p], tmin, best_t)
            if not hit:
                continue
            R = rotations[p]
            lox = R[0, 0] * cx + R[1, 0] * cy + R[2, 0] * cz
            loy = R[0, 1] * cx + R[1, 1] * cy + R[2, 1] * cz
            loz = R[0, 2] * cx + R[1, 2] * cy + R[2, 2] * cz
            ldx = R[0, 0] * dx + R[1, 0] * dy + R[2, 0] * dz
            ldy = R[0, 1] * dx + R[1, 1] * dy + R[2, 1] * dz
            ldz = R[0, 2] * dx + R[1, 2] * dy + R[2, 2] * dz
            t, face = _intersect_local(shapes[p], sizes[p, 0], sizes[p, 1], sizes[p, 2], lox, loy, loz, ldx, ldy, ldz,
                                       tmin)
            if t < best_t:
                best_t = t
                best = p
                best_face = face
                if any_hit:
                    return best_t, best, best_face
    return best_t, best, best_face


@njit(cache=True)
def _shade(ox, oy, oz, dx, dy, dz, t, p, face, shapes, centers, rotations, sizes, radii, clusters, tex_int, tex_float,
           lights, light_power, ambient, shadows):
    """Lambertian radiance (RGB) of the hit (t, p, face) of ray o + t d."""
    hx, hy, hz = ox + t * dx, oy + t * dy, oz + t * dz
    R = rotations[p]
    cx, cy, cz = hx - centers[p, 0], hy - centers[p, 1], hz - centers[p, 2]
    lx = R[0, 0] * cx + R[1, 0] * cy + R[2, 0] * cz
    ly = R[0, 1] * cx + R[1, 1] * cy + R[2, 1] * cz
    lz = R[0, 2] * cx + R[1, 2] * cy + R[2, 2] * cz
    nlx, nly, nlz = _normal_local(shapes[p], sizes[p, 0], sizes[p, 1], sizes[p, 2], lx, ly, lz, face)
    nx = R[0, 0] * nlx + R[0, 1] * nly + R[0, 2] * nlz
    ny = R[1, 0] * nlx + R[1, 1] * nly + R[1, 2] * nlz
    nz = R[2, 0] * nlx + R[2, 1] * nly + R[2, 2] * nlz
    if nx * dx + ny * dy + nz * dz > 0.0:
        nx, ny, nz = -nx, -ny, -nz
    ar, ag, ab = _albedo(lx, ly, lz, tex_int[p, 0], tex_int[p, 1], tex_int[p, 2], tex_float[p])
    light = ambient * (0.75 + 0.25 * nz)
    for li in range(lights.shape[0]):
        vx, vy, vz = lights[li, 0] - hx, lights[li, 1] - hy, lights[li, 2] - hz
        dist = math.sqrt(vx * vx + vy * vy + vz * vz)
        vx, vy, vz = vx / dist, vy / dist, vz / dist
        cos = nx * vx + ny * vy + nz * vz
        if cos <= 0.0:
            continue
        if shadows:
            st, sp, sf = cast_ray(hx + 1e-4 * nx, hy + 1e-4 * ny, hz + 1e-4 * nz, vx, vy, vz, 1e-6, dist,
                                shapes, centers, rotations, sizes, radii, clusters, True)
            if sp >= 0:
                continue
        light += light_power[li] * cos / (1.0 + (dist / LIGHT_FALLOFF) ** 2)
    return ar * light, ag * light, ab * light


@njit(parallel=True, cache=True)
def _render_kernel(width, height, fx, fy, cx, cy, cam_rot, cam_pos, ss, shapes, centers, rotations, sizes, radii,
                   clusters,
                   tex_int, tex_float, lights, light_power, ambient, shadows):
    """Render one view.  cam_rot: [3, 3] camera-to-world rotation; cam_pos: [3].

    Returns rgb [H, W, 3] float64 (mean of ss*ss rays), prim [H, W] int64 (primitive hit by the pixel
    centre ray, -1 for none) and depth [H, W] (camera z of that hit, 0 for none).
    """
    rgb = np.zeros((height, width, 3))
    prim = np.full((height, width), -1, dtype=np.int64)
    depth = np.zeros((height, width))
    ox, oy, oz = cam_pos[0], cam_pos[1], cam_pos[2]
    for y in prange(height):
        for x in range(width):
            # pixel-centre ray; direction scaled so that t is the camera z
            ux = (x + 0.5 - cx) / fx
            uy = (y + 0.5 - cy) / fy
            dx = cam_rot[0, 0] * ux + cam_rot[0, 1] * uy + cam_rot[0, 2]
            dy = cam_rot[1, 0] * ux + cam_rot[1, 1] * uy + cam_rot[1, 2]
            dz = cam_rot[2, 0] * ux + cam_rot[2, 1] * uy + cam_rot[2, 2]
            t, p, face = cast_ray(ox, oy, oz, dx, dy, dz, 1e-6, np.inf, shapes, centers, rotations, sizes, radii,
                                clusters, False)
            if p >= 0:
                prim[y, x] = p
                depth[y, x] = t
            acc_r = 0.0
            acc_g = 0.0
            acc_b = 0.0
            for sy in range(ss):
                for sx in range(ss):
                    ux = (x + (sx + 0.5) / ss - cx) / fx
                    uy = (y + (sy + 0.5) / ss - cy) / fy
                    dx = cam_rot[0, 0] * ux + cam_rot[0, 1] * uy + cam_rot[0, 2]
                    dy = cam_rot[1, 0] * ux + cam_rot[1, 1] * uy + cam_rot[1, 2]
                    dz = cam_rot[2, 0] * ux + cam_rot[2, 1] * uy + cam_rot[2, 2]
                    t, p, face = cast_ray(ox, oy, oz, dx, dy, dz, 1e-6, np.inf, shapes, centers, rotations, sizes,
                                        radii, clusters, False)
                    if p >= 0:
                        r_, g_, b_ = _shade(ox, oy, oz, dx, dy, dz, t, p, face, shapes, centers, rotations, sizes,
                                            radii, clusters, tex_int, tex_float, lights, light_power, ambient, shadows)
                        acc_r += r_
                        acc_g += g_
                        acc_b += b_
            inv = 1.0 / (ss * ss)
            rgb[y, x, 0] = acc_r * inv
            rgb[y, x, 1] = acc_g * inv
            rgb[y, x, 2] = acc_b * inv
    return rgb, prim, depth


def render_view(
    packed: PackedScene, camera: Camera, supersample: int = 2, ambient: float = 0.45, shadows: bool = True
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ray-cast one view (numba kernel).

    Returns:
        rgb: [H, W, 3] float64 linear radiance (mean over supersample^2 rays per pixel).
        prim: [H, W] int64 index of the primitive hit by the pixel-centre ray (-1 for none).
        depth: [H, W] float64 camera z of that hit (0 for none).
    """
    c2w = camera.camera_to_world
    K = camera.K
    return _render_kernel(
        camera.width, camera.height, K[0, 0], K[1, 1], K[0, 2], K[1, 2],
        np.ascontiguousarray(c2w[:3, :3]), np.ascontiguousarray(c2w[:3, 3]), int(supersample),
        packed.shapes, packed.centers, packed.rotations, packed.sizes, packed.radii, packed.clusters,
        packed.tex_int, packed.tex_float, packed.lights, packed.light_power, float(ambient), bool(shadows),
    )
