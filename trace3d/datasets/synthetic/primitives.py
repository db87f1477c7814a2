"""Primitives and their solid textures, and the packing of a room into the flat arrays the ray caster reads."""

from __future__ import annotations

import dataclasses
import math

import numpy as np


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
        """The geometry arguments of the kernels' ``cast_ray``: shapes, centers, rotations, sizes, radii, clusters."""
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
