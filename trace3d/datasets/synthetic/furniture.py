"""The furniture catalogue: :class:`RoomBuilder` builds each kind of furniture and item from primitives and
places it against walls, on the floor or on supports.  It is one class of ~760 lines because every
piece shares the builder's state (free wall and floor space, supports, the room's palette)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .layout import (Node, ObjectSpec, Surface, box_part, ellipsoid_part, frustum_part, hsv_rgb, reseeded, rot_x, rot_z,
                     single_part_object)
from .params import SyntheticParams
from .primitives import PAT_CHECKER, PAT_NOISE, PAT_PLANKS, PAT_RINGS, PAT_STRIPES, PAT_TILES, Primitive, Texture


class RoomBuilder:
    """Places furniture and items in a room; all randomness comes from ``rng``."""

    def __init__(self, params: SyntheticParams, rng: np.random.Generator):
        self.p = params
        self.rng = rng
        self.lx = float(rng.uniform(*params.room_width_range))
        self.ly = float(rng.uniform(*params.room_depth_range))
        self.lz = float(rng.uniform(*params.room_height_range))
        self.nodes: list[Node] = []
        self.primitives: list[Primitive] = []
        self.floor_rects: list[tuple[float, float, float, float]] = []
        self.wall_rects: dict[int, list[tuple[float, float, float, float]]] = {w: [] for w in range(4)}
        self.surfaces: list[Surface] = []
        self.counter: dict[str, int] = {}
        self.num_objects = 0
        self.palette_hue = float(rng.uniform(0, 1))  # room colour theme
        self.table_set: tuple | None = None  # (origin, rotation, half_x, half_y, group) of the dining set

    # --- hierarchy ---------------------------------------------------------------------------
    def _new_node(self, name: str, level: str, category: str, parent: int | None) -> int:
        key = len(self.nodes)
        self.nodes.append(Node(key, name, level, category, parent))
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
            c0 = hsv_rgb(h, r.uniform(0.08, 0.3), r.uniform(0.72, 0.88))
            c1 = hsv_rgb(h + r.uniform(-0.1, 0.1), r.uniform(0.15, 0.45), r.uniform(0.45, 0.65))
            low, high = {PAT_STRIPES: (0.12, 0.22), PAT_NOISE: (0.25, 0.4), PAT_TILES: (0.35, 0.6)}[pattern]
            scale = r.uniform(low, high)
            axis = 0 if pattern == PAT_STRIPES else 1
            return Texture(pattern, c0, c1, scale * ts, 0.8 * tc, 0.25, 0.3 * ts, axis, seed, offset)
        if kind == "floor":
            pattern = int(r.choice([PAT_PLANKS, PAT_TILES, PAT_CHECKER]))
            if pattern == PAT_PLANKS:
                h = r.uniform(0.05, 0.1)
                c0 = hsv_rgb(h, r.uniform(0.4, 0.6), r.uniform(0.55, 0.75))
                c1 = hsv_rgb(h, r.uniform(0.5, 0.7), r.uniform(0.25, 0.4))
                return Texture(pattern, c0, c1, r.uniform(0.14, 0.2) * ts, tc, 0.2, 0.2 * ts, 0, seed, offset)
            c0 = hsv_rgb(r.uniform(0, 1), r.uniform(0.05, 0.25), r.uniform(0.65, 0.85))
            c1 = hsv_rgb(r.uniform(0, 1), r.uniform(0.1, 0.4), r.uniform(0.25, 0.45))
            scale = r.uniform(0.35, 0.5) if pattern == PAT_TILES else r.uniform(0.3, 0.45)
            return Texture(pattern, c0, c1, scale * ts, 0.9 * tc, 0.3, 0.12 * ts, 2, seed, offset)
        if kind == "ceiling":
            c0 = hsv_rgb(hue, 0.05, 0.9)
            c1 = hsv_rgb(hue, 0.1, 0.7)
            return Texture(PAT_NOISE, c0, c1, 0.4 * ts, 0.6 * tc, 0.15, 0.25 * ts, 0, seed, offset)
        if kind == "wood":
            pattern = int(r.choice([PAT_PLANKS, PAT_RINGS, PAT_STRIPES]))
            h = r.uniform(0.04, 0.11)
            c0 = hsv_rgb(h, r.uniform(0.35, 0.65), r.uniform(0.5, 0.8))
            c1 = hsv_rgb(h, r.uniform(0.5, 0.8), r.uniform(0.2, 0.4))
            scale = {PAT_PLANKS: 0.1, PAT_RINGS: 0.06, PAT_STRIPES: 0.07}[pattern] * r.uniform(0.8, 1.3)
            return Texture(pattern, c0, c1, scale * ts, 0.9 * tc, 0.25, 0.08 * ts, int(r.integers(0, 3)), seed, offset)
        if kind == "fabric":
            pattern = int(r.choice([PAT_NOISE, PAT_CHECKER, PAT_STRIPES]))
            h = r.uniform(0, 1)
            c0 = hsv_rgb(h, r.uniform(0.3, 0.7), r.uniform(0.45, 0.8))
            c1 = hsv_rgb(h + r.uniform(-0.2, 0.2), r.uniform(0.3, 0.8), r.uniform(0.2, 0.45))
            scale = {PAT_NOISE: 0.12, PAT_CHECKER: 0.09, PAT_STRIPES: 0.08}[pattern] * r.uniform(0.8, 1.4)
            return Texture(pattern, c0, c1, scale * ts, 0.8 * tc, 0.25, 0.07 * ts, int(r.integers(0, 3)), seed, offset)
        if kind == "paint":  # lacquered furniture, doors
            h = r.uniform(0, 1)
            c0 = hsv_rgb(h, r.uniform(0.2, 0.6), r.uniform(0.6, 0.9))
            c1 = hsv_rgb(h + 0.05, r.uniform(0.3, 0.7), r.uniform(0.35, 0.55))
            pattern = int(r.choice([PAT_NOISE, PAT_TILES]))
            return Texture(pattern, c0, c1, r.uniform(0.15, 0.3) * ts, 0.7 * tc, 0.2, 0.06 * ts, 1, seed, offset)
        if kind == "metal":
            c0 = hsv_rgb(0.6, 0.05, r.uniform(0.6, 0.8))
            c1 = hsv_rgb(0.6, 0.1, r.uniform(0.25, 0.4))
            return Texture(PAT_NOISE, c0, c1, 0.08 * ts, 0.8 * tc, 0.15, 0.06 * ts, 2, seed, offset)
        if kind == "ceramic":
            pattern = int(r.choice([PAT_STRIPES, PAT_CHECKER, PAT_NOISE]))
            h = r.uniform(0, 1)
            c0 = hsv_rgb(h, r.uniform(0.4, 0.9), r.uniform(0.6, 0.95))
            c1 = hsv_rgb(h + r.uniform(0.2, 0.5), r.uniform(0.5, 0.9), r.uniform(0.3, 0.7))
            scale = {PAT_STRIPES: 0.05, PAT_CHECKER: 0.04, PAT_NOISE: 0.05}[pattern]
            return Texture(pattern, c0, c1, scale * ts, tc, 0.15, 0.06 * ts, 2, seed, offset)
        if kind == "plant":
            h = r.uniform(0.22, 0.38)
            c0 = hsv_rgb(h, r.uniform(0.5, 0.8), r.uniform(0.55, 0.8))
            c1 = hsv_rgb(h + 0.05, r.uniform(0.6, 0.9), r.uniform(0.15, 0.3))
            return Texture(PAT_NOISE, c0, c1, 0.08 * ts, 1.2 * tc, 0.3, 0.07 * ts, 0, seed, offset)
        if kind == "paper":  # book covers
            h = r.uniform(0, 1)
            c0 = hsv_rgb(h, r.uniform(0.4, 0.9), r.uniform(0.4, 0.9))
            c1 = hsv_rgb(h + r.uniform(0.3, 0.6), r.uniform(0.2, 0.8), r.uniform(0.2, 0.9))
            return Texture(PAT_STRIPES, c0, c1, r.uniform(0.05, 0.09) * ts, 0.8 * tc, 0.15, 0.06 * ts, 2, seed, offset)
        if kind == "art":
            pattern = int(r.choice([PAT_NOISE, PAT_RINGS, PAT_CHECKER, PAT_STRIPES]))
            c0 = hsv_rgb(r.uniform(0, 1), r.uniform(0.5, 1.0), r.uniform(0.6, 1.0))
            c1 = hsv_rgb(r.uniform(0, 1), r.uniform(0.5, 1.0), r.uniform(0.15, 0.5))
            scale = {PAT_NOISE: 0.25, PAT_RINGS: 0.12, PAT_CHECKER: 0.1, PAT_STRIPES: 0.1}[pattern]
            scale *= r.uniform(0.8, 1.3)
            return Texture(pattern, c0, c1, scale * ts, 1.2 * tc, 0.35, 0.12 * ts, 1, seed, offset)
        if kind == "sky":
            c0 = hsv_rgb(0.58, 0.15, 0.98)
            c1 = hsv_rgb(0.6, 0.6, 0.85)
            return Texture(PAT_NOISE, c0, c1, 0.35 * ts, 1.3 * tc, 0.1, 0.2 * ts, 0, seed, offset)
        if kind == "rug":
            pattern = int(r.choice([PAT_TILES, PAT_CHECKER, PAT_STRIPES, PAT_RINGS]))
            h = r.uniform(0, 1)
            c0 = hsv_rgb(h, r.uniform(0.3, 0.7), r.uniform(0.55, 0.85))
            c1 = hsv_rgb(h + r.uniform(0.3, 0.6), r.uniform(0.5, 0.9), r.uniform(0.2, 0.5))
            scale = {PAT_TILES: 0.3, PAT_CHECKER: 0.22, PAT_STRIPES: 0.18, PAT_RINGS: 0.2}[pattern]
            return Texture(pattern, c0, c1, scale * ts, tc, 0.3, 0.08 * ts, 2, seed, offset)
        if kind == "dark":
            c0 = hsv_rgb(0.6, 0.1, 0.2)
            c1 = hsv_rgb(0.6, 0.3, 0.05)
            return Texture(PAT_NOISE, c0, c1, 0.15 * ts, tc, 0.2, 0.1 * ts, 0, seed, offset)
        if kind == "shade":
            h = r.uniform(0.05, 0.15)
            c0 = hsv_rgb(h, r.uniform(0.1, 0.4), 0.95)
            c1 = hsv_rgb(h, r.uniform(0.3, 0.6), 0.6)
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
        floor = single_part_object("floor", box_part(None, (0, 0, -th / 2), slab, self.texture("floor")), 0, 0, 0)
        self.place(floor, np.zeros(3), np.eye(3), structural=True)
        ceiling = single_part_object("ceiling", box_part(None, (0, 0, lz + th / 2), slab, self.texture("ceiling")),
                                     0, 0, 0)
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
            spec = single_part_object("wall", box_part(None, (0, -th / 2, lz / 2), half, tex), 0, 0, 0)
            key = self.place(spec, origin, rotation, structural=True)
            self.nodes[key].name = f"wall_{'SENW'[wall]}"

    # --- furniture ---------------------------------------------------------------------------
    def spec_table(self) -> ObjectSpec:
        r = self.rng
        w, d, h = r.uniform(1.1, 1.5), r.uniform(0.7, 0.9), r.uniform(0.72, 0.76)
        top_t = 0.045
        wood = self.texture("wood")
        leg_tex = reseeded(wood, 1)
        parts = [box_part("top", (0, 0, h - top_t / 2), (w / 2, d / 2, top_t / 2), wood)]
        round_legs = bool(r.integers(0, 2))
        for i, (sx, sy) in enumerate(((-1, -1), (1, -1), (1, 1), (-1, 1))):
            c = (sx * (w / 2 - 0.07), sy * (d / 2 - 0.07), (h - top_t) / 2)
            if round_legs:
                parts.append(frustum_part(f"leg_{i + 1}", c, (0.028, 0.034, (h - top_t) / 2), leg_tex))
            else:
                parts.append(box_part(f"leg_{i + 1}", c, (0.03, 0.03, (h - top_t) / 2), leg_tex))
        return ObjectSpec("table", "table", parts, w / 2, d / 2, h)

    def spec_chair(self, wood: Texture, fabric: Texture) -> ObjectSpec:
        seat_h, hw, hd = 0.46, 0.22, 0.22
        parts = [box_part("seat", (0, 0, seat_h - 0.03), (hw, hd, 0.03), fabric)]
        for i, (sx, sy) in enumerate(((-1, -1), (1, -1), (1, 1), (-1, 1))):
            leg_h = (seat_h - 0.06) / 2
            center = (sx * (hw - 0.025), sy * (hd - 0.025), leg_h)
            parts.append(box_part(f"leg_{i + 1}", center, (0.022, 0.022, leg_h), wood))
        # backrest at local -y (the chair faces +y)
        parts.append(box_part("back", (0, -hd + 0.02, seat_h + 0.24), (hw, 0.02, 0.24), wood))
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
            self.surfaces.append(Surface(origin + rotation @ np.array([0, 0, table.height]), rotation,
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
        tex = lambda k: reseeded(wood, k)  # noqa: E731
        n_boards = int(r.integers(3, 5))
        parts = [
            box_part("side_left", (-w / 2 + t / 2, 0, h / 2), (t / 2, d / 2, h / 2), tex(1)),
            box_part("side_right", (w / 2 - t / 2, 0, h / 2), (t / 2, d / 2, h / 2), tex(2)),
            box_part("back", (0, -d / 2 + 0.005, h / 2), (w / 2 - t, 0.005, h / 2), tex(3)),
        ]
        levels = np.linspace(0.06, h - t / 2, n_boards + 1)
        for i, zc in enumerate(levels):
            parts.append(box_part(f"board_{i + 1}", (0, 0, zc), (w / 2 - t, d / 2, t / 2), tex(4 + i)))
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
            self.surfaces.append(Surface(origin + rotation @ np.array([0, 0.01, z_top]), rotation, w / 2 - t - 0.01,
                                          d / 2 - 0.03, clearance, group,
                                          kinds=("book_row", "book_row", "box_small", "vase", "ball", "plant_small")))
        return True

    def add_sofa(self) -> bool:
        r = self.rng
        w, d = r.uniform(1.6, 2.2), r.uniform(0.8, 0.9)
        fabric = self.texture("fabric")
        tex = lambda k: reseeded(fabric, k)  # noqa: E731
        arm, back_d, seat_top = 0.16, 0.2, 0.44
        parts = [
            box_part("base", (0, 0.02, 0.15), (w / 2 - arm, d / 2 - 0.02, 0.15), tex(1)),
            box_part("back", (0, -d / 2 + back_d / 2, 0.42), (w / 2, back_d / 2, 0.42), tex(2)),
            box_part("arm_left", (-w / 2 + arm / 2, 0.0, 0.31), (arm / 2, d / 2, 0.31), tex(3)),
            box_part("arm_right", (w / 2 - arm / 2, 0.0, 0.31), (arm / 2, d / 2, 0.31), tex(4)),
        ]
        n_cushions = 2 if w < 1.9 else 3
        inner = w - 2 * arm
        cw = inner / n_cushions
        cushion_tex = self.texture("fabric")
        for i in range(n_cushions):
            cx = -inner / 2 + cw * (i + 0.5)
            parts.append(box_part(f"cushion_{i + 1}", (cx, back_d / 2 + 0.01, (0.3 + seat_top) / 2),
                                   (cw / 2 - 0.01, (d - back_d) / 2 - 0.01, (seat_top - 0.3) / 2),
                                   reseeded(cushion_tex, i)))
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
            part = ellipsoid_part(None, (0, 0, 0.2), (0.2, 0.08, 0.2), self.texture("fabric"))
            pillow = single_part_object("pillow", part, 0.2, 0.08, 0.4)
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
        parts = [box_part("body", (0, yb, h / 2), (w / 2, d / 2, h / 2), body)]
        n_doors = 2 if w < 1.5 else 3
        dw = (w - 0.06) / n_doors
        for i in range(n_doors):
            xc = -w / 2 + 0.03 + dw * (i + 0.5)
            parts.append(box_part(f"door_{i + 1}", (xc, yb + d / 2 + 0.008, h / 2),
                                  (dw / 2 - 0.01, 0.008, h / 2 - 0.04), reseeded(doors, i)))
        sideboard = ObjectSpec("sideboard", "sideboard", parts, w / 2, d / 2 + 0.008, h)
        tv_w = min(w - 0.2, r.uniform(0.9, 1.3))
        tv_h = tv_w * 9 / 16
        frame = self.texture("dark")
        tv_parts = [
            box_part("stand", (0, 0, 0.01), (0.15, 0.1, 0.01), reseeded(frame, 1)),
            box_part("neck", (0, -0.02, 0.07), (0.03, 0.02, 0.06), reseeded(frame, 2)),
            box_part("frame", (0, -0.02, 0.12 + tv_h / 2), (tv_w / 2, 0.025, tv_h / 2), frame),
            box_part("screen", (0, 0.008, 0.12 + tv_h / 2), (tv_w / 2 - 0.025, 0.004, tv_h / 2 - 0.025),
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
                self.surfaces.append(Surface(origin + rotation @ np.array([xc, yb, h]), rotation, rest,
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
        parts = [box_part("body", (0, yb, h / 2 + 0.03), (w / 2, d / 2, h / 2 - 0.03), body),
                 box_part("plinth", (0, yb, 0.015), (w / 2 - 0.03, d / 2 - 0.03, 0.015), reseeded(body, 9))]
        n_drawers = int(r.integers(2, 4))
        dh = (h - 0.1) / n_drawers
        for i in range(n_drawers):
            zc = 0.06 + dh * (i + 0.5)
            parts.append(box_part(f"drawer_{i + 1}", (0, yb + d / 2 + 0.01, zc), (w / 2 - 0.04, 0.01, dh / 2 - 0.015),
                                   reseeded(front_tex, i)))
            parts.append(ellipsoid_part(f"knob_{i + 1}", (0, yb + d / 2 + 0.035, zc), (0.03, 0.018, 0.03), knob))
        spec = ObjectSpec("cabinet", "cabinet", parts, w / 2, d / 2 + front / 2, h)
        placed = self._against_wall(spec, z_range=(0.0, h + 0.6))  # keep the wall free above for a lamp
        if placed is None:
            return False
        origin, rotation, _ = placed
        group = self.new_group("cabinet_set")
        self.place(spec, origin, rotation, parent=group)
        surface = Surface(origin + rotation @ np.array([0, yb, h]), rotation, w / 2 - 0.03, d / 2 - 0.03, 0.8, group)
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
            frustum_part("base", (0, 0, 0.02), (0.17, 0.14, 0.02), metal),
            frustum_part("pole", (0, 0, 0.04 + (h - 0.04) / 2), (0.022, 0.022, (h - 0.04) / 2), reseeded(metal, 1)),
            frustum_part("shade", (0, 0, h + sh - 0.05), (rb, rt, sh), self.texture("shade")),
        ]
        return ObjectSpec("floor_lamp", "lamp", parts, rb, rb, h + 2 * sh)

    def spec_plant(self, scale: float = 1.0) -> ObjectSpec:
        r = self.rng
        ph = r.uniform(0.25, 0.35) * scale
        rb, rt = r.uniform(0.1, 0.13) * scale, r.uniform(0.14, 0.18) * scale
        fr = r.uniform(0.22, 0.3) * scale
        fz = r.uniform(1.1, 1.6) * fr
        parts = [
            frustum_part("pot", (0, 0, ph / 2), (rb, rt, ph / 2), self.texture("ceramic")),
            ellipsoid_part("foliage", (0, 0, ph + fz * 0.85), (fr, fr * r.uniform(0.8, 1.0), fz),
                           self.texture("plant")),
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
            frustum_part("top", (0, 0, h - 0.015), (rad, rad, 0.015), wood),
            frustum_part("stem", (0, 0, h / 2), (0.035, 0.035, h / 2 - 0.03), reseeded(wood, 1)),
            frustum_part("foot", (0, 0, 0.02), (0.2, 0.16, 0.02), reseeded(wood, 2)),
        ]
        group = self.new_group("side_table_set")
        placed = self.add_free_standing(ObjectSpec("side_table", "side_table", parts, rad, rad, h), parent=group)
        if placed is None:
            return False
        origin, rotation = placed
        self.surfaces.append(Surface(origin + np.array([0.0, 0.0, h]), rotation, rad * 0.6, rad * 0.6, 0.6, group))
        return True

    def add_door(self) -> bool:
        r = self.rng
        w, h = r.uniform(0.82, 0.95), r.uniform(2.0, 2.1)
        tex = self.texture("paint")
        parts = [
            box_part("panel", (0, 0.02, h / 2), (w / 2, 0.02, h / 2), tex),
            box_part("frame", (0, 0.015, h / 2 + 0.02), (w / 2 + 0.06, 0.015, h / 2 + 0.02), self.texture("paint")),
            ellipsoid_part("handle", (w / 2 - 0.1, 0.065, 1.0), (0.05, 0.025, 0.025), self.texture("metal")),
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
            parts = [box_part("frame", (0, 0.02, h / 2), (w / 2, 0.02, h / 2), frame_tex)]
            pane_w = (w - 0.15) / 2
            for i, sx in enumerate((-1, 1)):
                parts.append(box_part(f"pane_{i + 1}", (sx * (pane_w / 2 + 0.025), 0.045, h / 2),
                                  (pane_w / 2, 0.005, h / 2 - 0.05), self.texture("sky")))
            parts.append(box_part("sill", (0, 0.08, -0.02), (w / 2 + 0.05, 0.08, 0.02), reseeded(frame_tex, 5)))
            spec = ObjectSpec("window", "window", parts, w / 2 + 0.05, 0.07, h)
        elif kind == "painting":
            w, h = r.uniform(0.5, 1.0), r.uniform(0.4, 0.8)
            z0 = r.uniform(1.25, 1.55) - h / 2
            parts = [
                box_part("frame", (0, 0.02, h / 2), (w / 2, 0.02, h / 2), self.texture_of("wood", "dark")),
                box_part("canvas", (0, 0.042, h / 2), (w / 2 - 0.05, 0.005, h / 2 - 0.05), self.texture("art")),
            ]
            spec = ObjectSpec("painting", "painting", parts, w / 2, 0.03, h)
        elif kind == "clock":
            rad = r.uniform(0.14, 0.2)
            z0 = r.uniform(1.6, 1.9)
            parts = [
                frustum_part("body", (0, 0.025, rad), (rad, rad * 0.95, 0.025), self.texture("ceramic"),
                         rotation=rot_x(-math.pi / 2)),  # axis out of the wall
                box_part("hand", (0, 0.052, rad + rad * 0.35), (0.01, 0.005, rad * 0.35), self.texture("dark")),
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
                    spec = single_part_object("rug", box_part(None, (0, 0, 0.006), (w, d, 0.006), self.texture("rug")),
                                              w, d, 0.012)
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
                spec = single_part_object("rug", box_part(None, (0, 0, 0.006), (w, d, 0.006), self.texture("rug")),
                                          w, d, 0.012)
                self.place(spec, origin, rotation)
                return True
        return False

    def add_floor_item(self) -> bool:
        r = self.rng
        kind = str(r.choice(["ball", "basket", "basket", "ottoman", "plant", "plant"]))
        if kind == "ball":
            rad = r.uniform(0.1, 0.16)
            part = ellipsoid_part(None, (0, 0, rad), (rad, rad, rad), self.texture_of("ceramic", "fabric"))
            spec = single_part_object("ball", part, rad, rad, 2 * rad)
        elif kind == "basket":
            hx, hy, hz = r.uniform(0.18, 0.28), r.uniform(0.15, 0.22), r.uniform(0.12, 0.2)
            part = box_part(None, (0, 0, hz), (hx, hy, hz), self.texture_of("wood", "fabric"))
            spec = single_part_object("basket", part, hx, hy, 2 * hz)
        elif kind == "ottoman":
            rad, hz = r.uniform(0.22, 0.3), r.uniform(0.18, 0.22)
            part = frustum_part(None, (0, 0, hz), (rad, rad, hz), self.texture("fabric"))
            spec = single_part_object("ottoman", part, rad, rad, 2 * hz)
        else:
            spec = self.spec_plant(scale=1.0)
        return self.add_free_standing(spec) is not None

    # --- small items ---------------------------------------------------------------------------
    def spec_item(self, kind: str, clearance: float) -> ObjectSpec | None:
        """A small item standing on a support (local origin at its bottom centre); None if it cannot fit."""
        r = self.rng
        if kind == "mug":
            rad, h = r.uniform(0.04, 0.05), r.uniform(0.09, 0.11)
            parts = [frustum_part(None, (0, 0, h / 2), (rad * 0.9, rad, h / 2), self.texture("ceramic"))]
            spec = ObjectSpec("mug", "mug", parts, rad, rad, h)
        elif kind == "vase":
            rb, rt, h = r.uniform(0.05, 0.08), r.uniform(0.03, 0.06), r.uniform(0.18, 0.32)
            parts = [frustum_part("body", (0, 0, h / 2), (rb, rt, h / 2), self.texture("ceramic"))]
            if r.uniform() < 0.6:
                fr = r.uniform(0.08, 0.12)
                parts.append(ellipsoid_part("flowers", (0, 0, h + fr * 0.8), (fr, fr, fr),
                                            self.texture_of("plant", "art")))
                h = h + fr * 1.8
            else:
                parts[0].name = None
            ext = max(rb, 0.1) if len(parts) > 1 else rb
            spec = ObjectSpec("vase", "vase", parts, ext, ext, h)
        elif kind == "bowl":
            rad = r.uniform(0.1, 0.14)
            parts = [ellipsoid_part(None, (0, 0, 0.05), (rad, rad, 0.05), self.texture("ceramic"))]
            spec = ObjectSpec("bowl", "bowl", parts, rad, rad, 0.1)
        elif kind == "fruit_bowl":
            rad = r.uniform(0.13, 0.16)
            parts = [frustum_part("bowl", (0, 0, 0.035), (rad * 0.6, rad, 0.035), self.texture("ceramic"))]
            for i in range(3):
                ang = 2 * math.pi * i / 3 + r.uniform(-0.3, 0.3)
                fr = r.uniform(0.035, 0.045)
                center = (0.45 * rad * math.cos(ang), 0.45 * rad * math.sin(ang), 0.07 + fr * 0.6)
                parts.append(ellipsoid_part(f"fruit_{i + 1}", center, (fr, fr, fr), self.texture("ceramic")))
            spec = ObjectSpec("fruit_bowl", "fruit_bowl", parts, rad, rad, 0.16)
        elif kind == "book_pile":
            parts = []
            z = 0.0
            for i in range(int(r.integers(2, 4))):
                bx, by, bz = r.uniform(0.09, 0.12), r.uniform(0.13, 0.16), r.uniform(0.012, 0.025)
                center = (r.uniform(-0.01, 0.01), r.uniform(-0.01, 0.01), z + bz)
                parts.append(box_part(f"book_{i + 1}", center, (bx, by, bz), self.texture("paper"),
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
                parts.append(box_part(f"book_{i + 1}", (x + bw, 0, bh), (bw, bd, bh), self.texture("paper")))
                x += 2 * bw + 0.002
                max_h = max(max_h, 2 * bh)
            for part in parts:
                part.center = (part.center[0] - x / 2, 0, part.center[2])
            spec = ObjectSpec("book_row", "books", parts, x / 2, 0.12, max_h)
            spec.aligned = True
        elif kind == "bottle":
            rad, h = r.uniform(0.03, 0.045), r.uniform(0.18, 0.26)
            glass = self.texture("ceramic")
            parts = [frustum_part("body", (0, 0, h * 0.35), (rad, rad, h * 0.35), glass),
                     frustum_part("neck", (0, 0, h * 0.7 + h * 0.15), (rad, rad * 0.35, h * 0.15), reseeded(glass, 1))]
            spec = ObjectSpec("bottle", "bottle", parts, rad, rad, h)
        elif kind == "ball":
            rad = r.uniform(0.05, 0.09)
            part = ellipsoid_part(None, (0, 0, rad), (rad, rad, rad), self.texture("ceramic"))
            spec = single_part_object("ball", part, rad, rad, 2 * rad)
        elif kind == "box_small":
            hx, hy, hz = r.uniform(0.06, 0.12), r.uniform(0.05, 0.1), r.uniform(0.04, 0.09)
            part = box_part(None, (0, 0, hz), (hx, hy, hz), self.texture_of("paper", "wood", "fabric"))
            spec = single_part_object("box", part, hx, hy, 2 * hz)
        elif kind == "plant_small":
            spec = self.spec_plant(scale=0.45)
        elif kind == "table_lamp":
            rb = r.uniform(0.07, 0.09)
            stem_h = r.uniform(0.22, 0.3)
            shade_b, shade_t, shade_h = r.uniform(0.13, 0.17), r.uniform(0.08, 0.11), r.uniform(0.09, 0.12)
            metal = self.texture("metal")
            parts = [
                frustum_part("base", (0, 0, 0.02), (rb, rb * 0.8, 0.02), metal),
                frustum_part("stem", (0, 0, 0.04 + stem_h / 2), (0.015, 0.015, stem_h / 2), reseeded(metal, 1)),
                frustum_part("shade", (0, 0, 0.04 + stem_h + shade_h - 0.03), (shade_b, shade_t, shade_h),
                         self.texture("shade")),
            ]
            spec = ObjectSpec("table_lamp", "lamp", parts, shade_b, shade_b, 0.04 + stem_h + 2 * shade_h - 0.03)
        else:
            raise ValueError(kind)
        if spec.height > clearance:
            return None
        return spec

    def place_on(self, surface: Surface, kind: str) -> bool:
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
