"""Tests of the synthetic room generator (trace3d.datasets.synthetic): tiny rooms, 64x48, 8 views."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from trace3d.datasets import synthetic as syn
from trace3d.datasets.synthetic import raycast, raycast_reference
from trace3d.errors import ConfigError, Trace3DError
from trace3d.scene import Camera, Scene

TINY = dict(width=64, height=48, num_views=8, test_every=4)


def _generate(root: Path, **overrides) -> Path:
    params = syn.params_from({**TINY, **overrides})
    root.mkdir(parents=True)
    syn.generate_scene(root, params)
    return root


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory) -> Path:
    return _generate(tmp_path_factory.mktemp("synthetic") / "scene", seed=3)


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


# ----------------------------------------------------------------------------------------------
# format, determinism
# ----------------------------------------------------------------------------------------------


def test_scene_reads_and_has_all_outputs(scene_dir):
    scene = Scene.read(scene_dir)
    assert len(scene.cameras) == 8
    assert [c.name for c in scene.test_cameras] == ["view_002", "view_006"]
    assert scene.has_instances and scene.has_depth
    cam = scene.cameras[0]
    assert scene.image(cam.name).shape == (48, 64, 3)
    ids = scene.instances(cam.name)
    assert ids.dtype == np.uint16 and ids.shape == (48, 64) and (ids > 0).all()
    depth = scene.depth(cam.name)
    assert (depth > 0.1).all() and depth.max() < 10.0
    assert scene.meta["source"] == "synthetic"
    assert scene.meta["params"]["seed"] == 3
    assert scene.meta["room"]["num_objects"] == syn.SyntheticParams().num_objects
    # horizontal field of view from K
    assert math.degrees(2 * math.atan(cam.width / 2 / cam.K[0, 0])) == pytest.approx(80.0)


def test_same_seed_gives_identical_bytes(scene_dir, tmp_path):
    again = _generate(tmp_path / "again", seed=3)
    first, second = _files(scene_dir), _files(again)
    assert sorted(first) == sorted(second)
    assert len(first) == 3 * 8 + 3  # images, instances, depth + cameras, objects, meta
    for name in first:
        assert first[name] == second[name], name


def test_different_seed_gives_different_layout():
    a = syn.build_room(syn.SyntheticParams(seed=3))
    b = syn.build_room(syn.SyntheticParams(seed=4))
    assert a.size != b.size
    centers_a = np.array([p.center for p in a.primitives])
    centers_b = np.array([p.center for p in b.primitives])
    assert centers_a.shape != centers_b.shape or not np.allclose(centers_a, centers_b)
    names_a = [n.name for n in a.nodes if n.level == "object"]
    names_b = [n.name for n in b.nodes if n.level == "object"]
    assert names_a != names_b or not np.allclose(centers_a, centers_b)


# ----------------------------------------------------------------------------------------------
# physical consistency
# ----------------------------------------------------------------------------------------------


def _reproject(src: Camera, dst: Camera, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel centres of ``src`` with ``depth`` [H, W] -> (dst pixel x, dst pixel y, dst camera z), each [H, W]."""
    H, W = depth.shape
    ys, xs = np.mgrid[0:H, 0:W] + 0.5
    rays = np.stack([xs, ys, np.ones_like(xs)], -1) @ np.linalg.inv(src.K).T  # camera z = 1
    points_cam = rays * depth[..., None]
    c2w = src.camera_to_world
    points = points_cam.reshape(-1, 3) @ c2w[:3, :3].T + c2w[:3, 3]
    uv, z = dst.project(points)
    return uv[:, 0].reshape(H, W), uv[:, 1].reshape(H, W), z.reshape(H, W)


@pytest.fixture(scope="module")
def loop_dir(tmp_path_factory) -> Path:
    """16 views (22.5 degrees apart) so that neighbours overlap as on the real 72-view loop."""
    return _generate(tmp_path_factory.mktemp("synthetic") / "loop", seed=5, num_views=16, width=96, height=72)


def test_depth_reprojection_lands_on_same_instance(loop_dir):
    """Ground-truth depth of view i, re-projected into view i+1, lands on the same instance id."""
    scene = Scene.read(loop_dir)
    cams = scene.cameras
    agree_total = covisible_total = 0
    for i in range(len(cams)):
        src, dst = cams[i], cams[(i + 1) % len(cams)]
        ids_src, ids_dst = scene.instances(src.name), scene.instances(dst.name)
        u, v, z = _reproject(src, dst, scene.depth(src.name))
        inside = (u >= 0.5) & (u < dst.width - 0.5) & (v >= 0.5) & (v < dst.height - 0.5) & (z > 0)
        xi = np.floor(np.clip(u, 0, dst.width - 1)).astype(int)
        yi = np.floor(np.clip(v, 0, dst.height - 1)).astype(int)
        covisible = inside & (np.abs(scene.depth(dst.name)[yi, xi] - z) < 0.03 * z + 0.01)  # not occluded in dst
        assert covisible.mean() > 0.3, f"{src.name}->{dst.name}: too little overlap ({covisible.mean():.2f})"
        same = ids_src[covisible] == ids_dst[yi[covisible], xi[covisible]]
        agree_total += int(same.sum())
        covisible_total += int(covisible.sum())
        # the id at a sub-pixel location is one of the four surrounding pixel-centre samples
        x0 = np.clip(np.floor(u - 0.5).astype(int), 0, dst.width - 2)
        y0 = np.clip(np.floor(v - 0.5).astype(int), 0, dst.height - 2)
        among = np.zeros_like(covisible)
        for dy in (0, 1):
            for dx in (0, 1):
                among |= ids_dst[y0 + dy, x0 + dx] == ids_src
        assert among[covisible].mean() >= 0.98, f"{src.name}->{dst.name}: {among[covisible].mean():.3f}"
    assert agree_total / covisible_total >= 0.95, f"only {agree_total / covisible_total:.3f} of co-visible pixels agree"


def test_no_view_dependent_shading():
    """A surface point seen from two cameras gets the same radiance (fast kernel), as the reference says."""
    params = syn.SyntheticParams(seed=3)
    packed = syn.build_room(params).packed()
    cams = syn.camera_trajectory(params)
    geometry = packed.geometry()
    shading = (packed.tex_int, packed.tex_float, packed.lights, packed.light_power, params.ambient, True)
    rng = np.random.default_rng(0)
    compared = 0
    for _ in range(60):
        a, b = (cams[i] for i in rng.choice(len(cams), 2, replace=False))
        pixel = np.array([rng.uniform(0, a.width), rng.uniform(0, a.height), 1.0])
        d_a = a.camera_to_world[:3, :3] @ np.linalg.inv(a.K) @ pixel
        t_a, p_a, f_a = raycast.cast_ray(*a.center, *d_a, 1e-6, np.inf, *geometry, False)
        point = a.center + t_a * d_a
        d_b = point - b.center
        t_b, p_b, f_b = raycast.cast_ray(*b.center, *d_b, 1e-6, np.inf, *geometry, False)
        if p_b != p_a or abs(t_b - 1.0) > 1e-9:
            continue  # occluded from b
        in_front = (b.world_to_camera[:3, :3] @ d_b)[2] > 0
        color_a = np.array(raycast._shade(*a.center, *d_a, t_a, p_a, f_a, *geometry, *shading))
        color_b = np.array(raycast._shade(*b.center, *d_b, t_b, p_b, f_b, *geometry, *shading))
        np.testing.assert_allclose(color_a, color_b, rtol=1e-7, atol=1e-10)
        if compared < 8:
            ref = raycast_reference._ref_shade(packed, b.center[None], d_b[None], params.ambient, True)[0]
            np.testing.assert_allclose(color_b, ref, rtol=1e-7, atol=1e-10)
        compared += int(in_front)
    assert compared >= 5


# ----------------------------------------------------------------------------------------------
# fast kernel vs slow reference
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [3, 11])
def test_kernel_matches_reference(seed):
    params = syn.SyntheticParams(seed=seed, width=40, height=30, num_views=12)
    packed = syn.build_room(params).packed()
    for cam in syn.camera_trajectory(params)[::5]:
        rgb, prim, depth = syn.render_view(packed, cam, 2, params.ambient, True)
        rgb_ref, prim_ref, depth_ref = syn.render_view_reference(packed, cam, 2, params.ambient, True)
        same = prim == prim_ref
        assert same.mean() >= 0.998, f"{cam.name}: primitive ids differ on {(~same).sum()} pixels"
        np.testing.assert_allclose(depth[same], depth_ref[same], rtol=1e-9, atol=1e-9)
        close = np.abs(rgb - rgb_ref).max(axis=-1) < 1e-6
        assert close.mean() >= 0.99, f"{cam.name}: colours differ on {(~close).sum()} pixels"
        assert np.abs(rgb - rgb_ref).mean() < 1e-3


def test_primitive_intersections_match_reference():
    """Random rays against each primitive kind, including rays starting inside and grazing the caps."""
    rng = np.random.default_rng(0)
    for shape, size in ((syn.SHAPE_BOX, (0.3, 0.2, 0.5)), (syn.SHAPE_ELLIPSOID, (0.3, 0.2, 0.4)),
                        (syn.SHAPE_FRUSTUM, (0.3, 0.1, 0.25)), (syn.SHAPE_FRUSTUM, (0.2, 0.2, 0.4))):
        size = np.array(size)
        origins = rng.uniform(-1.0, 1.0, (400, 3))
        origins[:40] *= 0.2 * size / np.abs(origins[:40]).max(1, keepdims=True)  # rays starting inside
        dirs = rng.uniform(-0.9, 0.9, (400, 3)) * np.r_[size[:2].max(), size[:2].max(), size[2]] - origins
        dirs[40:90, 2] = 0.0  # horizontal rays (parallel to the caps)
        fast = np.array([raycast._intersect_local(shape, *size, *o, *d, 1e-9)[0] for o, d in zip(origins, dirs)])
        if shape == syn.SHAPE_BOX:
            slow = raycast_reference._ref_hit_box(origins, dirs, size, 1e-9)
        elif shape == syn.SHAPE_ELLIPSOID:
            slow = raycast_reference._ref_hit_ellipsoid(origins, dirs, size, 1e-9)
        else:
            slow = raycast_reference._ref_hit_frustum(origins, dirs, size, 1e-9)[0]
        assert np.isfinite(fast).sum() > 200
        np.testing.assert_allclose(fast, slow, rtol=1e-9, atol=1e-12)


# ----------------------------------------------------------------------------------------------
# objects.json
# ----------------------------------------------------------------------------------------------


def test_hierarchy_and_evaluated_flags(scene_dir):
    scene = Scene.read(scene_dir)
    table = scene.objects
    by_id = table.by_id
    objects = [o for o in table if o.level == "object"]
    movable = [o for o in objects if o.category not in syn.STRUCTURE_CATEGORIES]
    assert len(movable) == syn.SyntheticParams().num_objects >= 10
    assert {o.category for o in objects} >= {"floor", "ceiling", "wall", "table", "chair", "shelf"}
    for o in table:
        if o.level == "part":
            assert o.parent is not None and by_id[o.parent].level == "object"
        if o.level == "object" and o.parent is not None:
            assert by_id[o.parent].level == "group"
        if o.level == "group":
            assert o.parent is None and sum(c.parent == o.id for c in table) >= 2
    # composite objects with parts exist (table = top + legs)
    tables = [o for o in objects if o.category == "table"]
    assert tables
    parts = [p.name.split("/")[1] for p in table if p.parent == tables[0].id]
    assert "top" in parts and sum(p.startswith("leg_") for p in parts) == 4
    # instance maps only carry leaf ids
    parents = {o.parent for o in table if o.parent is not None}
    leaves = {o.id for o in table} - parents
    seen = set()
    lookup = table.lookup("object")
    max_pixels: dict[int, int] = {}
    for cam in scene.cameras:
        ids = scene.instances(cam.name)
        seen |= set(np.unique(ids).tolist())
        objs, counts = np.unique(lookup[ids], return_counts=True)
        for oid, count in zip(objs.tolist(), counts.tolist()):
            max_pixels[oid] = max(max_pixels.get(oid, 0), count)
    assert seen <= leaves
    threshold = scene.meta["params"]["min_visible_pixels"]
    for o in table:
        expected = (o.level == "object" and o.category not in syn.STRUCTURE_CATEGORIES
                    and max_pixels.get(o.id, 0) >= threshold)
        assert o.evaluated == expected, o
    assert any(o.evaluated for o in table)
    assert any(not o.evaluated and o.category not in syn.STRUCTURE_CATEGORIES and o.level == "object"
               for o in table) or all(max_pixels.get(o.id, 0) >= threshold for o in movable)


def test_layouts_place_objects_against_walls_and_on_supports():
    for seed in range(8):
        layout = syn.build_room(syn.SyntheticParams(seed=seed))
        lx, ly, lz = layout.size
        prims = layout.primitives
        # nothing pokes through the walls, the floor or the ceiling (structure excluded)
        structure = {n.key for n in layout.nodes if n.category in syn.STRUCTURE_CATEGORIES}
        for p in prims:
            if p.leaf in structure:
                continue
            lo, hi = _aabb(p)
            assert lo[0] > -lx / 2 - 1e-6 and hi[0] < lx / 2 + 1e-6, (seed, p.leaf)
            assert lo[1] > -ly / 2 - 1e-6 and hi[1] < ly / 2 + 1e-6, (seed, p.leaf)
            assert lo[2] > -1e-6 and hi[2] < lz, (seed, p.leaf)
        # some objects stand on other objects (items on tables / shelves)
        items = [n for n in layout.nodes if n.parent is not None and n.level == "object"
                 and n.category not in ("table", "chair", "shelf", "sofa", "cabinet", "side_table", "rug")]
        assert items, f"seed {seed}: no items on supports"


def _inside(p: syn.Primitive, points: np.ndarray, margin: float = 1e-4) -> np.ndarray:
    """[N] bool: world points [N, 3] strictly inside primitive ``p``."""
    local = (points - p.center) @ p.rotation
    if p.shape == syn.SHAPE_BOX:
        return (np.abs(local) <= p.size - margin).all(1)
    if p.shape == syn.SHAPE_ELLIPSOID:
        return ((local / p.size) ** 2).sum(1) <= 1 - margin
    r0, r1, h = p.size
    radius = r0 + (r1 - r0) * (local[:, 2] + h) / (2 * h)
    return (np.abs(local[:, 2]) <= h - margin) & (np.hypot(local[:, 0], local[:, 1]) <= radius - margin)


def test_objects_do_not_interpenetrate():
    """Points sampled inside each object's solids lie (almost) nowhere inside another object's solids."""
    rng = np.random.default_rng(0)
    for seed in (0, 5):
        layout = syn.build_room(syn.SyntheticParams(seed=seed))
        node = {n.key: n for n in layout.nodes}
        owner = [n.parent if n.level == "part" else n.key for n in (node[p.leaf] for p in layout.primitives)]
        skip = {"floor", "ceiling", "wall", "rug"}  # the rug lies on the floor under chair and table legs
        radii = np.array([syn.bounding_radius(p.shape, p.size) for p in layout.primitives])
        for i, p in enumerate(layout.primitives):
            if node[owner[i]].category in skip:
                continue
            lo, hi = _aabb(p)
            points = rng.uniform(lo, hi, (600, 3))
            points = points[_inside(p, points)]
            for j, q in enumerate(layout.primitives):
                if owner[j] == owner[i] or node[owner[j]].category == "rug":
                    continue
                if np.linalg.norm(p.center - q.center) > radii[i] + radii[j]:
                    continue
                frac = _inside(q, points).mean() if len(points) else 0.0
                assert frac < 0.05, f"seed {seed}: {node[p.leaf].name} is {frac:.0%} inside {node[q.leaf].name}"


def _aabb(p: syn.Primitive) -> tuple[np.ndarray, np.ndarray]:
    """Exact world-space bounding box (lo [3], hi [3]) of a primitive."""
    R = p.rotation
    if p.shape == syn.SHAPE_BOX:
        ext = np.abs(R) @ p.size
    elif p.shape == syn.SHAPE_ELLIPSOID:
        ext = np.sqrt((R**2) @ (p.size**2))
    else:  # union of the two cap discs (axis = local z)
        axis = R[:, 2]
        disc = np.sqrt(np.clip(1.0 - axis**2, 0.0, 1.0))
        ext = np.maximum(p.size[0], p.size[1]) * disc + p.size[2] * np.abs(axis)
    return p.center - ext, p.center + ext


# ----------------------------------------------------------------------------------------------
# parameters, bench
# ----------------------------------------------------------------------------------------------


def test_params_are_strict():
    assert syn.params_from({}) == syn.SyntheticParams()
    assert syn.params_from({"room_width_range": [5.5, 6]}).room_width_range == (5.5, 6.0)
    with pytest.raises(ConfigError, match="unknown parameter"):
        syn.params_from({"num_view": 10})
    with pytest.raises(ConfigError, match="width"):
        syn.params_from({"width": "wide"})
    with pytest.raises(ConfigError, match="test_every"):
        syn.params_from({"test_every": 1})
    with pytest.raises(ConfigError, match="clear_radius"):
        syn.params_from({"camera_radius": 1.0})


def test_too_many_objects_is_refused():
    with pytest.raises(Trace3DError, match="num_objects"):
        syn.build_room(syn.SyntheticParams(num_objects=400))


def test_trajectory_is_a_closed_outward_loop():
    params = syn.SyntheticParams()
    cams = syn.camera_trajectory(params)
    centers = np.array([c.center for c in cams])
    assert np.linalg.norm(centers[:, :2], axis=1).max() < params.clear_radius - 0.3
    steps = np.linalg.norm(np.diff(np.vstack([centers, centers[:1]]), axis=0), axis=1)
    assert steps.max() < 0.1  # neighbouring views are close
    forward = np.array([c.rotation[2] for c in cams])
    outward = (forward[:, :2] * centers[:, :2]).sum(1) / np.linalg.norm(centers[:, :2], axis=1)
    assert (outward > 0.5).all()
    angles = np.unwrap(np.arctan2(forward[:, 1], forward[:, 0]))
    assert abs(angles[-1] - angles[0]) > math.radians(330)  # a full turn
    assert sum(c.split == "test" for c in cams) == params.num_views // params.test_every
