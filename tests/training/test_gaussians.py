"""Tests of trace3d.gaussians (and trace3d.render.sh): SH evaluation, rotations, initialisations and the PLY
round trip."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from trace3d.errors import SceneFormatError, Trace3DError
from trace3d.gaussians import (
    GaussianModel,
    init_from_depth,
    init_from_points,
    init_random,
    _nearest_neighbour_scales_reference,
    nearest_neighbour_scales,
    quat_to_rotmat,
    quats_aligning_z_to,
    rgb_to_sh,
)
from trace3d.render.sh import SH_C0, eval_sh, num_sh_rest
from trace3d.datasets.depth_init import depth_points_and_normals
from trace3d.scene import Camera, Scene, write_cameras, write_frame


def random_model(n: int = 50, degree: int = 3, seed: int = 0) -> GaussianModel:
    g = torch.Generator().manual_seed(seed)
    return GaussianModel(
        means=torch.randn(n, 3, generator=g),
        quats=torch.randn(n, 4, generator=g),
        log_scales=torch.randn(n, 2, generator=g) - 2,
        opacity_logits=torch.randn(n, generator=g),
        sh_dc=torch.randn(n, 1, 3, generator=g),
        sh_rest=torch.randn(n, num_sh_rest(degree), 3, generator=g) * 0.1,
    )


# ----------------------------------------------------------------------------------------------
# SH
# ----------------------------------------------------------------------------------------------


def _sh_reference(degree: int, coeffs: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Real SH from the explicit Cartesian polynomials (normalisation constants written out)."""
    x, y, z = d
    basis = [0.5 * math.sqrt(1 / math.pi)]
    if degree >= 1:
        c = math.sqrt(3 / (4 * math.pi))
        basis += [-c * y, c * z, -c * x]
    if degree >= 2:
        basis += [
            0.5 * math.sqrt(15 / math.pi) * x * y,
            -0.5 * math.sqrt(15 / math.pi) * y * z,
            0.25 * math.sqrt(5 / math.pi) * (2 * z * z - x * x - y * y),
            -0.5 * math.sqrt(15 / math.pi) * x * z,
            0.25 * math.sqrt(15 / math.pi) * (x * x - y * y),
        ]
    if degree >= 3:
        basis += [
            -0.25 * math.sqrt(35 / (2 * math.pi)) * y * (3 * x * x - y * y),
            0.5 * math.sqrt(105 / math.pi) * x * y * z,
            -0.25 * math.sqrt(21 / (2 * math.pi)) * y * (4 * z * z - x * x - y * y),
            0.25 * math.sqrt(7 / math.pi) * z * (2 * z * z - 3 * x * x - 3 * y * y),
            -0.25 * math.sqrt(21 / (2 * math.pi)) * x * (4 * z * z - x * x - y * y),
            0.25 * math.sqrt(105 / math.pi) * z * (x * x - y * y),
            -0.25 * math.sqrt(35 / (2 * math.pi)) * x * (x * x - 3 * y * y),
        ]
    basis = np.array(basis)
    return basis @ coeffs[: len(basis)]


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_eval_sh_matches_explicit_polynomials(degree):
    g = torch.Generator().manual_seed(degree)
    coeffs = torch.randn(20, 16, 3, generator=g, dtype=torch.float64)
    dirs = torch.nn.functional.normalize(torch.randn(20, 3, generator=g, dtype=torch.float64), dim=-1)
    got = eval_sh(degree, coeffs, dirs).numpy()
    for i in range(20):
        np.testing.assert_allclose(got[i], _sh_reference(degree, coeffs[i].numpy(), dirs[i].numpy()), atol=1e-12)


def test_colors_dc_roundtrip_and_degree_control():
    rgb = torch.tensor([[0.1, 0.5, 0.9], [1.0, 0.0, 0.3]])
    model = init_from_points(torch.tensor([[0.0, 0, 0], [1.0, 0, 0]]), rgb, sh_degree=2)
    torch.testing.assert_close(model.colors(torch.zeros(3) + 5), rgb, atol=1e-6, rtol=0)
    model.sh_rest[:] = 1.0
    center = torch.tensor([0.0, 0.0, -3.0])
    assert torch.allclose(model.colors(center, degree=0), rgb, atol=1e-6)
    assert not torch.allclose(model.colors(center, degree=2), rgb, atol=1e-3)
    assert model.sh_degree == 2


# ----------------------------------------------------------------------------------------------
# Rotations
# ----------------------------------------------------------------------------------------------


def test_quat_to_rotmat_is_rotation_and_matches_axis_angle():
    q = torch.nn.functional.normalize(torch.randn(30, 4, dtype=torch.float64), dim=-1)
    R = quat_to_rotmat(q)
    eye = torch.eye(3, dtype=torch.float64).expand(30, 3, 3)
    torch.testing.assert_close(R @ R.transpose(1, 2), eye)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(30, dtype=torch.float64))
    # 90 degrees about z maps x to y
    half = math.pi / 4
    Rz = quat_to_rotmat(torch.tensor([[math.cos(half), 0, 0, math.sin(half)]], dtype=torch.float64))[0]
    torch.testing.assert_close(Rz @ torch.tensor([1.0, 0, 0], dtype=torch.float64),
                               torch.tensor([0.0, 1, 0], dtype=torch.float64))


def test_quats_aligning_z_to_normals():
    normals = torch.nn.functional.normalize(torch.randn(40, 3, dtype=torch.float64), dim=-1)
    normals = torch.cat([normals, torch.tensor([[0.0, 0, -1], [0.0, 0, 1]], dtype=torch.float64)])
    R = quat_to_rotmat(quats_aligning_z_to(normals))
    torch.testing.assert_close(R[:, :, 2], normals, atol=1e-9, rtol=0)


# ----------------------------------------------------------------------------------------------
# Initialisation
# ----------------------------------------------------------------------------------------------


def test_nearest_neighbour_scales_brute_force():
    g = torch.Generator().manual_seed(3)
    pts = torch.randn(57, 3, generator=g)
    d2 = ((pts[:, None] - pts[None]) ** 2).sum(-1)
    d2.fill_diagonal_(float("inf"))
    expected = d2.sort(dim=1).values[:, :3].mean(1).sqrt()
    slow = _nearest_neighbour_scales_reference(pts, k=3, chunk_elements=200)  # forces several chunks
    torch.testing.assert_close(slow, expected, atol=1e-5, rtol=1e-5)
    fast = nearest_neighbour_scales(pts, k=3)
    torch.testing.assert_close(fast, slow, atol=1e-6, rtol=1e-6)
    assert nearest_neighbour_scales(pts[:1]).tolist() == [1.0]
    torch.testing.assert_close(nearest_neighbour_scales(pts[:2]), (pts[0] - pts[1]).norm().expand(2))


def test_init_from_points_grid_scales_colours_and_opacity():
    xs = torch.arange(5, dtype=torch.float32) * 0.2
    grid = torch.stack(torch.meshgrid(xs, xs, indexing="ij"), -1).reshape(-1, 2)
    pts = torch.cat([grid, torch.zeros(25, 1)], 1)
    colors = np.full((25, 3), 255, dtype=np.uint8)
    colors[:, 1] = 0
    model = init_from_points(pts, colors, sh_degree=1, opacity=0.1, seed=1)
    assert len(model) == 25
    # 3 nearest neighbours: at 0.2 for edge and interior points; 0.2, 0.2, 0.2 sqrt(2) at the corners
    expected = torch.full((25,), 0.2)
    expected[[0, 4, 20, 24]] = math.sqrt((0.04 + 0.04 + 0.08) / 3)
    torch.testing.assert_close(model.scales, expected[:, None].expand(25, 2), atol=1e-5, rtol=0)
    torch.testing.assert_close(model.opacities, torch.full((25,), 0.1))
    torch.testing.assert_close(model.colors(torch.zeros(3) + 10), torch.tensor([1.0, 0.0, 1.0]).expand(25, 3),
                               atol=1e-6, rtol=0)
    assert model.sh_rest.shape == (25, 3, 3)
    # deterministic from the seed
    again = init_from_points(pts, colors, sh_degree=1, opacity=0.1, seed=1)
    torch.testing.assert_close(again.quats, model.quats)
    other = init_from_points(pts, colors, sh_degree=1, opacity=0.1, seed=2)
    assert not torch.allclose(other.quats, model.quats)


def test_init_from_points_rejects_bad_input():
    with pytest.raises(Trace3DError):
        init_from_points(np.zeros((0, 3)), np.zeros((0, 3)))
    with pytest.raises(Trace3DError):
        init_from_points(np.zeros((4, 3)), np.zeros((3, 3)))


def test_init_random_inside_bounds():
    model = init_random(500, np.array([-1.0, 0, 2]), np.array([1.0, 0.5, 3]), sh_degree=0, seed=4)
    assert len(model) == 500 and model.sh_rest.shape == (500, 0, 3)
    lo, hi = model.means.min(0).values, model.means.max(0).values
    assert (lo >= torch.tensor([-1.0, 0, 2])).all() and (hi <= torch.tensor([1.0, 0.5, 3])).all()
    assert (hi - lo > torch.tensor([1.8, 0.45, 0.9])).all()
    with pytest.raises(Trace3DError):
        init_random(10, np.zeros(3), np.zeros(3))


def _plane_scene(tmp_path, depth_value=2.0, width=16, height=12):
    """Two cameras facing a fronto-parallel plane at z = depth_value (world = camera 0 frame)."""
    K = np.array([[10.0, 0, width / 2], [0, 10.0, height / 2], [0, 0, 1]])
    cams = []
    for i, shift in enumerate([0.0, 0.3]):
        w2c = np.eye(4)
        w2c[0, 3] = -shift  # camera centre at x = shift
        cams.append(Camera(f"f{i}", "train", width, height, K, w2c))
        rgb = np.zeros((height, width, 3), np.uint8)
        rgb[..., 0] = 200
        depth = np.full((height, width), depth_value)
        depth[0, 0] = 0.0  # invalid pixel
        write_frame(tmp_path, f"f{i}", rgb, depth=depth)
    write_cameras(tmp_path, cams)
    return Scene.read(tmp_path)


def test_init_from_depth_back_projects_onto_the_plane(tmp_path):
    scene = _plane_scene(tmp_path)
    model = init_from_depth(scene, stride=2, max_points=None, sh_degree=0, seed=0)
    assert len(model) == 2 * 6 * 8
    torch.testing.assert_close(model.means[:, 2], torch.full((len(model),), 2.0))
    # depth normals face the camera (-z) away from the image border, where they are undefined (0)
    points, colors, normals = depth_points_and_normals(scene, stride=2, max_points=None, seed=0)
    torch.testing.assert_close(points, model.means)
    defined = normals.norm(dim=-1) > 0.5
    assert int(defined.sum()) == 2 * 5 * 7  # rows 1..9, columns 1..13 of the stride-2 grid
    torch.testing.assert_close(normals[defined], torch.tensor([0.0, 0.0, -1.0]).expand(70, 3), atol=1e-6, rtol=0)
    # the disks lie in the plane there
    torch.testing.assert_close(model.normals[defined], normals[defined], atol=1e-5, rtol=0)
    limited = init_from_depth(scene, stride=1, max_points=30, sh_degree=0, seed=0)
    assert len(limited) == 30


def test_init_from_depth_without_depth_raises(tmp_path):
    K = np.array([[10.0, 0, 4], [0, 10.0, 3], [0, 0, 1]])
    write_frame(tmp_path, "a", np.zeros((6, 8, 3), np.uint8))
    write_cameras(tmp_path, [Camera("a", "train", 8, 6, K, np.eye(4))])
    with pytest.raises(Trace3DError, match="depth"):
        init_from_depth(Scene.read(tmp_path))


# ----------------------------------------------------------------------------------------------
# PLY
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("degree", [0, 3])
def test_ply_round_trip(tmp_path, degree):
    model = random_model(37, degree)
    path = tmp_path / "pc.ply"
    model.write_ply(path)
    back = GaussianModel.read_ply(path)
    for name in GaussianModel.PARAM_NAMES:
        torch.testing.assert_close(getattr(back, name), getattr(model, name).float(), rtol=0, atol=0)
    # header: the standard attribute order, binary little endian
    header = path.read_bytes().split(b"end_header\n")[0].decode()
    props = [line.split()[-1] for line in header.splitlines() if line.startswith("property")]
    k = num_sh_rest(degree)
    assert props[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert props[9 : 9 + 3 * k] == [f"f_rest_{i}" for i in range(3 * k)]
    assert props[9 + 3 * k :] == ["opacity", "scale_0", "scale_1", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert "format binary_little_endian 1.0" in header


def test_ply_f_rest_is_channel_major(tmp_path):
    model = random_model(2, 1)
    model.sh_rest.zero_()
    model.sh_rest[0, 2, 0] = 7.0  # third red coefficient -> f_rest_2 (red block first)
    model.sh_rest[0, 0, 1] = 9.0  # first green coefficient -> f_rest_3
    path = tmp_path / "pc.ply"
    model.write_ply(path)
    raw = path.read_bytes()
    body = raw[raw.index(b"end_header\n") + len(b"end_header\n") :]
    row = np.frombuffer(body, dtype="<f4").reshape(2, -1)[0]
    assert row[9 + 2] == 7.0 and row[9 + 3] == 9.0


def test_read_ply_errors(tmp_path):
    with pytest.raises(SceneFormatError, match="missing"):
        GaussianModel.read_ply(tmp_path / "nope.ply")
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"not a ply")
    with pytest.raises(SceneFormatError, match="not a PLY"):
        GaussianModel.read_ply(bad)
    model = random_model(10, 0)
    path = tmp_path / "t.ply"
    model.write_ply(path)
    path.write_bytes(path.read_bytes()[:-20])
    with pytest.raises(SceneFormatError, match="truncated"):
        GaussianModel.read_ply(path)
    # missing a required attribute
    header = b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nend_header\n"
    only_x = tmp_path / "x.ply"
    only_x.write_bytes(header + np.zeros(1, "<f4").tobytes())
    with pytest.raises(SceneFormatError, match="lacks"):
        GaussianModel.read_ply(only_x)


def test_rgb_to_sh_constant():
    assert float(rgb_to_sh(torch.tensor(0.5))) == 0.0
    assert abs(float(rgb_to_sh(torch.tensor(1.0))) * SH_C0 - 0.5) < 1e-7


# ----------------------------------------------------------------------------------------------
# Extensible attributes: extras follow subsets, splits, optimiser edits and the PLY
# ----------------------------------------------------------------------------------------------


def model_with_extras(n: int = 5) -> GaussianModel:
    g = torch.Generator().manual_seed(3)
    return GaussianModel(
        means=torch.randn(n, 3, generator=g), quats=torch.randn(n, 4, generator=g),
        log_scales=torch.randn(n, 2, generator=g) - 3, opacity_logits=torch.randn(n, generator=g),
        sh_dc=torch.randn(n, 1, 3, generator=g), sh_rest=torch.randn(n, 3, 3, generator=g),
        extras={"features": torch.randn(n, 16, generator=g), "generation": torch.arange(n, dtype=torch.float32)},
    )


def test_extras_round_trip_through_ply(tmp_path):
    model = model_with_extras()
    model.write_ply(tmp_path / "m.ply")
    back = GaussianModel.read_ply(tmp_path / "m.ply")
    assert list(back.extras) == ["features", "generation"]
    assert back.extras["features"].shape == (5, 16) and back.extras["generation"].shape == (5,)
    for name in model.names:
        torch.testing.assert_close(back.get(name), model.get(name))
    header = (tmp_path / "m.ply").read_bytes().split(b"end_header")[0].decode()
    assert "property float extra_features_15" in header and "property float extra_generation\n" in header


def test_empty_model_round_trips_through_ply(tmp_path):
    """An object that owns no Gaussians still gets a valid (empty) PLY with the full attribute layout."""
    model = model_with_extras()
    empty = model.subset(torch.zeros(len(model), dtype=torch.bool))
    empty.write_ply(tmp_path / "e.ply")
    back = GaussianModel.read_ply(tmp_path / "e.ply")
    assert len(back) == 0 and back.sh_rest.shape[1] == model.sh_rest.shape[1]
    assert back.extras["features"].shape == (0, 16)
    header = (tmp_path / "e.ply").read_bytes().split(b"end_header")[0].decode()
    assert "element vertex 0" in header and "property float f_rest_0" in header


def test_extras_follow_subset_and_split():
    from trace3d.training import split_gaussians

    model = model_with_extras()
    sub = model.subset(torch.tensor([False, True, False, True, False]))
    torch.testing.assert_close(sub.extras["generation"], torch.tensor([1.0, 3.0]))
    children = split_gaussians(sub, 2, torch.Generator().manual_seed(0), scale_divisor=2.0)
    torch.testing.assert_close(children.extras["generation"], torch.tensor([1.0, 3.0, 1.0, 3.0]))
    torch.testing.assert_close(children.extras["features"], sub.extras["features"].repeat(2, 1))
    torch.testing.assert_close(children.scales, sub.scales.repeat(2, 1) / 2.0)


def test_optimizer_edits_carry_extras_and_statistics():
    from trace3d.training import GaussianOptimizer, TrainParams, learning_rates

    model = model_with_extras()
    params = TrainParams()
    lrs = {**learning_rates(params, 1.0), "features": 0.01}
    state = GaussianOptimizer(model, lrs, params, 1.0)
    assert isinstance(state.model.extras["features"], torch.nn.Parameter)
    assert not isinstance(state.model.extras["generation"], torch.nn.Parameter)  # no lr: carried along
    stat = state.add_statistic("seen", fill=-1.0)
    stat += 2.0
    state.append(model.subset(torch.tensor([0, 1])))
    assert len(state) == 7
    torch.testing.assert_close(state.statistics["seen"], torch.tensor([1.0] * 5 + [-1.0] * 2))
    torch.testing.assert_close(state.model.extras["generation"], torch.tensor([0.0, 1, 2, 3, 4, 0, 1]))
    state.keep(torch.tensor([True, False, True, False, True, True, False]))
    torch.testing.assert_close(state.model.extras["generation"], torch.tensor([0.0, 2, 4, 0]))
    assert state.statistics["seen"].shape == (4,)
    # the optimiser still steps the features
    state.model.extras["features"].grad = torch.ones(4, 16)
    before = state.model.extras["features"].detach().clone()
    state.step()
    assert bool((state.model.extras["features"] < before).all())
    group = next(g for g in state.optimizer.param_groups if g["name"] == "features")
    assert group["params"][0] is state.model.extras["features"]
    # new Gaussians without the model's extras are refused, and nothing is edited
    bare = GaussianModel(**{name: getattr(model, name)[:2] for name in GaussianModel.PARAM_NAMES})
    with pytest.raises(ValueError, match=r"extras \[\] differ from the model's \['features', 'generation'\]"):
        state.append(bare)
    assert len(state) == 4


def test_bad_extras_are_refused(tmp_path):
    model = model_with_extras()
    with pytest.raises(ValueError, match="extra 'bad'"):
        model.set("bad", torch.zeros(4))
    with pytest.raises(ValueError, match="_<digits>"):
        model.set("level_2", torch.zeros(5))


def test_activations_do_not_depend_on_the_thread_count():
    # torch's vector and scalar sigmoid differ in the last bit for some inputs, and which elements
    # get the scalar one depends on how the elements are shared among threads
    gen = torch.Generator().manual_seed(0)
    logits = torch.randn(70060, generator=gen) * 4.0
    log_scales = torch.randn(70060, 2, generator=gen)
    before = torch.get_num_threads()
    try:
        for n in range(70000, 70060, 3):
            model = init_random(n, np.zeros(3), np.ones(3), sh_degree=0, seed=0)
            model.opacity_logits = logits[:n].clone()
            model.log_scales = log_scales[:n].clone()
            torch.set_num_threads(1)
            one = (model.opacities, model.scales)
            torch.set_num_threads(2)
            two = (model.opacities, model.scales)
            assert torch.get_num_threads() == 2  # restored
            assert all(torch.equal(a, b) for a, b in zip(one, two)), n
    finally:
        torch.set_num_threads(before)


def test_init_scales_log_runs_on_one_torch_thread(monkeypatch):
    """The initial log-scales come from torch's log on one thread (a two-thread log once gave the
    second half other values, docs/history/performance.md, "Run to run"), and the caller's setting stays."""
    calls = []
    real_log = torch.log

    def recording_log(t, *args, **kwargs):
        calls.append((t.numel(), torch.get_num_threads()))
        return real_log(t, *args, **kwargs)

    before = torch.get_num_threads()
    gen = torch.Generator().manual_seed(0)
    pts = torch.rand(40000, 3, generator=gen)  # more than torch's grain size: it would split the log
    try:
        torch.set_num_threads(2)
        monkeypatch.setattr(torch, "log", recording_log)
        model = init_from_points(pts, np.full((40000, 3), 128, np.uint8), sh_degree=0, seed=0)
        assert torch.get_num_threads() == 2
    finally:
        monkeypatch.undo()
        torch.set_num_threads(before)
    assert (40000, 1) in calls and all(threads == 1 for _, threads in calls)
    torch.testing.assert_close(model.log_scales[:, 0], torch.log(nearest_neighbour_scales(pts)), rtol=0, atol=0)
