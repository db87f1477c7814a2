"""Procedural indoor rooms, rendered exactly by ray casting: the default synthetic benchmark.

A room is a closed box (floor, ceiling, four walls) furnished with objects built from three kinds of
primitives (boxes, ellipsoids/spheres, capped frustums/cylinders): a table set (table = top + legs,
chairs = seat + back + legs, items on the table, a rug under it), a shelf holding rows of books and
other items, a sofa with pillows, a cabinet with a table lamp, a sideboard with a television, a floor
lamp, plants, a door, a window, paintings, a clock, balls, baskets... placed so that they touch and
occlude each other (items stand on tables and shelves, furniture stands against the walls).  Some
pieces are optional, so rooms differ in inventory as well as in layout.  Every primitive carries a
procedural *solid* texture evaluated in its own local (object-space) coordinates, so a surface point
has the same colour from every view; shading is Lambertian under fixed point lights with hard
shadows and a hemispherical ambient term: nothing depends on the viewing direction, so a diffuse
Gaussian model can fit the images exactly.

Cameras follow a 360-degree loop around the room centre (kept free of furniture), looking outwards
with smooth height, pitch and yaw variation, like the Replica captures; every ``test_every``-th view
is held out for testing.

Outputs (see :mod:`trace3d.scene`): ``images/`` (RGB, ``supersample``^2 rays per pixel),
``instances/`` (leaf ids of the pixel-centre ray), ``depth/`` (camera z of the pixel-centre ray),
``cameras.json``, ``objects.json`` (part -> object -> group hierarchy, ``evaluated`` = non-structural
objects with at least ``min_visible_pixels`` pixels in some view), ``meta.json``.

The modules, in the order a room is made:

    params.py             SyntheticParams, params_from
    primitives.py         primitives, solid textures, the packed arrays the ray caster reads
    layout.py             object specs, hierarchy nodes, supports, RoomLayout
    furniture.py          RoomBuilder: the furniture and item catalogue and its placement rules
    room.py               build_room: furnish one room from its seed
    cameras.py            the camera loop
    raycast.py            the numba ray caster (cast_ray, render_view)
    raycast_reference.py  its slow, independently written numpy twin (render_view_reference)
    writer.py             generate_scene: render every view and write the canonical scene

Everything is deterministic from ``seed``.  Its benchmark, ``trace3d bench synthetic``, is
:mod:`trace3d.bench.synthetic`.
"""

from .cameras import camera_trajectory, intrinsics, look_rotation
from .layout import RoomLayout
from .params import SyntheticParams, params_from
from .primitives import (SHAPE_BOX, SHAPE_ELLIPSOID, SHAPE_FRUSTUM, SHAPE_NAMES, STRUCTURE_CATEGORIES, PackedScene,
                         Primitive, Texture, bounding_radius, pack_scene)
from .raycast import render_view
from .raycast_reference import render_view_reference
from .room import build_room
from .writer import generate_scene, to_uint8

__all__ = [
    "PackedScene", "Primitive", "RoomLayout", "SHAPE_BOX", "SHAPE_ELLIPSOID", "SHAPE_FRUSTUM", "SHAPE_NAMES",
    "STRUCTURE_CATEGORIES", "SyntheticParams", "Texture", "bounding_radius", "build_room", "camera_trajectory",
    "generate_scene", "intrinsics", "look_rotation", "pack_scene", "params_from", "render_view",
    "render_view_reference", "to_uint8",
]
