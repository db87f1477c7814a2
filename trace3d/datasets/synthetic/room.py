"""Furnishing one room from its seed: :func:`build_room`."""

from __future__ import annotations

import logging

import numpy as np

from ...errors import ConfigError
from .furniture import RoomBuilder
from .layout import RoomLayout
from .params import SyntheticParams

log = logging.getLogger(__name__)


def build_room(params: SyntheticParams) -> RoomLayout:
    """Furnish a room from ``params.seed``: structure, furniture against walls, a table set, items."""
    rng = np.random.default_rng(params.seed)
    b = RoomBuilder(params, rng)
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
