"""trace3d.pointcloud: PLY point clouds and Sim(3) (Umeyama) alignment."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from trace3d.errors import Trace3DError
from trace3d.pointcloud import Sim3, align_cameras, read_points_ply, rotation_angle_deg, umeyama, write_points_ply


def random_sim3(rng: np.random.Generator) -> Sim3:
    return Sim3(
        scale=float(np.exp(rng.uniform(-1.5, 1.5))),
        rotation=Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix(),
        translation=rng.normal(scale=5.0, size=3),
    )


# ----------------------------------------------------------------------------------------------
# PLY
# ----------------------------------------------------------------------------------------------


class TestPly:
    def test_round_trip(self, tmp_path):
        rng = np.random.default_rng(0)
        xyz = rng.normal(size=(1000, 3)) * 10
        rgb = rng.integers(0, 256, size=(1000, 3), dtype=np.uint8)
        path = tmp_path / "points3D.ply"
        write_points_ply(path, xyz, rgb)
        xyz2, rgb2 = read_points_ply(path)
        np.testing.assert_array_equal(xyz2, xyz.astype(np.float32).astype(np.float64))
        np.testing.assert_array_equal(rgb2, rgb)
        header = path.read_bytes()[:300].decode("ascii", errors="replace")
        assert "format binary_little_endian 1.0" in header and "property uchar red" in header
        assert path.stat().st_size == header.index("end_header\n") + len("end_header\n") + 1000 * 15

    def test_empty_and_default_colour(self, tmp_path):
        write_points_ply(tmp_path / "empty.ply", np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint8))
        xyz, rgb = read_points_ply(tmp_path / "empty.ply")
        assert xyz.shape == (0, 3) and rgb.shape == (0, 3)
        write_points_ply(tmp_path / "grey.ply", np.ones((2, 3)))
        assert (read_points_ply(tmp_path / "grey.ply")[1] == 128).all()

    def test_reads_ascii_and_big_endian_with_extra_properties(self, tmp_path):
        ascii_ply = (
            "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
            "property float nx\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
            "element face 0\nproperty list uchar int vertex_indices\nend_header\n"
            "1 2 3 0 10 20 30\n-1 -2 -3.5 1 255 0 7\n"
        )
        (tmp_path / "a.ply").write_text(ascii_ply)
        xyz, rgb = read_points_ply(tmp_path / "a.ply")
        np.testing.assert_array_equal(xyz, [[1, 2, 3], [-1, -2, -3.5]])
        np.testing.assert_array_equal(rgb, [[10, 20, 30], [255, 0, 7]])

        data = np.array([(1.5, 2.0, -3.0, 9, 1, 2, 3)],
                        dtype=[("x", ">f8"), ("y", ">f8"), ("z", ">f8"), ("id", ">i4"),
                               ("red", "u1"), ("green", "u1"), ("blue", "u1")])  # fmt: skip
        header = (
            "ply\nformat binary_big_endian 1.0\nelement vertex 1\nproperty double x\nproperty double y\n"
            "property double z\nproperty int id\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
            "end_header\n"
        )
        (tmp_path / "b.ply").write_bytes(header.encode() + data.tobytes())
        xyz, rgb = read_points_ply(tmp_path / "b.ply")
        np.testing.assert_array_equal(xyz, [[1.5, 2.0, -3.0]])
        np.testing.assert_array_equal(rgb, [[1, 2, 3]])

    def test_bad_files_name_the_file(self, tmp_path):
        path = tmp_path / "bad.ply"
        path.write_text("not a ply\n")
        with pytest.raises(Trace3DError, match=f"{path}: not a PLY file"):
            read_points_ply(path)
        write_points_ply(path, np.zeros((10, 3)))
        path.write_bytes(path.read_bytes()[:-5])
        with pytest.raises(Trace3DError, match="truncated"):
            read_points_ply(path)
        path.write_text("ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nend_header\n")
        with pytest.raises(Trace3DError, match=r"lacks the coordinate\(s\) \['y', 'z'\]"):
            read_points_ply(path)
        with pytest.raises(Trace3DError, match="does not exist"):
            read_points_ply(tmp_path / "nowhere.ply")

    def test_write_checks_inputs(self, tmp_path):
        with pytest.raises(ValueError, match="uint8"):
            write_points_ply(tmp_path / "x.ply", np.zeros((2, 3)), np.zeros((2, 3)))
        with pytest.raises(ValueError, match=r"\[P, 3\]"):
            write_points_ply(tmp_path / "x.ply", np.zeros((2, 2)))
        with pytest.raises(ValueError, match="non-finite"):
            write_points_ply(tmp_path / "x.ply", np.full((2, 3), np.nan))
        assert not (tmp_path / "x.ply").exists()


# ----------------------------------------------------------------------------------------------
# Sim(3)
# ----------------------------------------------------------------------------------------------


def _reference_fit(source: np.ndarray, target: np.ndarray, start: Sim3) -> tuple[Sim3, float]:
    """Slow twin of :func:`umeyama`: generic nonlinear least squares over (log scale, rotation vector, t)."""

    def residuals(x):
        sim = Sim3(np.exp(x[0]), Rotation.from_rotvec(x[1:4]).as_matrix(), x[4:])
        return (sim.apply(source) - target).ravel()

    x0 = np.concatenate([[np.log(start.scale)], Rotation.from_matrix(start.rotation).as_rotvec(), start.translation])
    fit = least_squares(residuals, x0, xtol=1e-14, ftol=1e-14, gtol=1e-14)
    sim = Sim3(np.exp(fit.x[0]), Rotation.from_rotvec(fit.x[1:4]).as_matrix(), fit.x[4:])
    return sim, float((fit.fun**2).sum())


class TestUmeyama:
    @pytest.mark.parametrize("seed", range(5))
    def test_recovers_known_similarity(self, seed):
        rng = np.random.default_rng(seed)
        truth = random_sim3(rng)
        source = rng.normal(size=(20, 3))
        fit = umeyama(source, truth.apply(source))
        assert fit.scale == pytest.approx(truth.scale, rel=1e-10)
        np.testing.assert_allclose(fit.rotation, truth.rotation, atol=1e-10)
        np.testing.assert_allclose(fit.translation, truth.translation, atol=1e-9)
        assert np.linalg.det(fit.rotation) == pytest.approx(1.0)

    def test_minimal_and_planar_sets(self):
        rng = np.random.default_rng(7)
        truth = random_sim3(rng)
        source = np.array([[0.0, 0, 0], [1, 0, 0], [0, 2, 0]])  # 3 points in a plane: SVD has a zero singular value
        fit = umeyama(source, truth.apply(source))
        np.testing.assert_allclose(fit.apply(source), truth.apply(source), atol=1e-10)
        assert np.linalg.det(fit.rotation) == pytest.approx(1.0)

    def test_never_returns_a_reflection(self):
        rng = np.random.default_rng(3)
        source = rng.normal(size=(30, 3))
        mirrored = source * np.array([1.0, 1.0, -1.0])  # best orthogonal map is a reflection
        fit = umeyama(source, mirrored)
        assert np.linalg.det(fit.rotation) == pytest.approx(1.0)

    @pytest.mark.parametrize("seed", range(3))
    def test_matches_generic_least_squares_on_noisy_data(self, seed):
        rng = np.random.default_rng(100 + seed)
        truth = random_sim3(rng)
        source = rng.normal(size=(40, 3))
        target = truth.apply(source) + rng.normal(scale=0.3 * truth.scale, size=(40, 3))
        fit = umeyama(source, target)
        cost = float(((fit.apply(source) - target) ** 2).sum())
        reference, reference_cost = _reference_fit(source, target, truth)
        assert cost <= reference_cost * (1 + 1e-9) + 1e-12
        assert fit.scale == pytest.approx(reference.scale, rel=1e-6)
        assert rotation_angle_deg(fit.rotation, reference.rotation) < 1e-4
        np.testing.assert_allclose(fit.translation, reference.translation, atol=1e-5 * truth.scale + 1e-6)

    def test_rigid_fit_keeps_unit_scale(self):
        rng = np.random.default_rng(11)
        truth = Sim3(1.0, Rotation.random(random_state=1).as_matrix(), rng.normal(size=3))
        source = rng.normal(size=(10, 3))
        fit = umeyama(source, truth.apply(source), with_scale=False)
        assert fit.scale == 1.0
        np.testing.assert_allclose(fit.rotation, truth.rotation, atol=1e-10)

    def test_degenerate_inputs(self):
        with pytest.raises(Trace3DError, match="at least 3"):
            umeyama(np.zeros((2, 3)), np.zeros((2, 3)))
        with pytest.raises(Trace3DError, match="coincide"):
            umeyama(np.ones((5, 3)), np.zeros((5, 3)))
        line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
        with pytest.raises(Trace3DError, match="collinear"):
            umeyama(line, line)


class TestSim3:
    def test_inverse_and_matrix(self):
        rng = np.random.default_rng(5)
        sim = random_sim3(rng)
        points = rng.normal(size=(7, 3))
        np.testing.assert_allclose(sim.inverse().apply(sim.apply(points)), points, atol=1e-10)
        homogeneous = np.concatenate([points, np.ones((7, 1))], axis=1) @ sim.matrix.T
        np.testing.assert_allclose(homogeneous[:, :3], sim.apply(points), atol=1e-10)

    def test_transformed_camera_sees_the_same_image(self):
        rng = np.random.default_rng(9)
        sim = random_sim3(rng)
        w2c = np.eye(4)
        w2c[:3, :3] = Rotation.random(random_state=2).as_matrix()
        w2c[:3, 3] = rng.normal(size=3)
        points_cam = np.concatenate([rng.normal(size=(12, 3)) + [0, 0, 5], np.ones((12, 1))], 1)
        points = (np.linalg.inv(w2c) @ points_cam.T).T[:, :3]
        new_w2c = sim.transform_world_to_camera(w2c)
        before = points @ w2c[:3, :3].T + w2c[:3, 3]
        after = sim.apply(points) @ new_w2c[:3, :3].T + new_w2c[:3, 3]
        np.testing.assert_allclose(after, sim.scale * before, atol=1e-9)  # same rays, depths scaled
        np.testing.assert_allclose(new_w2c[:3, :3] @ new_w2c[:3, :3].T, np.eye(3), atol=1e-12)

    def test_rotation_angle(self):
        a = Rotation.from_rotvec([0.0, 0.0, np.radians(30.0)]).as_matrix()
        assert rotation_angle_deg(a, np.eye(3)) == pytest.approx(30.0)
        assert rotation_angle_deg(a, a) == pytest.approx(0.0, abs=1e-6)


def random_cameras(rng: np.random.Generator, count: int, radius: float = 2.0) -> np.ndarray:
    """[L, 4, 4] world_to_camera poses with random orientations and centres on a noisy circle."""
    poses = np.tile(np.eye(4), (count, 1, 1))
    for i in range(count):
        rot = Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
        angle = 2 * np.pi * i / count
        centre = radius * np.array([np.cos(angle), np.sin(angle), 0.1 * rng.normal()])
        poses[i, :3, :3] = rot
        poses[i, :3, 3] = -rot @ centre
    return poses


class TestAlignCameras:
    @pytest.mark.parametrize("method", ["poses", "centers"])
    def test_recovers_known_similarity(self, method):
        rng = np.random.default_rng(21)
        truth = random_sim3(rng)
        source = random_cameras(rng, 8)
        target = np.stack([truth.transform_world_to_camera(w) for w in source])
        fit = align_cameras(source, target, method)
        assert fit.scale == pytest.approx(truth.scale, rel=1e-9)
        np.testing.assert_allclose(fit.rotation, truth.rotation, atol=1e-9)
        np.testing.assert_allclose(fit.translation, truth.translation, atol=1e-8 * max(1.0, truth.scale))

    def test_orientations_fix_the_rotation_of_a_short_noisy_loop(self):
        rng = np.random.default_rng(5)
        truth = random_sim3(rng)
        source = random_cameras(rng, 36, radius=0.5)
        target = np.stack([truth.transform_world_to_camera(w) for w in source])
        # perturb the source centres by 1 cm, keep the orientations exact
        noisy = source.copy()
        for pose in noisy:
            centre = -pose[:3, :3].T @ pose[:3, 3] + rng.normal(scale=0.01, size=3)
            pose[:3, 3] = -pose[:3, :3] @ centre
        by_poses = align_cameras(noisy, target, "poses")
        by_centres = align_cameras(noisy, target, "centers")
        assert rotation_angle_deg(by_poses.rotation, truth.rotation) < 1e-5  # arccos resolution
        assert rotation_angle_deg(by_centres.rotation, truth.rotation) > 0.1
        assert by_poses.scale == pytest.approx(truth.scale, rel=0.02)

    def test_degenerate_cameras(self):
        poses = np.tile(np.eye(4), (4, 1, 1))
        with pytest.raises(Trace3DError, match="coincide"):
            align_cameras(poses, poses, "poses")
        with pytest.raises(ValueError, match="unknown alignment method"):
            align_cameras(random_cameras(np.random.default_rng(0), 4), random_cameras(np.random.default_rng(1), 4),
                          "icp")
