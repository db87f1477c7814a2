"""The vocabulary of a furnished room: object specs made of local parts, the hierarchy nodes, supports
and the resulting :class:`RoomLayout`."""

from __future__ import annotations

import colorsys
import dataclasses
import math

import numpy as np

from .primitives import PackedScene, Primitive, SHAPE_BOX, SHAPE_ELLIPSOID, SHAPE_FRUSTUM, Texture, pack_scene


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


def box_part(name, center, half, texture, rotation=None) -> LocalPart:
    """A box part: ``half`` = half extents."""
    return LocalPart(name, SHAPE_BOX, center, half, texture, rotation)


def ellipsoid_part(name, center, axes, texture, rotation=None) -> LocalPart:
    """An ellipsoid part: ``axes`` = semi-axes."""
    return LocalPart(name, SHAPE_ELLIPSOID, center, axes, texture, rotation)


def frustum_part(name, center, size, texture, rotation=None) -> LocalPart:
    """A capped frustum around the local z axis: ``size`` = (bottom radius, top radius, half height)."""
    return LocalPart(name, SHAPE_FRUSTUM, center, size, texture, rotation)


def single_part_object(category: str, part: LocalPart, half_x: float, half_y: float, height: float) -> "ObjectSpec":
    """An object made of one primitive (its leaf id is the object id)."""
    return ObjectSpec(category, category, [part], half_x, half_y, height)


def reseeded(texture: Texture, k: int) -> Texture:
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
class Node:
    key: int
    name: str
    level: str
    category: str
    parent: int | None


@dataclasses.dataclass
class Surface:
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
    nodes: list[Node]
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


def hsv_rgb(h: float, s: float, v: float) -> tuple[float, float, float]:
    return tuple(float(c) for c in colorsys.hsv_to_rgb(h % 1.0, min(max(s, 0.0), 1.0), min(max(v, 0.0), 1.0)))
