"""Procedural indoor rooms, rendered exactly by ray casting: the default synthetic benchmark.

A room is a closed box (floor, ceiling, four walls) furnished with objects built from three kinds of
primitives (boxes, ellipsoids/spheres, capped frustums/cylinders): a table set (table = top + legs,
chairs = seat + back + legs, items on the table, a rug under it), a shelf holding rows of books and
other items, a sofa with pillows, a cabinet with a table lamp, a sideboard with a television, a floor
lamp, plants, a door, a window, paintings, a clock, balls, baskets... placed so that they touch and
occlude each other (items stand on tables and shelves, furniture stands against the walls).  Some
pieces are optional, so rooms differ in inventory as well as in layout.  Every primitive carries a procedural *solid* texture evaluated
in its own local (object-space) coordinates, so a surface point has the same colour from every view;
shading is Lambertian under fixed point lights with hard shadows and a hemispherical ambient term:
nothing depends on the viewing direction, so a diffuse Gaussian model can fit the images exactly.

Cameras follow a 360-degree loop around the room centre (kept free of furniture), looking outwards
with smooth height, pitch and yaw variation, like the Replica captures; every ``test_every``-th view
is held out for testing.

Outputs (see :mod:`trace3d.scene`): ``images/`` (RGB, ``supersample``^2 rays per pixel),
``instances/`` (leaf ids of the pixel-centre ray), ``depth/`` (camera z of the pixel-centre ray),
``cameras.json``, ``objects.json`` (part -> object -> group hierarchy, ``evaluated`` = non-structural
objects with at least ``min_visible_pixels`` pixels in some view), ``meta.json``.

The ray caster is a numba kernel (:func:`render_view`); :func:`render_view_reference` is its slow,
independently written numpy twin used by the tests.  Everything is deterministic from ``seed``.
"""

from __future__ import annotations

import colorsys
import dataclasses
import logging
import math
import os
import tempfile
import time
from pathlib import Path

import numba
import numpy as np
from numba import njit, prange
from tqdm import tqdm

from ..errors import ConfigError, Trace3DError
from ..io import write_json
from ..params import from_mapping, to_dict
from ..scene import Camera, ObjectTable, SceneObject, write_cameras, write_frame

log = logging.getLogger(__name__)

# ----------------------------------------------------------------------------------------------
# Parameters
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass
class SyntheticParams:
    """Parameters of one synthetic room; the defaults are the default benchmark room.

    Attributes:
        seed: seeds the layout, the textures and the camera path.
        width, height: image size in pixels.
        fov_x_deg: horizontal field of view (square pixels, principal point at the image centre).
        num_views: views on the 360-degree loop.
        test_every: every ``test_every``-th view (starting at ``test_every // 2``) is a test view.
        num_objects: objects in the room, not counting walls, floor and ceiling (a composite object
            such as a table counts once; its parts are extra leaf ids).
        room_width_range, room_depth_range, room_height_range: metres, (min, max) sampled uniformly.
        camera_radius: mean radius of the camera loop around the room centre (metres).
        camera_height: mean camera height above the floor (metres).
        camera_height_amplitude: height variation along the loop (metres).
        camera_pitch_deg: mean pitch (negative looks down).
        camera_pitch_amplitude_deg, camera_yaw_amplitude_deg: pitch / yaw variation along the loop.
        clear_radius: radius of the furniture-free disk around the room centre (metres); must exceed
            the camera loop so that no camera sits inside an object.
        supersample: RGB rays per pixel per axis (2 -> 2x2 anti-aliasing); instance ids and depth
            always come from the single pixel-centre ray.
        texture_scale: multiplies every texture feature size.
        texture_contrast: multiplies every texture contrast.
        ambient: hemispherical ambient light level.
        light_power: power of each of the two ceiling lights.
        shadows: cast hard shadows from the ceiling lights.
        min_visible_pixels: an object is evaluated when some view shows at least this many of its
            pixels.
    """

    seed: int = 0
    width: int = 160
    height: int = 120
    fov_x_deg: float = 80.0
    num_views: int = 72
    test_every: int = 8
    num_objects: int = 32
    room_width_range: tuple[float, float] = (5.4, 6.6)
    room_depth_range: tuple[float, float] = (4.6, 5.6)
    room_height_range: tuple[float, float] = (2.6, 3.0)
    camera_radius: float = 0.5
    camera_height: float = 1.45
    camera_height_amplitude: float = 0.15
    camera_pitch_deg: float = -18.0
    camera_pitch_amplitude_deg: float = 8.0
    camera_yaw_amplitude_deg: float = 12.0
    clear_radius: float = 1.05
    supersample: int = 2
    texture_scale: float = 1.0
    texture_contrast: float = 1.0
    ambient: float = 0.45
    light_power: float = 0.9
    shadows: bool = True
    min_visible_pixels: int = 64

    def __post_init__(self) -> None:
        where = "synthetic params"
        if self.width < 8 or self.height < 8:
            raise ConfigError(f"{where}: width and height must be at least 8 pixels, got {self.width}x{self.height}.")
        if not 20.0 <= self.fov_x_deg <= 150.0:
            raise ConfigError(f"{where}: fov_x_deg must lie in [20, 150], got {self.fov_x_deg}.")
        if self.num_views < 2:
            raise ConfigError(f"{where}: num_views must be at least 2, got {self.num_views}.")
        if self.test_every < 2:
            raise ConfigError(f"{where}: test_every must be at least 2, got {self.test_every}.")
        if self.num_objects < 1:
            raise ConfigError(f"{where}: num_objects must be at least 1, got {self.num_objects}.")
        for name in ("room_width_range", "room_depth_range", "room_height_range"):
            lo, hi = getattr(self, name)
            if not 0 < lo <= hi:
                raise ConfigError(f"{where}: {name} must be (min, max) with 0 < min <= max, got {(lo, hi)}.")
            setattr(self, name, (float(lo), float(hi)))
        if min(self.room_width_range[0], self.room_depth_range[0]) < 2 * self.clear_radius + 1.6:
            raise ConfigError(
                f"{where}: the room's smaller side must be at least 2 * clear_radius + 1.6 m "
                f"= {2 * self.clear_radius + 1.6:.2f} m to fit furniture around the camera loop."
            )
        if self.room_height_range[0] < 2.3:
            raise ConfigError(f"{where}: room_height_range must start at 2.3 m or more, got {self.room_height_range}.")
        if self.camera_radius * 1.3 + 0.3 > self.clear_radius:
            raise ConfigError(
                f"{where}: clear_radius ({self.clear_radius}) must exceed 1.3 * camera_radius + 0.3 m "
                f"({self.camera_radius * 1.3 + 0.3:.2f}) so that cameras stay away from furniture."
            )
        if not 0.5 <= self.camera_height <= self.room_height_range[0] - 0.5:
            raise ConfigError(f"{where}: camera_height must lie between 0.5 m and the ceiling minus 0.5 m.")
        if self.supersample < 1 or self.supersample > 8:
            raise ConfigError(f"{where}: supersample must lie in 1..8, got {self.supersample}.")
        if self.texture_scale <= 0 or self.texture_contrast < 0:
            raise ConfigError(f"{where}: texture_scale must be positive and texture_contrast non-negative.")
        if self.min_visible_pixels < 0:
            raise ConfigError(f"{where}: min_visible_pixels must be non-negative.")


def params_from(d: dict | None) -> SyntheticParams:
    """Strictly typed :class:`SyntheticParams` from a config mapping (unknown keys are refused)."""
    return from_mapping(SyntheticParams, d, "synthetic params")


# ----------------------------------------------------------------------------------------------
# Primitives and textures
# ----------------------------------------------------------------------------------------------

SHAPE_BOX, SHAPE_ELLIPSOID, SHAPE_FRUSTUM = 0, 1, 2
SHAPE_NAMES = ("box", "ellipsoid", "frustum")
PAT_NOISE, PAT_STRIPES, PAT_CHECKER, PAT_PLANKS, PAT_TILES, PAT_RINGS = range(6)
TEX_FLOATS = 13  # colour0 (3), colour1 (3), scale, contrast, noise_amp, noise_scale, offset (3)
STRUCTURE_CATEGORIES = ("floor", "ceiling", "wall")
LIGHT_FALLOFF = 3.0  # metres: light power halves at this distance


@dataclasses.dataclass
class Texture:
    """A procedural solid texture evaluated at object-space points.

    ``pattern`` (one of ``PAT_*``) yields t in [0, 1]; colour = colour0 + (colour1 - colour0) * t,
    multiplied by a value-noise brightness modulation of amplitude ``noise_amp``.  ``axis`` is the
    pattern's direction (stripes, plank grain, tile / ring normal).  ``offset`` [3] shifts the
    pattern so that no face coincides with a cell boundary.
    """

    pattern: int
    color0: tuple[float, float, float]
    color1: tuple[float, float, float]
    scale: float
    contrast: float = 1.0
    noise_amp: float = 0.1
    noise_scale: float = 0.1
    axis: int = 0
    seed: int = 0
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclasses.dataclass
class Primitive:
    """One solid in world space.

    Attributes:
        shape: ``SHAPE_BOX`` (size = half extents), ``SHAPE_ELLIPSOID`` (size = semi-axes) or
            ``SHAPE_FRUSTUM`` (size = bottom radius, top radius, half height; axis = local z).
        center: [3] world position of the local origin (the solid's centre).
        rotation: [3, 3] local-to-world rotation (columns are the local axes in world space).
        size: [3] see ``shape``.
        leaf: key of the hierarchy leaf it belongs to (becomes the instance id).
        texture: its surface texture, evaluated in local coordinates.
    """

    shape: int
    center: np.ndarray
    rotation: np.ndarray
    size: np.ndarray
    leaf: int
    texture: Texture


@dataclasses.dataclass
class PackedScene:
    """Flat arrays of P primitives and L lights that the kernels read.

    Attributes:
        shapes: [P] int64.  centers: [P, 3].  rotations: [P, 3, 3] local-to-world.  sizes: [P, 3].
        radii: [P] bounding-sphere radii.  clusters: [C, 6] (first, end, centre xyz, radius): contiguous
        primitive ranges (one per object) with a bounding sphere.  leaf_ids: [P] int64 instance ids.
        tex_int: [P, 3] int64 (pattern, axis, seed).  tex_float: [P, 13] (see ``TEX_FLOATS``).
        lights: [L, 3] positions.  light_power: [L].
    """

    shapes: np.ndarray
    centers: np.ndarray
    rotations: np.ndarray
    sizes: np.ndarray
    radii: np.ndarray
    clusters: np.ndarray
    leaf_ids: np.ndarray
    tex_int: np.ndarray
    tex_float: np.ndarray
    lights: np.ndarray
    light_power: np.ndarray

    def geometry(self) -> tuple:
        """The geometry arguments of the kernels' ``_trace``: shapes, centers, rotations, sizes, radii, clusters."""
        return self.shapes, self.centers, self.rotations, self.sizes, self.radii, self.clusters


def bounding_radius(shape: int, size: np.ndarray) -> float:
    """Radius of a sphere around the local origin that contains the primitive."""
    if shape == SHAPE_FRUSTUM:
        return float(math.hypot(max(size[0], size[1]), size[2]))
    if shape == SHAPE_ELLIPSOID:
        return float(max(size))
    return float(np.linalg.norm(size))


def pack_scene(primitives: list[Primitive], leaf_ids: list[int], lights: np.ndarray, power: np.ndarray,
               groups: list[int] | None = None) -> PackedScene:
    """Pack primitives (with their final instance ids ``leaf_ids`` [P]) and lights [L, 3] for the kernels.

    ``groups`` [P] (e.g. the object of each primitive) must be contiguous runs; each run becomes one
    bounding-sphere cluster.  Default: every primitive is its own cluster.
    """
    P = len(primitives)
    tex_int = np.zeros((P, 3), dtype=np.int64)
    tex_float = np.zeros((P, TEX_FLOATS), dtype=np.float64)
    for i, prim in enumerate(primitives):
        tx = prim.texture
        tex_int[i] = (tx.pattern, tx.axis, tx.seed)
        tex_float[i] = (*tx.color0, *tx.color1, tx.scale, tx.contrast, tx.noise_amp, tx.noise_scale, *tx.offset)
    centers = np.array([p.center for p in primitives], dtype=np.float64).reshape(P, 3)
    radii = np.array([bounding_radius(p.shape, p.size) * 1.0001 + 1e-6 for p in primitives], dtype=np.float64)
    groups = list(range(P)) if groups is None else list(groups)
    starts = [i for i in range(P) if i == 0 or groups[i] != groups[i - 1]]
    if len(set(groups)) != len(starts):
        raise ValueError("pack_scene: primitives of one group must be contiguous")
    clusters = np.zeros((len(starts), 6))
    for k, start in enumerate(starts):
        end = starts[k + 1] if k + 1 < len(starts) else P
        lo = (centers[start:end] - radii[start:end, None]).min(0)
        hi = (centers[start:end] + radii[start:end, None]).max(0)
        mid = (lo + hi) / 2
        radius = (np.linalg.norm(centers[start:end] - mid, axis=1) + radii[start:end]).max()
        clusters[k] = (start, end, *mid, radius * 1.0001 + 1e-6)
    return PackedScene(
        shapes=np.array([p.shape for p in primitives], dtype=np.int64),
        centers=centers,
        rotations=np.array([p.rotation for p in primitives], dtype=np.float64).reshape(P, 3, 3),
        sizes=np.array([p.size for p in primitives], dtype=np.float64).reshape(P, 3),
        radii=radii,
        clusters=clusters,
        leaf_ids=np.asarray(leaf_ids, dtype=np.int64),
        tex_int=tex_int,
        tex_float=tex_float,
        lights=np.asarray(lights, dtype=np.float64).reshape(-1, 3),
        light_power=np.asarray(power, dtype=np.float64).reshape(-1),
    )


# ----------------------------------------------------------------------------------------------
# Fast kernels (numba)
# ----------------------------------------------------------------------------------------------


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
    if abs(a) > 1e-14:
        disc = b * b - 4.0 * a * c
        if disc >= 0.0:
            sq = math.sqrt(disc)
            for root in ((-b - sq) / (2.0 * a), (-b + sq) / (2.0 * a)):
                if tmin < root < best:
                    zz = oz + root * dz
                    if -h <= zz <= h and rm + k * zz >= 0.0:
                        best = root
                        face = 0
    elif abs(b) > 1e-14:
        root = -c / b
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


@njit(cache=True)
def _trace(ox, oy, oz, dx, dy, dz, tmin, tmax, shapes, centers, rotations, sizes, radii, clusters, any_hit):
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
        cx = ox - clusters[k, 2]
        cy = oy - clusters[k, 3]
        cz = oz - clusters[k, 4]
        b = cx * dx + cy * dy + cz * dz
        c = cx * cx + cy * cy + cz * cz - clusters[k, 5] * clusters[k, 5]
        disc = b * b - dd * c
        if disc < 0.0:
            continue
        sq = math.sqrt(disc)
        if (-b + sq) / dd <= tmin or (-b - sq) / dd >= best_t:
            continue
        for p in range(np.int64(clusters[k, 0]), np.int64(clusters[k, 1])):
            cx = ox - centers[p, 0]
            cy = oy - centers[p, 1]
            cz = oz - centers[p, 2]
            b = cx * dx + cy * dy + cz * dz
            c = cx * cx + cy * cy + cz * cz - radii[p] * radii[p]
            disc = b * b - dd * c
            if disc < 0.0:
                continue
            sq = math.sqrt(disc)
            if (-b + sq) / dd <= tmin or (-b - sq) / dd >= best_t:
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
            st, sp, sf = _trace(hx + 1e-4 * nx, hy + 1e-4 * ny, hz + 1e-4 * nz, vx, vy, vz, 1e-6, dist,
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
            t, p, face = _trace(ox, oy, oz, dx, dy, dz, 1e-6, np.inf, shapes, centers, rotations, sizes, radii,
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
                    t, p, face = _trace(ox, oy, oz, dx, dy, dz, 1e-6, np.inf, shapes, centers, rotations, sizes,
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


# ----------------------------------------------------------------------------------------------
# Slow reference twin (numpy, vectorised over rays, written independently of the kernels)
# ----------------------------------------------------------------------------------------------


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


def _ref_trace(packed: PackedScene, o: np.ndarray, d: np.ndarray, tmin: float = 1e-6):
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
    t, prim, face = _ref_trace(packed, o, d)
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
            ts, ps, _ = _ref_trace(packed, points + 1e-4 * normals, to_light)
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
    t, prim, _ = _ref_trace(packed, origin, rays(0.5, 0.5))
    depth = np.where(prim >= 0, t, 0.0).reshape(H, W)
    rgb = np.zeros((H * W, 3))
    ss = int(supersample)
    for sy in range(ss):
        for sx in range(ss):
            rgb += _ref_shade(packed, origin, rays((sx + 0.5) / ss, (sy + 0.5) / ss), ambient, shadows)
    return (rgb / ss**2).reshape(H, W, 3), prim.reshape(H, W), depth


def to_uint8(rgb: np.ndarray) -> np.ndarray:
    """[H, W, 3] linear radiance -> uint8 display values (clipped, mild gamma)."""
    return np.round(np.clip(rgb, 0.0, 1.0) ** (1 / 1.1) * 255.0).astype(np.uint8)


# ----------------------------------------------------------------------------------------------
# Room layout
# ----------------------------------------------------------------------------------------------


def rot_z(angle: float) -> np.ndarray:
    """[3, 3] rotation by ``angle`` radians about the world up axis (z)."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_x(angle: float) -> np.ndarray:
    """[3, 3] rotation by ``angle`` radians about x."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


@dataclasses.dataclass
class LocalPart:
    """A primitive in the frame of the object being built (origin at the object's floor centre,
    x = width, y = towards the object's front, z = up)."""

    name: str | None
    shape: int
    center: tuple[float, float, float]
    size: tuple[float, float, float]
    texture: Texture
    rotation: np.ndarray | None = None


def _box(name, center, half, texture, rotation=None) -> LocalPart:
    """A box part: ``half`` = half extents."""
    return LocalPart(name, SHAPE_BOX, center, half, texture, rotation)


def _ellipsoid(name, center, axes, texture, rotation=None) -> LocalPart:
    """An ellipsoid part: ``axes`` = semi-axes."""
    return LocalPart(name, SHAPE_ELLIPSOID, center, axes, texture, rotation)


def _frustum(name, center, size, texture, rotation=None) -> LocalPart:
    """A capped frustum around the local z axis: ``size`` = (bottom radius, top radius, half height)."""
    return LocalPart(name, SHAPE_FRUSTUM, center, size, texture, rotation)


def _single(category: str, part: LocalPart, half_x: float, half_y: float, height: float) -> "ObjectSpec":
    """An object made of one primitive (its leaf id is the object id)."""
    return ObjectSpec(category, category, [part], half_x, half_y, height)


def _reseed(texture: Texture, k: int) -> Texture:
    """The same material with a different noise seed (neighbouring parts do not repeat each other)."""
    return dataclasses.replace(texture, seed=texture.seed + k)


@dataclasses.dataclass
class ObjectSpec:
    """An object ready to be placed: local parts, footprint half sizes (x, y) and height.

    ``aligned``: keep the support's orientation (a row of books stands along the shelf) instead of
    a random yaw.
    """

    name: str
    category: str
    parts: list[LocalPart]
    half_x: float
    half_y: float
    height: float
    aligned: bool = False

    def yaw_radius(self) -> float:
        """Radius of the footprint under any yaw: max(half_x, half_y) when every part is a solid of
        revolution around the object's vertical axis, else the footprint's half diagonal."""
        round_ = all(p.shape != SHAPE_BOX and p.rotation is None and abs(p.center[0]) < 1e-9
                     and abs(p.center[1]) < 1e-9 for p in self.parts)
        return max(self.half_x, self.half_y) if round_ else math.hypot(self.half_x, self.half_y)


@dataclasses.dataclass
class _Node:
    key: int
    name: str
    level: str
    category: str
    parent: int | None


@dataclasses.dataclass
class _Surface:
    """A horizontal support (table top, shelf board ...) in its own frame (origin at its centre)."""

    origin: np.ndarray  # [3]; z = top of the support
    rotation: np.ndarray  # [3, 3]
    half_x: float
    half_y: float
    clearance: float
    parent: int | None  # group key for items placed here
    occupied: list = dataclasses.field(default_factory=list)  # local rects (x0, x1, y0, y1)
    kinds: tuple = ("mug", "vase", "bowl", "book_pile", "bottle", "ball", "fruit_bowl", "plant_small", "box_small")


@dataclasses.dataclass
class RoomLayout:
    """A furnished room: primitives, hierarchy, lights and a summary."""

    size: tuple[float, float, float]
    primitives: list[Primitive]
    nodes: list[_Node]
    lights: np.ndarray
    light_power: np.ndarray
    key_to_id: dict

    def packed(self) -> PackedScene:
        """Kernel arrays; the primitives of one object share a bounding-sphere cluster."""
        parent = {n.key: n.parent for n in self.nodes}
        level = {n.key: n.level for n in self.nodes}
        objects = [p.leaf if level[p.leaf] != "part" else parent[p.leaf] for p in self.primitives]
        return pack_scene(self.primitives, [self.key_to_id[p.leaf] for p in self.primitives], self.lights,
                          self.light_power, objects)


def _rgb(h: float, s: float, v: float) -> tuple[float, float, float]:
    return tuple(float(c) for c in colorsys.hsv_to_rgb(h % 1.0, min(max(s, 0.0), 1.0), min(max(v, 0.0), 1.0)))


class _RoomBuilder:
    """Places furniture and items in a room; all randomness comes from ``rng``."""

    def __init__(self, params: SyntheticParams, rng: np.random.Generator):
        self.p = params
        self.rng = rng
        self.lx = float(rng.uniform(*params.room_width_range))
        self.ly = float(rng.uniform(*params.room_depth_range))
        self.lz = float(rng.uniform(*params.room_height_range))
        self.nodes: list[_Node] = []
        self.primitives: list[Primitive] = []
        self.floor_rects: list[tuple[float, float, float, float]] = []
        self.wall_rects: dict[int, list[tuple[float, float, float, float]]] = {w: [] for w in range(4)}
        self.surfaces: list[_Surface] = []
        self.counter: dict[str, int] = {}
        self.num_objects = 0
        self.palette_hue = float(rng.uniform(0, 1))  # room colour theme
        self.table_set: tuple | None = None  # (origin, rotation, half_x, half_y, group) of the dining set

    # --- hierarchy ---------------------------------------------------------------------------
    def _new_node(self, name: str, level: str, category: str, parent: int | None) -> int:
        key = len(self.nodes)
        self.nodes.append(_Node(key, name, level, category, parent))
        return key

    def _name(self, category: str) -> str:
        self.counter[category] = self.counter.get(category, 0) + 1
        return f"{category}_{self.counter[category]}"

    def new_group(self, category: str) -> int:
        return self._new_node(self._name(category), "group", category, None)

    def room_left(self) -> int:
        return self.p.num_objects - self.num_objects

    def place(self, spec: ObjectSpec, origin: np.ndarray, rotation: np.ndarray, parent: int | None = None,
              structural: bool = False) -> int:
        """Add ``spec`` with its local frame at ``origin`` [3] / ``rotation`` [3, 3]; returns the object key."""
        name = spec.category if structural else self._name(spec.category)
        obj = self._new_node(name, "object", spec.category, parent)
        if not structural:
            self.num_objects += 1
        composite = len(spec.parts) > 1
        for part in spec.parts:
            leaf = obj
            if composite:
                leaf = self._new_node(f"{name}/{part.name}", "part", spec.category, obj)
            local_rot = np.eye(3) if part.rotation is None else part.rotation
            self.primitives.append(
                Primitive(
                    shape=part.shape,
                    center=np.asarray(origin, dtype=np.float64) + rotation @ np.asarray(part.center, dtype=np.float64),
                    rotation=rotation @ local_rot,
                    size=np.asarray(part.size, dtype=np.float64),
                    leaf=leaf,
                    texture=part.texture,
                )
            )
        return obj

    # --- textures ----------------------------------------------------------------------------
    def texture(self, kind: str) -> Texture:
        """A random texture of a material family (scales in metres)."""
        r = self.rng
        ts, tc = self.p.texture_scale, self.p.texture_contrast
        seed = int(r.integers(0, 2**20))
        offset = tuple(float(v) for v in r.uniform(0.0, 10.0, 3))
        hue = self.palette_hue
        if kind == "wall":
            pattern = int(r.choice([PAT_STRIPES, PAT_NOISE, PAT_TILES]))
            h = hue + r.uniform(-0.08, 0.08)
            c0 = _rgb(h, r.uniform(0.08, 0.3), r.uniform(0.72, 0.88))
            c1 = _rgb(h + r.uniform(-0.1, 0.1), r.uniform(0.15, 0.45), r.uniform(0.45, 0.65))
            low, high = {PAT_STRIPES: (0.12, 0.22), PAT_NOISE: (0.25, 0.4), PAT_TILES: (0.35, 0.6)}[pattern]
            scale = r.uniform(low, high)
            axis = 0 if pattern == PAT_STRIPES else 1
            return Texture(pattern, c0, c1, scale * ts, 0.8 * tc, 0.25, 0.3 * ts, axis, seed, offset)
        if kind == "floor":
            pattern = int(r.choice([PAT_PLANKS, PAT_TILES, PAT_CHECKER]))
            if pattern == PAT_PLANKS:
                h = r.uniform(0.05, 0.1)
                c0 = _rgb(h, r.uniform(0.4, 0.6), r.uniform(0.55, 0.75))
                c1 = _rgb(h, r.uniform(0.5, 0.7), r.uniform(0.25, 0.4))
                return Texture(pattern, c0, c1, r.uniform(0.14, 0.2) * ts, tc, 0.2, 0.2 * ts, 0, seed, offset)
            c0 = _rgb(r.uniform(0, 1), r.uniform(0.05, 0.25), r.uniform(0.65, 0.85))
            c1 = _rgb(r.uniform(0, 1), r.uniform(0.1, 0.4), r.uniform(0.25, 0.45))
            scale = r.uniform(0.35, 0.5) if pattern == PAT_TILES else r.uniform(0.3, 0.45)
            return Texture(pattern, c0, c1, scale * ts, 0.9 * tc, 0.3, 0.12 * ts, 2, seed, offset)
        if kind == "ceiling":
            c0 = _rgb(hue, 0.05, 0.9)
            c1 = _rgb(hue, 0.1, 0.7)
            return Texture(PAT_NOISE, c0, c1, 0.4 * ts, 0.6 * tc, 0.15, 0.25 * ts, 0, seed, offset)
        if kind == "wood":
            pattern = int(r.choice([PAT_PLANKS, PAT_RINGS, PAT_STRIPES]))
            h = r.uniform(0.04, 0.11)
            c0 = _rgb(h, r.uniform(0.35, 0.65), r.uniform(0.5, 0.8))
            c1 = _rgb(h, r.uniform(0.5, 0.8), r.uniform(0.2, 0.4))
            scale = {PAT_PLANKS: 0.1, PAT_RINGS: 0.06, PAT_STRIPES: 0.07}[pattern] * r.uniform(0.8, 1.3)
            return Texture(pattern, c0, c1, scale * ts, 0.9 * tc, 0.25, 0.08 * ts, int(r.integers(0, 3)), seed, offset)
        if kind == "fabric":
            pattern = int(r.choice([PAT_NOISE, PAT_CHECKER, PAT_STRIPES]))
            h = r.uniform(0, 1)
            c0 = _rgb(h, r.uniform(0.3, 0.7), r.uniform(0.45, 0.8))
            c1 = _rgb(h + r.uniform(-0.2, 0.2), r.uniform(0.3, 0.8), r.uniform(0.2, 0.45))
            scale = {PAT_NOISE: 0.12, PAT_CHECKER: 0.09, PAT_STRIPES: 0.08}[pattern] * r.uniform(0.8, 1.4)
            return Texture(pattern, c0, c1, scale * ts, 0.8 * tc, 0.25, 0.07 * ts, int(r.integers(0, 3)), seed, offset)
        if kind == "paint":  # lacquered furniture, doors
            h = r.uniform(0, 1)
            c0 = _rgb(h, r.uniform(0.2, 0.6), r.uniform(0.6, 0.9))
            c1 = _rgb(h + 0.05, r.uniform(0.3, 0.7), r.uniform(0.35, 0.55))
            pattern = int(r.choice([PAT_NOISE, PAT_TILES]))
            return Texture(pattern, c0, c1, r.uniform(0.15, 0.3) * ts, 0.7 * tc, 0.2, 0.06 * ts, 1, seed, offset)
        if kind == "metal":
            c0 = _rgb(0.6, 0.05, r.uniform(0.6, 0.8))
            c1 = _rgb(0.6, 0.1, r.uniform(0.25, 0.4))
            return Texture(PAT_NOISE, c0, c1, 0.08 * ts, 0.8 * tc, 0.15, 0.06 * ts, 2, seed, offset)
        if kind == "ceramic":
            pattern = int(r.choice([PAT_STRIPES, PAT_CHECKER, PAT_NOISE]))
            h = r.uniform(0, 1)
            c0 = _rgb(h, r.uniform(0.4, 0.9), r.uniform(0.6, 0.95))
            c1 = _rgb(h + r.uniform(0.2, 0.5), r.uniform(0.5, 0.9), r.uniform(0.3, 0.7))
            scale = {PAT_STRIPES: 0.05, PAT_CHECKER: 0.04, PAT_NOISE: 0.05}[pattern]
            return Texture(pattern, c0, c1, scale * ts, tc, 0.15, 0.06 * ts, 2, seed, offset)
        if kind == "plant":
            h = r.uniform(0.22, 0.38)
            c0 = _rgb(h, r.uniform(0.5, 0.8), r.uniform(0.55, 0.8))
            c1 = _rgb(h + 0.05, r.uniform(0.6, 0.9), r.uniform(0.15, 0.3))
            return Texture(PAT_NOISE, c0, c1, 0.08 * ts, 1.2 * tc, 0.3, 0.07 * ts, 0, seed, offset)
        if kind == "paper":  # book covers
            h = r.uniform(0, 1)
            c0 = _rgb(h, r.uniform(0.4, 0.9), r.uniform(0.4, 0.9))
            c1 = _rgb(h + r.uniform(0.3, 0.6), r.uniform(0.2, 0.8), r.uniform(0.2, 0.9))
            return Texture(PAT_STRIPES, c0, c1, r.uniform(0.05, 0.09) * ts, 0.8 * tc, 0.15, 0.06 * ts, 2, seed, offset)
        if kind == "art":
            pattern = int(r.choice([PAT_NOISE, PAT_RINGS, PAT_CHECKER, PAT_STRIPES]))
            c0 = _rgb(r.uniform(0, 1), r.uniform(0.5, 1.0), r.uniform(0.6, 1.0))
            c1 = _rgb(r.uniform(0, 1), r.uniform(0.5, 1.0), r.uniform(0.15, 0.5))
            scale = {PAT_NOISE: 0.25, PAT_RINGS: 0.12, PAT_CHECKER: 0.1, PAT_STRIPES: 0.1}[pattern]
            scale *= r.uniform(0.8, 1.3)
            return Texture(pattern, c0, c1, scale * ts, 1.2 * tc, 0.35, 0.12 * ts, 1, seed, offset)
        if kind == "sky":
            c0 = _rgb(0.58, 0.15, 0.98)
            c1 = _rgb(0.6, 0.6, 0.85)
            return Texture(PAT_NOISE, c0, c1, 0.35 * ts, 1.3 * tc, 0.1, 0.2 * ts, 0, seed, offset)
        if kind == "rug":
            pattern = int(r.choice([PAT_TILES, PAT_CHECKER, PAT_STRIPES, PAT_RINGS]))
            h = r.uniform(0, 1)
            c0 = _rgb(h, r.uniform(0.3, 0.7), r.uniform(0.55, 0.85))
            c1 = _rgb(h + r.uniform(0.3, 0.6), r.uniform(0.5, 0.9), r.uniform(0.2, 0.5))
            scale = {PAT_TILES: 0.3, PAT_CHECKER: 0.22, PAT_STRIPES: 0.18, PAT_RINGS: 0.2}[pattern]
            return Texture(pattern, c0, c1, scale * ts, tc, 0.3, 0.08 * ts, 2, seed, offset)
        if kind == "dark":
            c0 = _rgb(0.6, 0.1, 0.2)
            c1 = _rgb(0.6, 0.3, 0.05)
            return Texture(PAT_NOISE, c0, c1, 0.15 * ts, tc, 0.2, 0.1 * ts, 0, seed, offset)
        if kind == "shade":
            h = r.uniform(0.05, 0.15)
            c0 = _rgb(h, r.uniform(0.1, 0.4), 0.95)
            c1 = _rgb(h, r.uniform(0.3, 0.6), 0.6)
            return Texture(PAT_STRIPES, c0, c1, 0.06 * ts, 0.6 * tc, 0.1, 0.05 * ts, 2, seed, offset)
        raise ValueError(f"unknown texture kind {kind!r}")

    def texture_of(self, *kinds: str) -> Texture:
        """A random texture of one of the material families ``kinds``."""
        return self.texture(str(self.rng.choice(kinds)))

    # --- geometry helpers ----------------------------------------------------------------------
    def wall_frame(self, wall: int) -> tuple[np.ndarray, np.ndarray, float]:
        """(origin [3] on the wall at floor level, rotation [3, 3] with y pointing into the room, length)."""
        hx, hy = self.lx / 2, self.ly / 2
        origin, yaw, length = {
            0: ((0.0, -hy), 0.0, self.lx),  # south wall, facing +y
            1: ((hx, 0.0), math.pi / 2, self.ly),  # east wall, facing -x
            2: ((0.0, hy), math.pi, self.lx),  # north wall, facing -y
            3: ((-hx, 0.0), -math.pi / 2, self.ly),  # west wall, facing +x
        }[wall]
        return np.array([origin[0], origin[1], 0.0]), rot_z(yaw), length

    def world_rect(self, origin: np.ndarray, rotation: np.ndarray, hx: float, hy: float) -> tuple:
        """World AABB (x0, x1, y0, y1) of the local rectangle [-hx, hx] x [-hy, hy]."""
        corners = np.array([[sx * hx, sy * hy, 0.0] for sx in (-1, 1) for sy in (-1, 1)]) @ rotation.T + origin
        return corners[:, 0].min(), corners[:, 0].max(), corners[:, 1].min(), corners[:, 1].max()

    def floor_free(self, rect: tuple, margin: float = 0.05) -> bool:
        x0, x1, y0, y1 = rect
        if x0 < -self.lx / 2 - 1e-6 or x1 > self.lx / 2 + 1e-6 or y0 < -self.ly / 2 - 1e-6 or y1 > self.ly / 2 + 1e-6:
            return False
        # keep the camera loop free: distance from the room centre to the rectangle
        dx = max(x0, 0.0, -x1)
        dy = max(y0, 0.0, -y1)
        if math.hypot(dx, dy) < self.p.clear_radius:
            return False
        for a0, a1, b0, b1 in self.floor_rects:
            if x0 < a1 + margin and a0 < x1 + margin and y0 < b1 + margin and b0 < y1 + margin:
                return False
        return True

    def wall_free(self, wall: int, s0: float, s1: float, z0: float, z1: float, margin: float = 0.05) -> bool:
        length = self.lx if wall in (0, 2) else self.ly
        if s0 < -length / 2 + 0.02 or s1 > length / 2 - 0.02:
            return False
        for a0, a1, b0, b1 in self.wall_rects[wall]:
            if s0 < a1 + margin and a0 < s1 + margin and z0 < b1 + margin and b0 < z1 + margin:
                return False
        return True

    def occupy_floor(self, rect: tuple, height: float) -> None:
        """Reserve the floor AABB ``rect`` and, where it touches a wall, that wall up to ``height``."""
        self.floor_rects.append(rect)
        x0, x1, y0, y1 = rect
        corners = np.array([[x0, y0, 0.0], [x0, y1, 0.0], [x1, y0, 0.0], [x1, y1, 0.0]])
        for wall in range(4):
            w_origin, w_rot, _ = self.wall_frame(wall)
            local = (corners - w_origin) @ w_rot  # x along the wall, y into the room
            if local[:, 1].min() < 0.08:
                self.wall_rects[wall].append((local[:, 0].min(), local[:, 0].max(), 0.0, height))

    # --- structure -----------------------------------------------------------------------------
    def build_structure(self) -> None:
        lx, ly, lz = self.lx, self.ly, self.lz
        th = 0.1  # wall thickness (outside the room)
        slab = (lx / 2 + th, ly / 2 + th, th / 2)
        floor = _single("floor", _box(None, (0, 0, -th / 2), slab, self.texture("floor")), 0, 0, 0)
        self.place(floor, np.zeros(3), np.eye(3), structural=True)
        ceiling = _single("ceiling", _box(None, (0, 0, lz + th / 2), slab, self.texture("ceiling")), 0, 0, 0)
        self.place(ceiling, np.zeros(3), np.eye(3), structural=True)
        wall_tex = self.texture("wall")
        accent = int(self.rng.integers(0, 4))
        for wall in range(4):
            origin, rotation, length = self.wall_frame(wall)
            tex = self.texture("wall") if wall == accent else dataclasses.replace(
                wall_tex, seed=int(self.rng.integers(0, 2**20)),
                offset=tuple(float(v) for v in self.rng.uniform(0, 10, 3)))
            # extend along the wall so that the corners are closed
            half = (length / 2 + th, th / 2, lz / 2 + th)
            spec = _single("wall", _box(None, (0, -th / 2, lz / 2), half, tex), 0, 0, 0)
            key = self.place(spec, origin, rotation, structural=True)
            self.nodes[key].name = f"wall_{'SENW'[wall]}"

    # --- furniture ---------------------------------------------------------------------------
    def spec_table(self) -> ObjectSpec:
        r = self.rng
        w, d, h = r.uniform(1.1, 1.5), r.uniform(0.7, 0.9), r.uniform(0.72, 0.76)
        top_t = 0.045
        wood = self.texture("wood")
        leg_tex = _reseed(wood, 1)
        parts = [_box("top", (0, 0, h - top_t / 2), (w / 2, d / 2, top_t / 2), wood)]
        round_legs = bool(r.integers(0, 2))
        for i, (sx, sy) in enumerate(((-1, -1), (1, -1), (1, 1), (-1, 1))):
            c = (sx * (w / 2 - 0.07), sy * (d / 2 - 0.07), (h - top_t) / 2)
            if round_legs:
                parts.append(_frustum(f"leg_{i + 1}", c, (0.028, 0.034, (h - top_t) / 2), leg_tex))
            else:
                parts.append(_box(f"leg_{i + 1}", c, (0.03, 0.03, (h - top_t) / 2), leg_tex))
        return ObjectSpec("table", "table", parts, w / 2, d / 2, h)

    def spec_chair(self, wood: Texture, fabric: Texture) -> ObjectSpec:
        seat_h, hw, hd = 0.46, 0.22, 0.22
        parts = [_box("seat", (0, 0, seat_h - 0.03), (hw, hd, 0.03), fabric)]
        for i, (sx, sy) in enumerate(((-1, -1), (1, -1), (1, 1), (-1, 1))):
            leg_h = (seat_h - 0.06) / 2
            center = (sx * (hw - 0.025), sy * (hd - 0.025), leg_h)
            parts.append(_box(f"leg_{i + 1}", center, (0.022, 0.022, leg_h), wood))
        # backrest at local -y (the chair faces +y)
        parts.append(_box("back", (0, -hd + 0.02, seat_h + 0.24), (hw, 0.02, 0.24), wood))
        return ObjectSpec("chair", "chair", parts, hw, hd, seat_h + 0.48)

    def add_table_set(self) -> bool:
        r = self.rng
        table = self.spec_table()
        wood = self.texture("wood")
        fabric = self.texture("fabric")
        for _ in range(200):
            ang = r.uniform(0, 2 * math.pi)
            dist = r.uniform(self.p.clear_radius + 0.6, max(self.lx, self.ly) / 2)
            origin = np.array([dist * math.cos(ang), dist * math.sin(ang), 0.0])
            yaw = (math.pi / 2) * int(r.integers(0, 2)) + r.uniform(-0.15, 0.15)
            rotation = rot_z(yaw)
            # chairs at both long sides, pushed 0.12 m under the table
            chairs = []
            for side in (-1, 1):
                for off in ((-0.28, 0.28) if table.half_x > 0.65 else (0.0,)):
                    cy = side * (table.half_y + 0.22 - 0.12)
                    chairs.append((np.array([off, cy, 0.0]), math.pi if side > 0 else 0.0))
            rect = self.world_rect(origin, rotation, table.half_x + 0.05, table.half_y + 0.35)
            if not self.floor_free(rect):
                continue
            group = self.new_group("table_set")
            self.occupy_floor(rect, table.height)
            self.place(table, origin, rotation, parent=group)
            for local, chair_yaw in chairs:
                if self.room_left() <= 0:
                    break
                jitter = r.uniform(-0.1, 0.1)
                self.place(self.spec_chair(wood, fabric), origin + rotation @ local,
                           rotation @ rot_z(chair_yaw + jitter), parent=group)
            self.surfaces.append(_Surface(origin + rotation @ np.array([0, 0, table.height]), rotation,
                                          table.half_x - 0.04, table.half_y - 0.04, 0.6, group))
            self.table_set = (origin, rotation, table.half_x, table.half_y, group)
            return True
        return False

    def _against_wall(self, spec: ObjectSpec, gap: float = 0.01, tries: int = 200, z_range: tuple | None = None,
                      floor: bool = True) -> tuple | None:
        """Find a wall position for ``spec`` (its local -y side touching the wall); returns (origin, rotation, wall)."""
        r = self.rng
        for _ in range(tries):
            wall = int(r.integers(0, 4))
            w_origin, w_rot, length = self.wall_frame(wall)
            if 2 * spec.half_x > length - 0.2:
                continue
            s = r.uniform(-length / 2 + spec.half_x + 0.02, length / 2 - spec.half_x - 0.02)
            z0, z1 = z_range if z_range is not None else (0.0, spec.height)
            if not self.wall_free(wall, s - spec.half_x, s + spec.half_x, z0, z1):
                continue
            origin = w_origin + w_rot @ np.array([s, spec.half_y + gap, 0.0])
            if floor:
                rect = self.world_rect(origin, w_rot, spec.half_x, spec.half_y)
                if not self.floor_free(rect):
                    continue
                self.occupy_floor(rect, spec.height)
            self.wall_rects[wall].append((s - spec.half_x, s + spec.half_x, z0, z1))
            return origin, w_rot, wall
        return None

    def add_shelf(self) -> bool:
        r = self.rng
        w, d, h = r.uniform(0.8, 1.2), r.uniform(0.32, 0.4), r.uniform(1.5, 1.9)
        t = 0.025
        wood = self.texture_of("wood", "paint")
        tex = lambda k: _reseed(wood, k)  # noqa: E731
        n_boards = int(r.integers(3, 5))
        parts = [
            _box("side_left", (-w / 2 + t / 2, 0, h / 2), (t / 2, d / 2, h / 2), tex(1)),
            _box("side_right", (w / 2 - t / 2, 0, h / 2), (t / 2, d / 2, h / 2), tex(2)),
            _box("back", (0, -d / 2 + 0.005, h / 2), (w / 2 - t, 0.005, h / 2), tex(3)),
        ]
        levels = np.linspace(0.06, h - t / 2, n_boards + 1)
        for i, zc in enumerate(levels):
            parts.append(_box(f"board_{i + 1}", (0, 0, zc), (w / 2 - t, d / 2, t / 2), tex(4 + i)))
        spec = ObjectSpec("shelf", "shelf", parts, w / 2, d / 2, h)
        placed = self._against_wall(spec)
        if placed is None:
            return False
        origin, rotation, _ = placed
        group = self.new_group("shelf_unit")
        self.place(spec, origin, rotation, parent=group)
        for i in range(n_boards):
            z_top = levels[i] + t / 2
            clearance = levels[i + 1] - t / 2 - z_top - 0.02
            self.surfaces.append(_Surface(origin + rotation @ np.array([0, 0.01, z_top]), rotation, w / 2 - t - 0.01,
                                          d / 2 - 0.03, clearance, group,
                                          kinds=("book_row", "book_row", "box_small", "vase", "ball", "plant_small")))
        return True

    def add_sofa(self) -> bool:
        r = self.rng
        w, d = r.uniform(1.6, 2.2), r.uniform(0.8, 0.9)
        fabric = self.texture("fabric")
        tex = lambda k: _reseed(fabric, k)  # noqa: E731
        arm, back_d, seat_top = 0.16, 0.2, 0.44
        parts = [
            _box("base", (0, 0.02, 0.15), (w / 2 - arm, d / 2 - 0.02, 0.15), tex(1)),
            _box("back", (0, -d / 2 + back_d / 2, 0.42), (w / 2, back_d / 2, 0.42), tex(2)),
            _box("arm_left", (-w / 2 + arm / 2, 0.0, 0.31), (arm / 2, d / 2, 0.31), tex(3)),
            _box("arm_right", (w / 2 - arm / 2, 0.0, 0.31), (arm / 2, d / 2, 0.31), tex(4)),
        ]
        n_cushions = 2 if w < 1.9 else 3
        inner = w - 2 * arm
        cw = inner / n_cushions
        cushion_tex = self.texture("fabric")
        for i in range(n_cushions):
            cx = -inner / 2 + cw * (i + 0.5)
            parts.append(_box(f"cushion_{i + 1}", (cx, back_d / 2 + 0.01, (0.3 + seat_top) / 2),
                                   (cw / 2 - 0.01, (d - back_d) / 2 - 0.01, (seat_top - 0.3) / 2),
                                   _reseed(cushion_tex, i)))
        spec = ObjectSpec("sofa", "sofa", parts, w / 2, d / 2, 0.84)
        placed = self._against_wall(spec)
        if placed is None:
            return False
        origin, rotation, _ = placed
        group = self.new_group("sofa_set")
        self.place(spec, origin, rotation, parent=group)
        # throw pillows leaning on the back
        for i in range(min(2, self.room_left())):
            side = -1 if i == 0 else 1
            part = _ellipsoid(None, (0, 0, 0.2), (0.2, 0.08, 0.2), self.texture("fabric"))
            pillow = _single("pillow", part, 0.2, 0.08, 0.4)
            local = np.array([side * (inner / 2 - 0.3), -d / 2 + back_d + 0.08, seat_top - 0.03])
            self.place(pillow, origin + rotation @ local, rotation @ rot_x(-0.25), parent=group)
        return True

    def add_tv_unit(self) -> bool:
        """A low sideboard against a wall with a television (screen + frame + stand) on it."""
        r = self.rng
        w, d, h = r.uniform(1.2, 1.8), r.uniform(0.38, 0.45), r.uniform(0.4, 0.5)
        body = self.texture_of("wood", "paint")
        doors = self.texture("paint")
        yb = -0.008  # body centre: doors stick out 16 mm at the front, the back touches the wall
        parts = [_box("body", (0, yb, h / 2), (w / 2, d / 2, h / 2), body)]
        n_doors = 2 if w < 1.5 else 3
        dw = (w - 0.06) / n_doors
        for i in range(n_doors):
            xc = -w / 2 + 0.03 + dw * (i + 0.5)
            parts.append(_box(f"door_{i + 1}", (xc, yb + d / 2 + 0.008, h / 2), (dw / 2 - 0.01, 0.008, h / 2 - 0.04),
                              _reseed(doors, i)))
        sideboard = ObjectSpec("sideboard", "sideboard", parts, w / 2, d / 2 + 0.008, h)
        tv_w = min(w - 0.2, r.uniform(0.9, 1.3))
        tv_h = tv_w * 9 / 16
        frame = self.texture("dark")
        tv_parts = [
            _box("stand", (0, 0, 0.01), (0.15, 0.1, 0.01), _reseed(frame, 1)),
            _box("neck", (0, -0.02, 0.07), (0.03, 0.02, 0.06), _reseed(frame, 2)),
            _box("frame", (0, -0.02, 0.12 + tv_h / 2), (tv_w / 2, 0.025, tv_h / 2), frame),
            _box("screen", (0, 0.008, 0.12 + tv_h / 2), (tv_w / 2 - 0.025, 0.004, tv_h / 2 - 0.025),
                 self.texture("art")),  # a picture on the screen (emits nothing: Lambertian like the rest)
        ]
        tv = ObjectSpec("tv", "tv", tv_parts, tv_w / 2, 0.1, 0.12 + tv_h)
        placed = self._against_wall(dataclasses.replace(sideboard, height=h + tv.height))
        if placed is None:
            return False
        origin, rotation, _ = placed
        group = self.new_group("tv_set")
        self.place(sideboard, origin, rotation, parent=group)
        if self.room_left() > 0:
            self.place(tv, origin + rotation @ np.array([0.0, yb - 0.05, h]), rotation, parent=group)
        rest = (w / 2 - tv_w / 2 - 0.02) / 2  # free top beside the television, each side
        for side in (-1, 1):
            if rest > 0.08:
                xc = side * (tv_w / 2 + 0.02 + rest)
                self.surfaces.append(_Surface(origin + rotation @ np.array([xc, yb, h]), rotation, rest,
                                              d / 2 - 0.03, 0.5, group))
        return True

    def add_cabinet(self) -> bool:
        r = self.rng
        w, d, h = r.uniform(0.8, 1.4), r.uniform(0.4, 0.5), r.uniform(0.7, 0.9)
        body = self.texture_of("wood", "paint")
        front_tex = self.texture("paint")
        knob = self.texture("metal")
        front = 0.055  # drawer fronts and knobs stick out this far
        yb = -front / 2  # body centre: its back touches the local -y side of the footprint
        parts = [_box("body", (0, yb, h / 2 + 0.03), (w / 2, d / 2, h / 2 - 0.03), body),
                 _box("plinth", (0, yb, 0.015), (w / 2 - 0.03, d / 2 - 0.03, 0.015), _reseed(body, 9))]
        n_drawers = int(r.integers(2, 4))
        dh = (h - 0.1) / n_drawers
        for i in range(n_drawers):
            zc = 0.06 + dh * (i + 0.5)
            parts.append(_box(f"drawer_{i + 1}", (0, yb + d / 2 + 0.01, zc), (w / 2 - 0.04, 0.01, dh / 2 - 0.015),
                                   _reseed(front_tex, i)))
            parts.append(_ellipsoid(f"knob_{i + 1}", (0, yb + d / 2 + 0.035, zc), (0.03, 0.018, 0.03), knob))
        spec = ObjectSpec("cabinet", "cabinet", parts, w / 2, d / 2 + front / 2, h)
        placed = self._against_wall(spec, z_range=(0.0, h + 0.6))  # keep the wall free above for a lamp
        if placed is None:
            return False
        origin, rotation, _ = placed
        group = self.new_group("cabinet_set")
        self.place(spec, origin, rotation, parent=group)
        surface = _Surface(origin + rotation @ np.array([0, yb, h]), rotation, w / 2 - 0.03, d / 2 - 0.03, 0.8, group)
        self.surfaces.append(surface)
        if self.room_left() > 0:
            self.place_on(surface, "table_lamp")
        return True

    def spec_floor_lamp(self) -> ObjectSpec:
        r = self.rng
        h = r.uniform(1.5, 1.75)
        metal = self.texture("metal")
        rb, rt, sh = r.uniform(0.2, 0.26), r.uniform(0.13, 0.17), r.uniform(0.14, 0.18)
        parts = [
            _frustum("base", (0, 0, 0.02), (0.17, 0.14, 0.02), metal),
            _frustum("pole", (0, 0, 0.04 + (h - 0.04) / 2), (0.022, 0.022, (h - 0.04) / 2), _reseed(metal, 1)),
            _frustum("shade", (0, 0, h + sh - 0.05), (rb, rt, sh), self.texture("shade")),
        ]
        return ObjectSpec("floor_lamp", "lamp", parts, rb, rb, h + 2 * sh)

    def spec_plant(self, scale: float = 1.0) -> ObjectSpec:
        r = self.rng
        ph = r.uniform(0.25, 0.35) * scale
        rb, rt = r.uniform(0.1, 0.13) * scale, r.uniform(0.14, 0.18) * scale
        fr = r.uniform(0.22, 0.3) * scale
        fz = r.uniform(1.1, 1.6) * fr
        parts = [
            _frustum("pot", (0, 0, ph / 2), (rb, rt, ph / 2), self.texture("ceramic")),
            _ellipsoid("foliage", (0, 0, ph + fz * 0.85), (fr, fr * r.uniform(0.8, 1.0), fz), self.texture("plant")),
        ]
        return ObjectSpec("plant", "plant", parts, max(fr, rt), max(fr, rt), ph + fz * 1.85)

    def add_free_standing(self, spec: ObjectSpec, parent: int | None = None) -> tuple | None:
        """Place ``spec`` on the floor near a wall with a random yaw; returns (origin, rotation) or None."""
        r = self.rng
        ext = spec.yaw_radius()
        for _ in range(200):
            rotation = rot_z(r.uniform(0, 2 * math.pi))
            w_origin, w_rot, length = self.wall_frame(int(r.integers(0, 4)))
            if length < 2 * ext + 0.1:
                continue
            s = r.uniform(-length / 2 + ext + 0.02, length / 2 - ext - 0.02)
            origin = w_origin + w_rot @ np.array([s, ext + r.uniform(0.02, 0.3), 0.0])
            rect = (origin[0] - ext, origin[0] + ext, origin[1] - ext, origin[1] + ext)
            if not self.floor_free(rect):
                continue
            self.occupy_floor(rect, spec.height)
            self.place(spec, origin, rotation, parent=parent)
            return origin, rotation
        return None

    def add_side_table(self) -> bool:
        r = self.rng
        rad, h = r.uniform(0.25, 0.32), r.uniform(0.5, 0.6)
        wood = self.texture("wood")
        parts = [
            _frustum("top", (0, 0, h - 0.015), (rad, rad, 0.015), wood),
            _frustum("stem", (0, 0, h / 2), (0.035, 0.035, h / 2 - 0.03), _reseed(wood, 1)),
            _frustum("foot", (0, 0, 0.02), (0.2, 0.16, 0.02), _reseed(wood, 2)),
        ]
        group = self.new_group("side_table_set")
        placed = self.add_free_standing(ObjectSpec("side_table", "side_table", parts, rad, rad, h), parent=group)
        if placed is None:
            return False
        origin, rotation = placed
        self.surfaces.append(_Surface(origin + np.array([0.0, 0.0, h]), rotation, rad * 0.6, rad * 0.6, 0.6, group))
        return True

    def add_door(self) -> bool:
        r = self.rng
        w, h = r.uniform(0.82, 0.95), r.uniform(2.0, 2.1)
        tex = self.texture("paint")
        parts = [
            _box("panel", (0, 0.02, h / 2), (w / 2, 0.02, h / 2), tex),
            _box("frame", (0, 0.015, h / 2 + 0.02), (w / 2 + 0.06, 0.015, h / 2 + 0.02), self.texture("paint")),
            _ellipsoid("handle", (w / 2 - 0.1, 0.065, 1.0), (0.05, 0.025, 0.025), self.texture("metal")),
        ]
        spec = ObjectSpec("door", "door", parts, w / 2 + 0.06, 0.03, h + 0.04)
        # the door needs free floor in front of it
        for _ in range(100):
            placed = self._against_wall(spec, gap=-spec.half_y, tries=1, floor=False)
            if placed is None:
                continue
            origin, rotation, wall = placed
            rect = self.world_rect(origin + rotation @ np.array([0, 0.45, 0]), rotation, w / 2, 0.45)
            if not self.floor_free(rect, margin=0.0):
                self.wall_rects[wall].pop()
                continue
            self.occupy_floor(rect, 0.0)
            self.place(spec, origin, rotation)
            return True
        return False

    def add_wall_item(self, kind: str) -> bool:
        r = self.rng
        if kind == "window":
            w, h, z0 = r.uniform(1.0, 1.4), r.uniform(1.0, 1.3), r.uniform(0.85, 1.0)
            frame_tex = self.texture("paint")
            parts = [_box("frame", (0, 0.02, h / 2), (w / 2, 0.02, h / 2), frame_tex)]
            pane_w = (w - 0.15) / 2
            for i, sx in enumerate((-1, 1)):
                parts.append(_box(f"pane_{i + 1}", (sx * (pane_w / 2 + 0.025), 0.045, h / 2),
                                  (pane_w / 2, 0.005, h / 2 - 0.05), self.texture("sky")))
            parts.append(_box("sill", (0, 0.08, -0.02), (w / 2 + 0.05, 0.08, 0.02), _reseed(frame_tex, 5)))
            spec = ObjectSpec("window", "window", parts, w / 2 + 0.05, 0.07, h)
        elif kind == "painting":
            w, h = r.uniform(0.5, 1.0), r.uniform(0.4, 0.8)
            z0 = r.uniform(1.25, 1.55) - h / 2
            parts = [
                _box("frame", (0, 0.02, h / 2), (w / 2, 0.02, h / 2), self.texture_of("wood", "dark")),
                _box("canvas", (0, 0.042, h / 2), (w / 2 - 0.05, 0.005, h / 2 - 0.05), self.texture("art")),
            ]
            spec = ObjectSpec("painting", "painting", parts, w / 2, 0.03, h)
        elif kind == "clock":
            rad = r.uniform(0.14, 0.2)
            z0 = r.uniform(1.6, 1.9)
            parts = [
                _frustum("body", (0, 0.025, rad), (rad, rad * 0.95, 0.025), self.texture("ceramic"),
                         rotation=rot_x(-math.pi / 2)),  # axis out of the wall
                _box("hand", (0, 0.052, rad + rad * 0.35), (0.01, 0.005, rad * 0.35), self.texture("dark")),
            ]
            spec = ObjectSpec("clock", "clock", parts, rad, 0.03, 2 * rad)
        else:
            raise ValueError(kind)
        for _ in range(100):
            placed = self._against_wall(spec, gap=-spec.half_y, tries=1, z_range=(z0, z0 + spec.height), floor=False)
            if placed is None:
                continue
            origin, rotation, wall = placed
            self.place(spec, origin + np.array([0, 0, z0]), rotation)
            return True
        return False

    def add_rug(self) -> bool:
        """A rug under the dining set (chairs and table legs stand on it), or on free floor."""
        r = self.rng
        if self.table_set is not None:
            origin, rotation, hx, hy, group = self.table_set
            for _ in range(20):
                w, d = hx + r.uniform(0.4, 0.7), hy + r.uniform(0.5, 0.8)
                x0, x1, y0, y1 = self.world_rect(origin, rotation, w, d)
                if x0 > -self.lx / 2 and x1 < self.lx / 2 and y0 > -self.ly / 2 and y1 < self.ly / 2:
                    spec = _single("rug", _box(None, (0, 0, 0.006), (w, d, 0.006), self.texture("rug")), w, d, 0.012)
                    self.place(spec, origin, rotation, parent=group)
                    return True
        for _ in range(100):
            w, d = r.uniform(0.7, 1.1), r.uniform(0.5, 0.8)
            rotation = rot_z((math.pi / 2) * int(r.integers(0, 2)))
            w_origin, w_rot, length = self.wall_frame(int(r.integers(0, 4)))
            s = r.uniform(-length / 2 + w + 0.05, length / 2 - w - 0.05)
            origin = w_origin + w_rot @ np.array([s, d + r.uniform(0.1, 0.5), 0.0])
            rect = self.world_rect(origin, rotation, w, d)
            if self.floor_free(rect):
                self.occupy_floor(rect, 0.0)
                spec = _single("rug", _box(None, (0, 0, 0.006), (w, d, 0.006), self.texture("rug")), w, d, 0.012)
                self.place(spec, origin, rotation)
                return True
        return False

    def add_floor_item(self) -> bool:
        r = self.rng
        kind = str(r.choice(["ball", "basket", "basket", "ottoman", "plant", "plant"]))
        if kind == "ball":
            rad = r.uniform(0.1, 0.16)
            part = _ellipsoid(None, (0, 0, rad), (rad, rad, rad), self.texture_of("ceramic", "fabric"))
            spec = _single("ball", part, rad, rad, 2 * rad)
        elif kind == "basket":
            hx, hy, hz = r.uniform(0.18, 0.28), r.uniform(0.15, 0.22), r.uniform(0.12, 0.2)
            part = _box(None, (0, 0, hz), (hx, hy, hz), self.texture_of("wood", "fabric"))
            spec = _single("basket", part, hx, hy, 2 * hz)
        elif kind == "ottoman":
            rad, hz = r.uniform(0.22, 0.3), r.uniform(0.18, 0.22)
            part = _frustum(None, (0, 0, hz), (rad, rad, hz), self.texture("fabric"))
            spec = _single("ottoman", part, rad, rad, 2 * hz)
        else:
            spec = self.spec_plant(scale=1.0)
        return self.add_free_standing(spec) is not None

    # --- small items ---------------------------------------------------------------------------
    def spec_item(self, kind: str, clearance: float) -> ObjectSpec | None:
        """A small item standing on a support (local origin at its bottom centre); None if it cannot fit."""
        r = self.rng
        if kind == "mug":
            rad, h = r.uniform(0.04, 0.05), r.uniform(0.09, 0.11)
            parts = [_frustum(None, (0, 0, h / 2), (rad * 0.9, rad, h / 2), self.texture("ceramic"))]
            spec = ObjectSpec("mug", "mug", parts, rad, rad, h)
        elif kind == "vase":
            rb, rt, h = r.uniform(0.05, 0.08), r.uniform(0.03, 0.06), r.uniform(0.18, 0.32)
            parts = [_frustum("body", (0, 0, h / 2), (rb, rt, h / 2), self.texture("ceramic"))]
            if r.uniform() < 0.6:
                fr = r.uniform(0.08, 0.12)
                parts.append(_ellipsoid("flowers", (0, 0, h + fr * 0.8), (fr, fr, fr), self.texture_of("plant", "art")))
                h = h + fr * 1.8
            else:
                parts[0].name = None
            ext = max(rb, 0.1) if len(parts) > 1 else rb
            spec = ObjectSpec("vase", "vase", parts, ext, ext, h)
        elif kind == "bowl":
            rad = r.uniform(0.1, 0.14)
            parts = [_ellipsoid(None, (0, 0, 0.05), (rad, rad, 0.05), self.texture("ceramic"))]
            spec = ObjectSpec("bowl", "bowl", parts, rad, rad, 0.1)
        elif kind == "fruit_bowl":
            rad = r.uniform(0.13, 0.16)
            parts = [_frustum("bowl", (0, 0, 0.035), (rad * 0.6, rad, 0.035), self.texture("ceramic"))]
            for i in range(3):
                ang = 2 * math.pi * i / 3 + r.uniform(-0.3, 0.3)
                fr = r.uniform(0.035, 0.045)
                center = (0.45 * rad * math.cos(ang), 0.45 * rad * math.sin(ang), 0.07 + fr * 0.6)
                parts.append(_ellipsoid(f"fruit_{i + 1}", center, (fr, fr, fr), self.texture("ceramic")))
            spec = ObjectSpec("fruit_bowl", "fruit_bowl", parts, rad, rad, 0.16)
        elif kind == "book_pile":
            parts = []
            z = 0.0
            for i in range(int(r.integers(2, 4))):
                bx, by, bz = r.uniform(0.09, 0.12), r.uniform(0.13, 0.16), r.uniform(0.012, 0.025)
                center = (r.uniform(-0.01, 0.01), r.uniform(-0.01, 0.01), z + bz)
                parts.append(_box(f"book_{i + 1}", center, (bx, by, bz), self.texture("paper"),
                                       rotation=rot_z(r.uniform(-0.2, 0.2))))
                z += 2 * bz
            spec = ObjectSpec("book_pile", "books", parts, 0.17, 0.2, z)
        elif kind == "book_row":
            parts = []
            x = 0.0
            n = int(r.integers(4, 9))
            max_h = 0.0
            for i in range(n):
                bw, bd, bh = r.uniform(0.012, 0.025), r.uniform(0.08, 0.12), r.uniform(0.09, 0.14)
                bh = min(bh, (clearance - 0.01) / 2)
                if bh < 0.06:
                    return None
                parts.append(_box(f"book_{i + 1}", (x + bw, 0, bh), (bw, bd, bh), self.texture("paper")))
                x += 2 * bw + 0.002
                max_h = max(max_h, 2 * bh)
            for part in parts:
                part.center = (part.center[0] - x / 2, 0, part.center[2])
            spec = ObjectSpec("book_row", "books", parts, x / 2, 0.12, max_h)
            spec.aligned = True
        elif kind == "bottle":
            rad, h = r.uniform(0.03, 0.045), r.uniform(0.18, 0.26)
            glass = self.texture("ceramic")
            parts = [_frustum("body", (0, 0, h * 0.35), (rad, rad, h * 0.35), glass),
                     _frustum("neck", (0, 0, h * 0.7 + h * 0.15), (rad, rad * 0.35, h * 0.15), _reseed(glass, 1))]
            spec = ObjectSpec("bottle", "bottle", parts, rad, rad, h)
        elif kind == "ball":
            rad = r.uniform(0.05, 0.09)
            part = _ellipsoid(None, (0, 0, rad), (rad, rad, rad), self.texture("ceramic"))
            spec = _single("ball", part, rad, rad, 2 * rad)
        elif kind == "box_small":
            hx, hy, hz = r.uniform(0.06, 0.12), r.uniform(0.05, 0.1), r.uniform(0.04, 0.09)
            part = _box(None, (0, 0, hz), (hx, hy, hz), self.texture_of("paper", "wood", "fabric"))
            spec = _single("box", part, hx, hy, 2 * hz)
        elif kind == "plant_small":
            spec = self.spec_plant(scale=0.45)
        elif kind == "table_lamp":
            rb = r.uniform(0.07, 0.09)
            stem_h = r.uniform(0.22, 0.3)
            shade_b, shade_t, shade_h = r.uniform(0.13, 0.17), r.uniform(0.08, 0.11), r.uniform(0.09, 0.12)
            metal = self.texture("metal")
            parts = [
                _frustum("base", (0, 0, 0.02), (rb, rb * 0.8, 0.02), metal),
                _frustum("stem", (0, 0, 0.04 + stem_h / 2), (0.015, 0.015, stem_h / 2), _reseed(metal, 1)),
                _frustum("shade", (0, 0, 0.04 + stem_h + shade_h - 0.03), (shade_b, shade_t, shade_h),
                         self.texture("shade")),
            ]
            spec = ObjectSpec("table_lamp", "lamp", parts, shade_b, shade_b, 0.04 + stem_h + 2 * shade_h - 0.03)
        else:
            raise ValueError(kind)
        if spec.height > clearance:
            return None
        return spec

    def place_on(self, surface: _Surface, kind: str) -> bool:
        r = self.rng
        spec = self.spec_item(kind, surface.clearance)
        if spec is None or spec.half_x > surface.half_x or spec.half_y > surface.half_y:
            return False
        no_yaw = spec.aligned
        for _ in range(30):
            yaw = 0.0 if no_yaw else r.uniform(0, 2 * math.pi)
            ext_x = spec.half_x if no_yaw else spec.yaw_radius()
            ext_y = spec.half_y if no_yaw else spec.yaw_radius()
            if ext_x > surface.half_x or ext_y > surface.half_y:
                return False
            x = r.uniform(-surface.half_x + ext_x, surface.half_x - ext_x)
            y = r.uniform(-surface.half_y + ext_y, surface.half_y - ext_y)
            rect = (x - ext_x, x + ext_x, y - ext_y, y + ext_y)
            gap = 0.02
            if any(rect[0] < b[1] + gap and b[0] < rect[1] + gap and rect[2] < b[3] + gap and b[2] < rect[3] + gap
                   for b in surface.occupied):
                continue
            surface.occupied.append(rect)
            origin = surface.origin + surface.rotation @ np.array([x, y, 0.0])
            self.place(spec, origin, surface.rotation @ rot_z(yaw), parent=surface.parent)
            return True
        return False

    # --- lights --------------------------------------------------------------------------------
    def lights(self) -> tuple[np.ndarray, np.ndarray]:
        r = self.rng
        lights = []
        for sx in (-1, 1):
            lights.append((sx * self.lx * r.uniform(0.15, 0.3), r.uniform(-0.2, 0.2) * self.ly, self.lz - 0.3))
        return np.array(lights), np.full(len(lights), self.p.light_power)


def build_room(params: SyntheticParams) -> RoomLayout:
    """Furnish a room from ``params.seed``: structure, furniture against walls, a table set, items."""
    rng = np.random.default_rng(params.seed)
    b = _RoomBuilder(params, rng)
    b.build_structure()
    furniture = ["table_set", "shelf", "sofa", "cabinet", "floor_lamp", "plant", "door", "window", "painting",
                 "painting", "side_table", "clock", "rug", "tv_unit"]
    # each left out with probability 1/4 so that rooms differ in inventory, not only in layout
    optional = ("floor_lamp", "plant", "painting", "side_table", "clock", "tv_unit")
    furniture = [k for k in furniture if k not in optional or rng.uniform() >= 0.25]
    order = [furniture[i] for i in rng.permutation(len(furniture))]
    # the big pieces first so that they find wall space
    priority = {"door": 0, "shelf": 1, "sofa": 1, "cabinet": 1, "table_set": 1, "tv_unit": 1, "window": 2,
                "rug": 4}
    order.sort(key=lambda k: priority.get(k, 3))
    for kind in order:
        if b.room_left() <= 0:
            break
        if kind == "table_set":
            ok = b.add_table_set()
        elif kind == "shelf":
            ok = b.add_shelf()
        elif kind == "sofa":
            ok = b.add_sofa()
        elif kind == "cabinet":
            ok = b.add_cabinet()
        elif kind == "tv_unit":
            ok = b.add_tv_unit()
        elif kind == "floor_lamp":
            ok = b.add_free_standing(b.spec_floor_lamp()) is not None
        elif kind == "plant":
            ok = b.add_free_standing(b.spec_plant()) is not None
        elif kind == "side_table":
            ok = b.add_side_table()
        elif kind == "door":
            ok = b.add_door()
        elif kind == "rug":
            ok = b.add_rug()
        else:
            ok = b.add_wall_item(kind)
        log.debug("furniture %s placed: %s", kind, ok)
    # small items: one per support first, then random supports and the floor
    for surface in b.surfaces:
        for _ in range(10):
            if b.room_left() <= 0 or b.place_on(surface, str(rng.choice(surface.kinds))):
                break
    attempts = 0
    while b.room_left() > 0 and attempts < 400:
        attempts += 1
        if b.surfaces and rng.uniform() < 0.85:
            surface = b.surfaces[int(rng.integers(0, len(b.surfaces)))]
            b.place_on(surface, str(rng.choice(surface.kinds)))
        else:
            b.add_floor_item()
    if b.room_left() > 0:
        raise ConfigError(
            f"synthetic params: could only place {b.num_objects} of num_objects = {params.num_objects} objects "
            f"in the {b.lx:.1f} x {b.ly:.1f} m room of seed {params.seed}; lower num_objects or enlarge the room."
        )
    # drop groups that ended up with fewer than two members
    members: dict[int, int] = {}
    for n in b.nodes:
        if n.parent is not None:
            members[n.parent] = members.get(n.parent, 0) + 1
    for n in b.nodes:
        if n.parent is not None and b.nodes[n.parent].level == "group" and members[n.parent] < 2:
            n.parent = None
    nodes = [n for n in b.nodes if n.level != "group" or members.get(n.key, 0) >= 2]
    # ids: structure first, then in creation order
    key_to_id = {n.key: i + 1 for i, n in enumerate(nodes)}
    lights, power = b.lights()
    return RoomLayout(size=(b.lx, b.ly, b.lz), primitives=b.primitives, nodes=nodes, lights=lights, light_power=power,
                      key_to_id=key_to_id)


# ----------------------------------------------------------------------------------------------
# Cameras
# ----------------------------------------------------------------------------------------------


def look_rotation(yaw: float, pitch: float) -> np.ndarray:
    """[3, 3] world-to-camera rotation (OpenCV axes) of a camera looking along ``yaw`` (radians from +x,
    counter-clockwise) with ``pitch`` (radians, positive looks up) in the z-up world."""
    forward = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), math.sin(pitch)])
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return np.stack([right, down, forward])


def intrinsics(params: SyntheticParams) -> np.ndarray:
    """[3, 3] pinhole K with the horizontal field of view ``fov_x_deg`` and square pixels."""
    f = params.width / 2 / math.tan(math.radians(params.fov_x_deg) / 2)
    return np.array([[f, 0.0, params.width / 2], [0.0, f, params.height / 2], [0.0, 0.0, 1.0]])


def camera_trajectory(params: SyntheticParams) -> list[Camera]:
    """A closed loop of ``num_views`` cameras around the room centre, looking outwards.

    Radius, height, pitch and yaw oscillate smoothly (phases from the seed); view i is a test view
    when ``i % test_every == test_every // 2``.
    """
    rng = np.random.default_rng([params.seed, 1])
    phase = rng.uniform(0, 2 * math.pi, 5)
    K = intrinsics(params)
    cameras = []
    for i in range(params.num_views):
        theta = phase[0] + 2 * math.pi * i / params.num_views
        radius = params.camera_radius * (1.0 + 0.25 * math.sin(2 * theta + phase[1]))
        height = params.camera_height + params.camera_height_amplitude * math.sin(3 * theta + phase[2])
        yaw = theta + math.radians(params.camera_yaw_amplitude_deg) * math.sin(2 * theta + phase[3])
        pitch_deg = params.camera_pitch_deg + params.camera_pitch_amplitude_deg * math.sin(3 * theta + phase[4])
        pitch = math.radians(pitch_deg)
        position = np.array([radius * math.cos(theta), radius * math.sin(theta), height])
        rotation = look_rotation(yaw, pitch)
        w2c = np.eye(4)
        w2c[:3, :3] = rotation
        w2c[:3, 3] = -rotation @ position
        split = "test" if i % params.test_every == params.test_every // 2 else "train"
        cameras.append(Camera(name=f"view_{i:03d}", split=split, width=params.width, height=params.height, K=K,
                              world_to_camera=w2c))
    return cameras


# ----------------------------------------------------------------------------------------------
# Scene generation
# ----------------------------------------------------------------------------------------------


def _object_table(layout: RoomLayout, max_pixels: dict[int, int], min_visible_pixels: int) -> ObjectTable:
    """The hierarchy with ``evaluated`` = non-structural objects seen by >= min_visible_pixels in some view.

    ``max_pixels`` maps an object-level id to its largest per-view pixel count (parts summed).
    """
    objects = []
    for node in layout.nodes:
        oid = layout.key_to_id[node.key]
        evaluated = (
            node.level == "object"
            and node.category not in STRUCTURE_CATEGORIES
            and max_pixels.get(oid, 0) >= min_visible_pixels
        )
        parent = layout.key_to_id[node.parent] if node.parent is not None else None
        objects.append(SceneObject(id=oid, name=node.name, level=node.level, parent=parent, category=node.category,
                                   evaluated=bool(evaluated)))
    return ObjectTable(objects)


def generate_scene(out_dir: Path, params: SyntheticParams) -> None:
    """Build the room of ``params`` and write the canonical scene into ``out_dir`` (an empty folder)."""
    out_dir = Path(out_dir)
    layout = build_room(params)
    cameras = camera_trajectory(params)
    packed = layout.packed()
    table = _object_table(layout, {}, 0)
    object_lookup = table.lookup("object")
    log.info("synthetic room seed %d: %.1f x %.1f x %.1f m, %d primitives, %d views of %dx%d",
             params.seed, *layout.size, len(layout.primitives), len(cameras), params.width, params.height)
    max_pixels: dict[int, int] = {}
    views_seen: dict[int, int] = {}
    for cam in tqdm(cameras, desc=f"synthetic room {params.seed}", unit="view", leave=False):
        rgb, prim, depth = render_view(packed, cam, params.supersample, params.ambient, params.shadows)
        if (prim < 0).any():
            raise Trace3DError(f"{out_dir}: view {cam.name} sees outside the room; the camera path leaves the room.")
        leaf = packed.leaf_ids[prim]
        write_frame(out_dir, cam.name, to_uint8(rgb), leaf.astype(np.uint16), depth)
        ids, counts = np.unique(object_lookup[leaf], return_counts=True)
        for oid, count in zip(ids.tolist(), counts.tolist()):
            max_pixels[oid] = max(max_pixels.get(oid, 0), count)
            views_seen[oid] = views_seen.get(oid, 0) + 1
    table = _object_table(layout, max_pixels, params.min_visible_pixels)
    write_cameras(out_dir, cameras)
    write_json(out_dir / "objects.json", table.to_json())
    categories: dict[str, int] = {}
    for o in table:
        if o.level == "object":
            categories[o.category] = categories.get(o.category, 0) + 1
    meta = {
        "source": "synthetic",
        "params": to_dict(params),
        "room": {
            "size_m": [round(v, 4) for v in layout.size],
            "num_objects": sum(1 for o in table if o.level == "object" and o.category not in STRUCTURE_CATEGORIES),
            "num_evaluated": len(table.evaluated_ids()),
            "num_parts": sum(1 for o in table if o.level == "part"),
            "num_groups": sum(1 for o in table if o.level == "group"),
            "num_primitives": len(layout.primitives),
            "objects_per_category": dict(sorted(categories.items())),
            "lights": [[round(float(v), 4) for v in light] for light in layout.lights],
        },
        "views": {"train": sum(c.split == "train" for c in cameras), "test": sum(c.split == "test" for c in cameras)},
        "object_max_visible_pixels": {str(k): v for k, v in sorted(max_pixels.items())},
        "object_views_visible": {str(k): v for k, v in sorted(views_seen.items())},
    }
    write_json(out_dir / "meta.json", meta)


def run_bench(quick: bool = False) -> dict:
    """Time generating the default room (``quick``: 8 views) including PNG writing.

    Returns views, resolution, compile_s (first-call numba compile / cache load), total_s and
    ms_per_view (wall clock: rendering + writing, after compilation), cpu_s (process CPU time),
    numba_threads and the 1-minute load average (the machine may be shared).
    """
    params = SyntheticParams(num_views=8) if quick else SyntheticParams()
    start = time.perf_counter()
    tiny = dataclasses.replace(SyntheticParams(), width=16, height=12)
    render_view(build_room(tiny).packed(), camera_trajectory(tiny)[0], 1)
    compile_s = time.perf_counter() - start
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        cpu_start = time.process_time()
        generate_scene(Path(tmp) / "scene", params)
        total = time.perf_counter() - start
        cpu = time.process_time() - cpu_start
    return {
        "views": params.num_views,
        "resolution": [params.width, params.height],
        "supersample": params.supersample,
        "compile_s": round(compile_s, 3),
        "total_s": round(total, 3),
        "ms_per_view": round(1000 * total / params.num_views, 2),
        "cpu_s": round(cpu, 3),  # all threads of this process; on a busy machine total_s >> cpu_s / cores
        "numba_threads": int(numba.get_num_threads()),
        "load_average_1min": round(os.getloadavg()[0], 2),
    }
