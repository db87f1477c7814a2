"""Tests of trace3d.losses and trace3d.training: losses, density control, the loop and the step."""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest
import torch

from trace3d.errors import ConfigError, Trace3DError
from trace3d.gaussians import GaussianModel, init_from_points
from trace3d.geometry import depth_to_normal, depth_to_points
from trace3d.losses import _ssim_map_reference, normal_consistency_loss, photometric_loss, psnr, ssim, ssim_map
from trace3d.params import from_mapping
from trace3d.pointcloud import write_points_ply
from trace3d.scene import Camera, Scene, write_cameras, write_frame
from trace3d.training import (
    GaussianOptimizer,
    densify_and_prune,
    learning_rates,
    TrainingDiverged,
    TrainParams,
    evaluate_views,
    exponential_lr,
    failed_dir_for,
    fit,
    points_extent,
    run_gaussians,
    scene_extent,
    split_gaussians,
)

@pytest.fixture(autouse=True)
def single_thread():
    """Tiny scenes run fastest on one thread, and stay fast on a busy shared machine (parallel
    regions of two threads stall whenever one of them is descheduled)."""
    import numba

    torch_threads, numba_threads = torch.get_num_threads(), numba.get_num_threads()
    torch.set_num_threads(1)
    numba.set_num_threads(1)
    yield
    torch.set_num_threads(torch_threads)
    numba.set_num_threads(numba_threads)


# ----------------------------------------------------------------------------------------------
# A tiny scene: a smoothly textured plane z = 3 seen by cameras on a small circle (exact images)
# ----------------------------------------------------------------------------------------------

PLANE_Z = 3.0


def look_at(center: np.ndarray, target: np.ndarray) -> np.ndarray:
    z = target - center
    z = z / np.linalg.norm(z)
    x = np.cross(np.array([0.0, 1.0, 0.0]), z)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    w2c = np.eye(4)
    w2c[:3, :3] = np.stack([x, y, z])
    w2c[:3, 3] = -w2c[:3, :3] @ center
    return w2c


def texture(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return np.stack(
        [
            0.5 + 0.35 * np.sin(3 * x + 0.5) * np.cos(2 * y),
            0.5 + 0.35 * np.cos(2.5 * x - 1.5 * y),
            0.45 + 0.3 * np.sin(4 * y + x),
        ],
        axis=-1,
    )


def plane_views(count: int, width: int = 32, height: int = 24, split=lambda i: "train"):
    """``count`` cameras looking at the plane and their exact images [H, W, 3] float."""
    K = np.array([[30.0, 0, width / 2], [0, 30.0, height / 2], [0, 0, 1]])
    cameras, images = [], []
    xs, ys = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    rays_cam = np.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], np.ones_like(xs)], -1)
    for i in range(count):
        angle = 2 * math.pi * i / count
        center = np.array([0.4 * math.cos(angle), 0.3 * math.sin(angle), 0.0])
        cam = Camera(f"v{i:02d}", split(i), width, height, K, look_at(center, np.array([0.0, 0.0, PLANE_Z])))
        rays = rays_cam @ cam.rotation  # camera -> world directions (R^T d)
        t = (PLANE_Z - cam.center[2]) / rays[..., 2]
        hits = cam.center + rays * t[..., None]
        cameras.append(cam)
        images.append(torch.tensor(texture(hits[..., 0], hits[..., 1]), dtype=torch.float32))
    return cameras, images


def plane_points(count: int = 300, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts = np.concatenate([rng.uniform(-2, 2, (count, 2)), np.full((count, 1), PLANE_Z)], 1)
    return pts + rng.normal(0, 0.05, (count, 3))


def tiny_params(**overrides) -> TrainParams:
    values = dict(
        schedule_scale=1.0, iterations=200, densify_from=50, densify_until=150, densify_interval=25,
        opacity_reset_interval=1000, normal_from=100, sh_degree_interval=50, sh_degree=1, device="cpu",
        densify_grad_threshold=0.0002,
    )
    values.update(overrides)
    return TrainParams(**values)


# ----------------------------------------------------------------------------------------------
# Losses
# ----------------------------------------------------------------------------------------------


class TestSSIM:
    def test_identical_is_one_and_bounded(self):
        g = torch.Generator().manual_seed(0)
        a = torch.rand(20, 24, 3, generator=g)
        assert float(ssim(a, a)) == pytest.approx(1.0, abs=1e-6)
        b = torch.rand(20, 24, 3, generator=g)
        assert -1.0 <= float(ssim(a, b)) < 0.5

    def test_matches_skimage_away_from_the_border(self):
        from skimage.metrics import structural_similarity

        rng = np.random.default_rng(1)
        a = rng.random((30, 34, 3))
        b = np.clip(a + rng.normal(0, 0.1, a.shape), 0, 1)
        _, full = structural_similarity(a, b, channel_axis=2, gaussian_weights=True, sigma=1.5,
                                        use_sample_covariance=False, data_range=1.0, full=True)
        ours = ssim_map(torch.tensor(a), torch.tensor(b))[0].permute(1, 2, 0).numpy()
        np.testing.assert_allclose(ours[5:-5, 5:-5], full[5:-5, 5:-5], atol=1e-6)

    def test_separable_matches_2d_window_reference_with_gradients(self):
        g = torch.Generator().manual_seed(2)
        a = torch.rand(2, 19, 23, 3, generator=g, dtype=torch.float64, requires_grad=True)
        b = torch.rand(2, 19, 23, 3, generator=g, dtype=torch.float64)
        fast = ssim_map(a, b)
        slow = _ssim_map_reference(a, b)
        torch.testing.assert_close(fast, slow, rtol=1e-10, atol=1e-12)
        upstream = torch.rand(fast.shape, generator=g, dtype=torch.float64)
        (grad_fast,) = torch.autograd.grad((fast * upstream).sum(), a)
        (grad_slow,) = torch.autograd.grad((slow * upstream).sum(), a)
        torch.testing.assert_close(grad_fast, grad_slow, rtol=1e-9, atol=1e-12)

    def test_gradcheck(self):
        g = torch.Generator().manual_seed(2)
        a = torch.rand(5, 6, 1, generator=g, dtype=torch.float64, requires_grad=True)
        b = torch.rand(5, 6, 1, generator=g, dtype=torch.float64)
        assert torch.autograd.gradcheck(lambda x: ssim(x, b), (a,))

    @pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-6)])
    @pytest.mark.parametrize("size", [(37, 52, 3), (7, 9, 3), (4, 3, 1), (11, 30, 5)])
    def test_fused_kernel_matches_torch_twin_with_gradients(self, dtype, tol, size):
        """The numba SSIM of the training loss against the torch ssim: value and image gradient,
        images smaller than the window included."""
        from trace3d.loss_kernels import fused_ssim

        g = torch.Generator().manual_seed(sum(size))
        a = torch.rand(size, generator=g, dtype=dtype).requires_grad_()
        b = (a.detach() * 0.6 + 0.4 * torch.rand(size, generator=g, dtype=dtype)).clamp(0, 1)
        fused, twin = fused_ssim(a, b), ssim(a, b)
        assert fused.dtype == dtype
        assert float(fused) == pytest.approx(float(twin), abs=tol * 10)
        (g_fused,) = torch.autograd.grad(fused * 3.0, a)
        (g_twin,) = torch.autograd.grad(twin * 3.0, a)
        assert float((g_fused - g_twin).abs().max()) <= tol * float(g_twin.abs().max()) * 10

    @pytest.mark.parametrize("dtype", [np.float32, np.float64])
    @pytest.mark.parametrize("size", [(3, 40, 31), (2, 11, 11), (1, 12, 5), (2, 4, 3), (1, 1, 17)])
    def test_blur_equals_the_tap_by_tap_sum_bit_for_bit(self, dtype, size):
        """The SSIM's separable blur (per-column taps on interior rows, per-tap passes elsewhere)
        against numpy adding the taps one by one in k order, rows and columns outside the image
        skipped: the same sum in the same order, so equal to the bit."""
        from trace3d.loss_kernels import _blur, _window

        rng = np.random.default_rng(sum(size))
        src = rng.standard_normal(size).astype(dtype)
        g = _window(dtype)
        m, h, w = size
        r = len(g) // 2
        tmp = np.zeros_like(src)
        for k in range(len(g)):
            lo, hi = max(0, r - k), min(h, h + r - k)  # output rows whose tap row y + k - r is inside
            if lo < hi:
                tmp[:, lo:hi] += g[k] * src[:, lo + k - r:hi + k - r]
        want = np.zeros_like(src)
        for k in range(len(g)):
            lo, hi = max(0, r - k), min(w, w + r - k)
            if lo < hi:
                want[:, :, lo:hi] += g[k] * tmp[:, :, lo + k - r:hi + k - r]
        got = np.empty_like(src)
        _blur(src, g, got)
        assert np.array_equal(got.view(np.uint8), want.view(np.uint8))

    def test_fused_kernel_gradcheck_and_where_it_applies(self):
        from trace3d.loss_kernels import fused_ssim, fused_ssim_applies
        from trace3d.render.glue_kernels import set_fused

        g = torch.Generator().manual_seed(3)
        a = torch.rand(6, 13, 2, generator=g, dtype=torch.float64, requires_grad=True)
        b = torch.rand(6, 13, 2, generator=g, dtype=torch.float64)
        assert torch.autograd.gradcheck(lambda x: fused_ssim(x, b), (a,))
        assert fused_ssim_applies(a, b)
        assert not fused_ssim_applies(a[None], b[None])  # batches take the torch path
        assert not fused_ssim_applies(a, b.float())
        with pytest.raises(ValueError, match="fused_ssim"):
            fused_ssim(a[None], b[None])
        set_fused(False)
        try:
            assert not fused_ssim_applies(a, b)
        finally:
            set_fused(True)

    def test_fused_ssim_reuses_the_target_statistics_only_while_valid(self):
        """The blurred target statistics are cached per target tensor: a hit gives the uncached value
        and gradient bit for bit, an in-place change of the target is noticed, and the cache stays
        within its byte budget (dropping the least recently used)."""
        from trace3d.loss_kernels import _target_cache, _TargetStats, fused_ssim

        g = torch.Generator().manual_seed(5)
        b = torch.rand(20, 30, 3, generator=g)

        def value_and_grad(image, target):
            x = image.clone().requires_grad_()
            s = fused_ssim(x, target)
            (grad,) = torch.autograd.grad(s, x)
            return s, grad

        a1, a2 = torch.rand(20, 30, 3, generator=g), torch.rand(20, 30, 3, generator=g)
        value_and_grad(a1, b)  # fills the cache for b
        assert id(b) in _target_cache.entries
        hit, fresh = value_and_grad(a2, b), value_and_grad(a2, b.clone())
        assert torch.equal(hit[0], fresh[0]) and torch.equal(hit[1], fresh[1])
        b.mul_(0.5)  # the cached statistics are stale now
        changed, fresh = value_and_grad(a2, b), value_and_grad(a2, b.clone())
        assert torch.equal(changed[0], fresh[0]) and torch.equal(changed[1], fresh[1])
        assert not torch.equal(changed[0], hit[0])
        small = _TargetStats(max_bytes=2 * 20 * 30 * 3 * 4 + 1)  # room for one target's statistics
        from trace3d.loss_kernels import _window

        y1, y2 = a1.numpy(), a2.numpy()
        small.get(a1, y1, _window(np.float32))
        small.get(a2, y2, _window(np.float32))
        assert list(small.entries) == [id(a2)] and small.bytes <= small.max_bytes

    @pytest.mark.parametrize("size", [(37, 52, 3), (6, 9, 3), (120, 160, 3)])
    def test_fused_photometric_terms_equal_the_torch_composition_bit_for_bit(self, size):
        """photometric_terms (the training loop's call) against photometric_loss + psnr, the path the
        loop took before: loss, L1, SSIM, PSNR and the image gradient, exactly; pixels outside [0, 1]
        (the PSNR clamps) and equal to the target (sgn 0) included; also with the L1 or the SSIM
        weight alone."""
        from trace3d.losses import photometric_terms

        g = torch.Generator().manual_seed(size[0])
        target = torch.rand(size, generator=g)
        image = (target * 0.7 + 0.4 * torch.rand(size, generator=g) - 0.1)
        image[0, :3] = target[0, :3]
        for lam in (0.2, 0.0, 1.0):
            x1, x2 = image.clone().requires_grad_(), image.clone().requires_grad_()
            loss, l1, s, p = photometric_terms(x1, target, lam)
            loss_t, l1_t, s_t = photometric_loss(x2, target, lam)
            p_t = psnr(x2.detach().clamp(0, 1), target, exact=False)
            assert torch.equal(loss, loss_t) and torch.equal(l1, l1_t) and torch.equal(s, s_t) and p == p_t
            (g1,) = torch.autograd.grad(loss * 1.7, x1)
            (g2,) = torch.autograd.grad(loss_t * 1.7, x2)
            assert torch.equal(g1, g2), lam
            assert bool((g1 != 0).any())
        from trace3d.loss_kernels import fused_photometric

        with pytest.raises(ValueError, match="fused_photometric: needs"):
            fused_photometric(image.double(), target.double())

    def test_photometric_loss_weights(self):
        a = torch.zeros(16, 16, 3)
        b = torch.full((16, 16, 3), 0.5)
        loss, l1, s = photometric_loss(a, b, lambda_dssim=0.2)
        assert float(l1) == pytest.approx(0.5)
        assert float(loss) == pytest.approx(0.8 * 0.5 + 0.2 * (1 - float(s)))
        assert psnr(a, b) == pytest.approx(-10 * math.log10(0.25))


class TestDepthNormal:
    K = np.array([[20.0, 0, 10.0], [0, 22.0, 8.0], [0, 0, 1]])

    def plane_depth(self, normal: np.ndarray, offset: float, height=16, width=20) -> torch.Tensor:
        """Depth (camera z) of the plane n . X = offset seen by camera K at the origin."""
        xs, ys = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
        rays = np.stack([(xs - self.K[0, 2]) / self.K[0, 0], (ys - self.K[1, 2]) / self.K[1, 1], np.ones_like(xs)], -1)
        return torch.tensor(offset / (rays @ normal), dtype=torch.float64)

    def test_points_reproject_to_pixel_centres(self):
        depth = torch.full((6, 7), 2.5, dtype=torch.float64)
        pts = depth_to_points(depth, self.K)
        uv = (pts @ torch.tensor(self.K).T)
        uv = uv[..., :2] / uv[..., 2:]
        assert torch.allclose(uv[2, 3], torch.tensor([3.5, 2.5], dtype=torch.float64))

    def test_tilted_plane_normal_faces_camera(self):
        normal = np.array([0.3, -0.2, -1.0])
        normal /= np.linalg.norm(normal)  # facing the camera (negative z)
        depth = self.plane_depth(normal, offset=-3.0)
        assert (depth > 0).all()
        got = depth_to_normal(depth, self.K)
        assert torch.allclose(got[1:-1, 1:-1], torch.tensor(normal).expand(14, 18, 3), atol=1e-9)
        assert (got[0] == 0).all() and (got[:, -1] == 0).all()

    def test_normal_consistency_zero_when_aligned(self):
        n = torch.nn.functional.normalize(torch.randn(5, 6, 3), dim=-1)
        alpha = torch.ones(5, 6)
        assert float(normal_consistency_loss(n, n, alpha)) == pytest.approx(0.0, abs=1e-6)
        assert float(normal_consistency_loss(n, -n, alpha)) == pytest.approx(2.0, abs=1e-6)

    @staticmethod
    def _normal_inputs(h, w, dtype, seed=0):
        g = torch.Generator().manual_seed(seed)
        depth = (torch.rand(h, w, generator=g, dtype=dtype) * 0.3 + 2.0).requires_grad_()
        rn = torch.nn.functional.normalize(torch.randn(h, w, 3, generator=g, dtype=dtype), dim=-1).requires_grad_()
        alpha = torch.rand(h, w, generator=g, dtype=dtype)
        K = np.array([[50.0, 0.4, w / 2], [0, 48.0, h / 2], [0, 0, 1]])  # with skew
        return rn, depth, alpha, K

    @pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
    @pytest.mark.parametrize("size", [(23, 31), (3, 3), (2, 6), (6, 1)])
    def test_fused_normal_consistency_matches_torch_twin(self, dtype, tol, size):
        """The numba term against depth_to_normal + normal_consistency_loss: value and both gradients."""
        from trace3d.loss_kernels import fused_normal_consistency

        rn, depth, alpha, K = self._normal_inputs(*size, dtype)
        fused = fused_normal_consistency(rn, depth, alpha, K)
        twin = normal_consistency_loss(rn, depth_to_normal(depth, K), alpha)
        assert fused.dtype == dtype and float(fused) == pytest.approx(float(twin), abs=tol * 10)
        g_fused = torch.autograd.grad(fused * 1.7, (rn, depth))
        g_twin = torch.autograd.grad(twin * 1.7, (rn, depth))
        for a, b in zip(g_fused, g_twin):
            assert a.dtype == dtype
            assert float((a - b).abs().max()) <= tol * max(float(b.abs().max()), 1e-3) * 10

    def test_fused_normal_consistency_gradcheck_and_dispatch(self):
        from trace3d.losses import depth_normal_consistency
        from trace3d.loss_kernels import fused_normal_consistency
        from trace3d.render.glue_kernels import set_fused

        rn, depth, alpha, K = self._normal_inputs(5, 6, torch.float64, seed=4)
        assert torch.autograd.gradcheck(lambda n, d: fused_normal_consistency(n, d, alpha, K), (rn, depth))
        set_fused(False)
        try:
            twin = depth_normal_consistency(rn, depth, alpha, K)  # the torch composition
        finally:
            set_fused(True)
        assert float(depth_normal_consistency(rn, depth, alpha, K)) == pytest.approx(float(twin), abs=1e-12)
        with pytest.raises(ValueError, match="fused_normal_consistency"):
            fused_normal_consistency(rn[None], depth, alpha, K)


# ----------------------------------------------------------------------------------------------
# Schedule and parameters
# ----------------------------------------------------------------------------------------------


def test_exponential_lr_endpoints_and_monotone():
    assert exponential_lr(0, 1.6e-4, 1.6e-6, 100) == pytest.approx(1.6e-4)
    assert exponential_lr(100, 1.6e-4, 1.6e-6, 100) == pytest.approx(1.6e-6)
    assert exponential_lr(50, 1.6e-4, 1.6e-6, 100) == pytest.approx(1.6e-5)
    assert exponential_lr(500, 1.6e-4, 1.6e-6, 100) == pytest.approx(1.6e-6)


def test_schedule_scaling_and_reference_defaults():
    ref = TrainParams.reference_2dgs().schedule()
    assert ref == {"iterations": 30000, "densify_from": 500, "densify_until": 15000, "densify_interval": 100,
                   "opacity_reset_interval": 3000, "sh_degree_interval": 1000, "normal_from": 7000,
                   "distortion_from": 3000, "checkpoint_interval": 1000}
    assert TrainParams.reference_2dgs().densify_grad_threshold == 0.0002
    half = TrainParams(schedule_scale=0.5).schedule()
    assert half["iterations"] == 15000 and half["densify_interval"] == 50
    assert TrainParams(schedule_scale=1e-4).scaled("densify_interval") == 1  # never 0


def test_params_validation():
    with pytest.raises(ConfigError, match="unknown"):
        from_mapping(TrainParams, {"iteratons": 5})
    with pytest.raises(ConfigError, match="sh_degree"):
        from_mapping(TrainParams, {"sh_degree": 4})
    with pytest.raises(ConfigError):
        from_mapping(TrainParams, {"schedule_scale": 0})
    p = from_mapping(TrainParams, {"iterations": 7, "background": [1, 1, 1]})
    assert p.iterations == 7 and p.background == [1.0, 1.0, 1.0]


def test_scene_extent():
    cams = [Camera(f"c{i}", "train", 4, 4, np.eye(3), np.eye(4)) for i in range(2)]
    cams[1].world_to_camera[0, 3] = -2.0  # centre at x = 2
    assert scene_extent(cams) == pytest.approx(1.1)
    assert scene_extent(cams[:1]) == 1.0
    # inside-out: points on a sphere of radius 3 around the camera centroid (1, 0, 0)
    dirs = torch.nn.functional.normalize(torch.randn(501, 3, generator=torch.Generator().manual_seed(0)), dim=-1)
    points = dirs * 3.0 + torch.tensor([1.0, 0.0, 0.0])
    assert points_extent(points, cams) == pytest.approx(3.3, rel=1e-5)


# ----------------------------------------------------------------------------------------------
# Density control on constructed cases
# ----------------------------------------------------------------------------------------------


def constructed_model() -> GaussianModel:
    """Six Gaussians, ordered: small-hot, large-hot, cold, transparent, huge, ordinary."""
    n = 6
    scales = torch.tensor([[0.005, 0.002], [0.05, 0.03], [0.005, 0.005], [0.005, 0.005], [0.5, 0.1], [0.02, 0.02]])
    opac = torch.tensor([0.5, 0.5, 0.5, 0.01, 0.5, 0.5])
    return GaussianModel(
        means=torch.arange(n, dtype=torch.float32)[:, None] * torch.tensor([1.0, 0.0, 0.0]),
        quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
        log_scales=scales.log(),
        opacity_logits=torch.logit(opac),
        sh_dc=torch.arange(n, dtype=torch.float32)[:, None, None].repeat(1, 1, 3),
        sh_rest=torch.zeros(n, 3, 3),
    )


def densify_stats(state: GaussianOptimizer) -> None:
    from trace3d.training.strategy import reset_stats

    reset_stats(state)


def constructed_state(**overrides) -> GaussianOptimizer:
    # extent 1: clone when max scale <= 0.01, split above; world-size prune above 0.1
    params = tiny_params(**overrides)
    state = GaussianOptimizer(constructed_model(), learning_rates(params, 1.0), params, extent=1.0)
    densify_stats(state)
    # mean NDC gradients: hot = 1e-3 (above 2e-4), cold = 1e-5; seen by 2 views
    hot = torch.tensor([1e-3, 1e-3, 1e-5, 1e-5, 1e-5, 1e-5])
    state.statistics["grad_accum"] = hot * 2
    state.statistics["grad_count"] = torch.full((6,), 2.0)
    state.statistics["max_radii"] = torch.tensor([1.0, 5.0, 1.0, 1.0, 4.0, 30.0])  # the last is too large on screen
    # give Adam moments we can follow through the edits
    for group in state.optimizer.param_groups:
        param = group["params"][0]
        state.optimizer.state[param] = {
            "step": torch.tensor(3.0),
            "exp_avg": torch.ones_like(param) * torch.arange(6).view(-1, *[1] * (param.ndim - 1)),
            "exp_avg_sq": torch.ones_like(param),
        }
    return state


def test_densify_clones_splits_and_prunes_without_size_limits():
    state = constructed_state()
    before = state.model.detached_copy()
    event = densify_and_prune(state, use_size_limits=False, generator=torch.Generator().manual_seed(0))
    assert event == {"cloned": 1, "split": 1, "pruned": 1, "total": 7}
    ids = state.model.sh_dc[:, 0, 0].round().long().tolist()
    # originals except the split (1) and the transparent (3) one, then the clone of 0, then 2 children of 1
    assert ids == [0, 2, 4, 5, 0, 1, 1]
    # clone: identical copy
    torch.testing.assert_close(state.model.means[4], before.means[0])
    torch.testing.assert_close(state.model.log_scales[4], before.log_scales[0])
    # split children: scales / (0.8 * 2), centres on the parent's disk (z offset 0: normal is +z)
    torch.testing.assert_close(state.model.scales[5:], before.scales[1].expand(2, 2) / 1.6)
    offsets = state.model.means[5:] - before.means[1]
    assert (offsets[:, 2].abs() < 1e-7).all() and (offsets[:, :2].abs() > 0).any()
    assert not torch.allclose(state.model.means[5], state.model.means[6])
    # Adam moments follow the survivors; new Gaussians start at zero
    exp_avg = state.optimizer.state[state.model.means]["exp_avg"][:, 0]
    torch.testing.assert_close(exp_avg, torch.tensor([0.0, 2, 4, 5, 0, 0, 0]))
    for group in state.optimizer.param_groups:
        assert group["params"][0] is getattr(state.model, group["name"])
        assert state.optimizer.state[group["params"][0]]["exp_avg"].shape == group["params"][0].shape
    # statistics are reset
    assert state.statistics["grad_accum"].shape == (7,) and float(state.statistics["grad_accum"].abs().sum()) == 0.0


def test_densify_size_limits_prune_huge_and_screen_large():
    state = constructed_state()
    event = densify_and_prune(state, use_size_limits=True, generator=torch.Generator().manual_seed(0))
    # also pruned: 4 (world size 0.5 > 0.1 x extent) and 5 (30 px > 20 px on screen)
    assert event["pruned"] == 3
    assert state.model.sh_dc[:, 0, 0].round().long().tolist() == [0, 2, 0, 1, 1]


def test_densify_respects_opacity_grace_and_growth_cap():
    state = constructed_state()
    event = densify_and_prune(state, use_size_limits=False, prune_by_opacity=False)
    assert event["pruned"] == 0 and event["total"] == 8
    capped = constructed_state(max_gaussians=7)  # room for one more: the clone (same gradient; cheaper first)
    event = densify_and_prune(capped, use_size_limits=False)
    assert event["cloned"] + event["split"] == 1 and len(capped) <= 7


def test_split_gaussians_statistics():
    parent = constructed_model().subset(torch.tensor([1]))
    parent.quats[:] = torch.tensor([0.7071068, 0.7071068, 0.0, 0.0])  # 90 deg about x: t_v -> z
    children = split_gaussians(parent, 2, torch.Generator().manual_seed(0))
    assert len(children) == 2
    many = split_gaussians(parent.map(lambda t: t.repeat(*([4000] + [1] * (t.ndim - 1)))), 2,
                           torch.Generator().manual_seed(1))
    offsets = many.means - parent.means
    std = offsets.std(dim=0)
    # s_u = 0.05 along x, s_v = 0.03 along t_v = z after the rotation, nothing along the normal (y)
    torch.testing.assert_close(std, torch.tensor([0.05, 0.0, 0.03]), atol=2e-3, rtol=0)


def test_reset_opacity_caps_and_zeroes_moments():
    state = constructed_state()
    state.reset_opacity(0.01)
    opacities = state.model.opacities.detach()
    assert float(opacities.max()) == pytest.approx(0.01, rel=1e-4)
    moments = state.optimizer.state[state.model.opacity_logits]
    assert float(moments["exp_avg"].abs().sum()) == 0.0


# ----------------------------------------------------------------------------------------------
# The loop
# ----------------------------------------------------------------------------------------------


def test_fit_reduces_loss_and_reaches_psnr_on_tiny_scene():
    cameras, images = plane_views(6)
    model = init_from_points(plane_points(), np.full((300, 3), 0.5), sh_degree=1, seed=0)
    params = tiny_params()
    before, _ = evaluate_views(model, cameras, images, 1, None)
    result = fit(model, cameras, images, params, progress=False)
    after, _ = evaluate_views(result.model, cameras, images, 1, None)
    assert result.history[-1]["loss"] < 0.5 * result.history[0]["loss"]
    assert np.mean([r["psnr"] for r in before]) < 15.0
    assert np.mean([r["psnr"] for r in after]) > 25.0
    assert any(e["split"] + e["cloned"] > 0 for e in result.densify_events)
    assert len(result.model) > 300
    # deterministic from the seed
    again = fit(model, cameras, images, tiny_params(iterations=20, densify=False), progress=False)
    again2 = fit(model, cameras, images, tiny_params(iterations=20, densify=False), progress=False)
    torch.testing.assert_close(again.model.means, again2.model.means)


def test_fit_divergence_raises_with_last_good_checkpoint():
    cameras, images = plane_views(4)
    images[2] = images[2].clone()
    images[2][3, 4, 1] = float("nan")  # the loss is NaN whenever view 2 is drawn
    model = init_from_points(plane_points(60), np.full((60, 3), 0.5), sh_degree=0, seed=0)
    with pytest.raises(TrainingDiverged, match="diverged") as info:
        fit(model, cameras, images, tiny_params(iterations=50, checkpoint_interval=1, densify=False, log_interval=1),
            progress=False)
    exc = info.value
    assert exc.iteration >= 1 and exc.checkpoint_iteration == exc.iteration - 1
    assert exc.checkpoint.is_finite() and len(exc.checkpoint) == 60
    assert len(exc.history) == exc.iteration - 1


@pytest.mark.parametrize("inject_at", [3, 4])
def test_fit_divergence_from_a_gradient_is_caught_in_its_iteration(monkeypatch, inject_at):
    """With compact gradients the loop checks the view's gradients instead of every parameter, except
    at checkpoints: a non-finite gradient must still stop the fit in the iteration it appears (3: not a
    checkpoint, 4: one), with the last checkpoint finite."""
    from trace3d.training.optimizer import GaussianOptimizer

    cameras, images = plane_views(4)
    model = init_from_points(plane_points(60), np.full((60, 3), 0.5), sh_degree=0, seed=0)
    original = GaussianOptimizer.sparse_step
    calls = []

    def poisoned(self, rows, grads, sources, visible=None):
        calls.append(1)
        if len(calls) == inject_at:
            grads["means"][0, 1] = float("inf")
        return original(self, rows, grads, sources, visible)

    monkeypatch.setattr(GaussianOptimizer, "sparse_step", poisoned)
    with pytest.raises(TrainingDiverged, match="non-finite at iteration") as info:
        fit(model, cameras, images, tiny_params(iterations=20, checkpoint_interval=2, densify=False, log_interval=1),
            progress=False)
    exc = info.value
    assert exc.iteration == inject_at
    assert exc.checkpoint_iteration == 2 and exc.checkpoint.is_finite()


# ----------------------------------------------------------------------------------------------
# The pipeline step
# ----------------------------------------------------------------------------------------------


def write_plane_scene(root, count=6):
    cameras, images = plane_views(count, split=lambda i: "test" if i % 3 == 2 else "train")
    for cam, img in zip(cameras, images):
        write_frame(root, cam.name, (img.numpy() * 255).round().astype(np.uint8))
    write_cameras(root, cameras)
    return Scene.read(root)


STEP_PARAMS = {"schedule_scale": 1.0, "iterations": 60, "densify_from": 20, "densify_until": 50,
               "densify_interval": 10, "normal_from": 30, "sh_degree": 1, "sh_degree_interval": 20,
               "random_init_count": 300, "device": "cpu", "num_render_views": 2}


def test_run_gaussians_writes_all_outputs(tmp_path):
    scene = write_plane_scene(tmp_path / "scene")
    poses = tmp_path / "poses"
    poses.mkdir()
    # poses: the scene's cameras (all views), and a point cloud on the plane
    write_cameras(poses, scene.cameras)
    write_points_ply(poses / "points3D.ply", plane_points(200).astype(np.float32), np.full((200, 3), 128, np.uint8))
    out = tmp_path / "gaussians"
    run_gaussians(scene, poses, out, dict(STEP_PARAMS))
    for name in ("point_cloud.ply", "train.csv", "metrics.json", "config.json", "cameras.json", "train_curve.png",
                 "renders.png"):
        assert (out / name).is_file(), name
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["init"] == "points" and metrics["num_test_views"] == 2 and metrics["num_train_views"] == 4
    assert len(metrics["test_views"]) == 2 and metrics["test_psnr"] > 12
    assert metrics["num_gaussians"] == len(GaussianModel.read_ply(out / "point_cloud.ply"))
    config = json.loads((out / "config.json").read_text())
    assert config["params"]["iterations"] == 60 and config["schedule"]["iterations"] == 60
    lines = (out / "train.csv").read_text().splitlines()
    assert lines[0].startswith("iteration,loss,l1,ssim,normal,distortion,psnr,gaussians")
    assert len(lines) == 1 + 6


def test_run_gaussians_random_init_and_bad_params(tmp_path):
    scene = write_plane_scene(tmp_path / "scene")
    with pytest.raises(ConfigError, match="unknown"):
        run_gaussians(scene, None, tmp_path / "x", {"bogus": 1})
    with pytest.raises(ConfigError, match="points"):
        run_gaussians(scene, None, tmp_path / "x", {"init": "points"})
    run_gaussians(scene, None, tmp_path / "out", dict(STEP_PARAMS, iterations=10, densify=False))
    assert json.loads((tmp_path / "out" / "metrics.json").read_text())["init"] == "random"


def test_run_gaussians_missing_test_pose(tmp_path):
    scene = write_plane_scene(tmp_path / "scene")
    poses = tmp_path / "poses"
    write_cameras(poses, [c for c in scene.cameras if c.split == "train"])
    with pytest.raises(Trace3DError, match="test views"):
        run_gaussians(scene, poses, tmp_path / "out", dict(STEP_PARAMS))


def test_run_gaussians_divergence_keeps_checkpoint_beside_output(tmp_path):
    scene = write_plane_scene(tmp_path / "scene")
    out = tmp_path / ".gaussians.tmp-123-abcdef12"  # the CLI's temporary name for results/.../gaussians
    params = dict(STEP_PARAMS, feature_lr=1e30, checkpoint_interval=1, densify=False)
    with pytest.raises(Trace3DError, match="checkpoint_last_good.ply") as info:
        run_gaussians(scene, None, out, params)
    failed = tmp_path / "gaussians.failed"
    assert failed_dir_for(out) == failed
    assert str(failed) in str(info.value)
    kept = GaussianModel.read_ply(failed / "checkpoint_last_good.ply")
    assert kept.is_finite() and len(kept) == 300
    assert json.loads((failed / "failure.json").read_text())["iteration"] >= 2


def test_bench_fit_phases_add_up_and_instrumentation_is_removed(tmp_path):
    """`trace3d bench fit` measures the real loop by wrapping what it calls; the wrappers go away after."""
    import torch

    from trace3d.render import core, kernels
    from trace3d.training import bench, loop

    before = (torch.Tensor.backward, core.project, kernels.forward_kernel, loop.render_view, kernels.Binning.__init__)
    out = bench.bench_size((32, 24), gaussians=400, iterations=4, warmup=1, views=4, root=tmp_path)
    after = (torch.Tensor.backward, core.project, kernels.forward_kernel, loop.render_view, kernels.Binning.__init__)
    assert before == after
    phases = out["phases_ms"]
    assert set(phases) == set(bench.PHASES)
    assert sum(phases.values()) == pytest.approx(out["ms_per_iteration"])
    for name in ("projection", "forward_kernel", "backward_kernel", "loss", "optimizer"):
        assert phases[name] > 0, name
    assert 0 < out["kernel_share"] < 1 and out["gaussians_start"] == 400
    for suffix in ("", "_geometry"):  # features only (lifting's frozen geometry), and with the geometry
        assert out["channels"][f"fwd_bwd_ms_16{suffix}"] > 0 and out["channels"][f"ratio_16_over_3{suffix}"] > 0
    # cores busy: CPU time over wall time in the same spans, at most the machine's cores (+ timer slack)
    assert set(out["cores_busy"]) == set(bench.PHASES)
    cores = os.cpu_count() or 1
    for name in ("forward_kernel", "backward_kernel", "loss", "optimizer"):
        assert 0 < out["cores_busy"][name] <= cores + 0.5, name
    assert 0 < out["cores_busy_iteration"] <= cores + 0.5


def test_bench_fit_phase_arithmetic():
    """Nested spans are subtracted: render minus its parts is the glue, backward minus its kernel the rest."""
    from trace3d.training import bench

    per = {"projection": 1.0, "binning": 2.0, "forward_kernel": 3.0, "render": 10.0, "loss": 4.0,
           "backward_kernel": 5.0, "backward": 12.0, "optimizer": 1.5, "density_control": 0.5}
    phases = bench._phases(per, 40.0)
    assert phases["render_glue"] == 4.0 and phases["autograd_rest"] == 7.0
    assert phases["other"] == 40.0 - (1 + 2 + 3 + 4 + 4 + 5 + 7 + 1.5 + 0.5)
    assert sum(phases.values()) == pytest.approx(40.0)


def test_fit_sweep_runs_the_step_per_budget_and_schedule(tmp_path):
    """`trace3d bench fit-sweep`: one gaussians step per (budget, schedule scale), iterations scaled."""
    from trace3d.training import bench

    room = tmp_path / "room"
    write_plane_scene(room / "scene")
    params = {k: v for k, v in STEP_PARAMS.items() if k != "schedule_scale"}
    plot = tmp_path / "sweep.png"
    out = bench.run_sweep([room], budgets=[150, 400], scales=[0.5, 1.0], out_plot=plot, base_params=params)
    rows = out["rows"]
    assert [(r["max_gaussians"], r["schedule_scale"]) for r in rows] == [(150, 0.5), (150, 1.0), (400, 0.5), (400, 1.0)]
    assert [r["iterations"] for r in rows] == [30, 60, 30, 60]
    assert all(r["room"] == "room" and 5 < r["test_psnr"] < 60 and r["minutes"] > 0 for r in rows), rows
    # the budget caps densification: never more Gaussians than it allows after the initial 300
    assert all(r["gaussians"] <= max(300, r["max_gaussians"]) for r in rows)
    assert plot.stat().st_size > 1000


def test_fit_sweep_merge_keeps_rows_in_order_and_names_a_bad_file(tmp_path):
    from trace3d.cli import main
    from trace3d.training import bench

    row = {"room": "r", "max_gaussians": 10, "schedule_scale": 0.1, "iterations": 30, "test_psnr": 20.0,
           "minutes": 1.0, "train_minutes": 0.9, "gaussians": 10}
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    a.write_text(json.dumps({"rows": [row, {**row, "schedule_scale": 0.2, "iterations": 60, "test_psnr": 22.0,
                                                     "minutes": 2.0}], "load_average": [1.0, 1.0, 1.0]}))
    b.write_text(json.dumps({"rows": [{**row, "max_gaussians": 20, "test_psnr": 21.0}], "load_average": [2.0, 2.0, 2.0]}))
    merged = bench.merge_sweeps([a, b], tmp_path / "m.png")
    assert [(r["max_gaussians"], r["schedule_scale"]) for r in merged["rows"]] == [(10, 0.1), (10, 0.2), (20, 0.1)]
    assert [r["load_average"][0] for r in merged["rows"]] == [1.0, 1.0, 2.0]
    assert (tmp_path / "m.png").stat().st_size > 1000
    bad = tmp_path / "bad.json"
    bad.write_text("{}")
    with pytest.raises(Trace3DError, match="bad.json: not a fit-sweep result"):
        bench.merge_sweeps([a, bad])
    # the command line: --merge instead of --rooms
    assert main(["bench", "fit-sweep", "--merge", str(a), str(b), "--out", str(tmp_path / "o.json")]) == 0
    assert len(json.loads((tmp_path / "o.json").read_text())["rows"]) == 3


def test_bench_fit_compare_and_baseline_checks(tmp_path):
    from trace3d.training import bench

    current = {"sizes": {"160x120": {"iterations_per_s": 20.0}, "504x378": {"iterations_per_s": 6.0}}}
    base = {"sizes": {"160x120": {"iterations_per_s": 5.0}}}
    cmp = bench.compare(current, base)
    assert set(cmp) == {"160x120"} and cmp["160x120"]["speedup"] == pytest.approx(4.0)
    with pytest.raises(FileNotFoundError, match="not a trace3d checkout"):
        bench.run_baseline(tmp_path, None, None, quick=True)


def test_bench_fit_rounds_alternate_with_the_baseline_and_pair_up(monkeypatch, tmp_path):
    """--rounds: baseline and current runs alternate; per size the median round is reported (a real
    round, not per-field medians), and the speedup is the median of the round pairs' ratios."""
    from trace3d.cli import main
    from trace3d.training import bench

    calls = []
    cur_ms = iter([10.0, 30.0, 20.0])
    base_ms = iter([20.0, 30.0, 60.0])

    def fake(ms_iter, who):
        ms = next(ms_iter)
        calls.append(who)
        return {"torch_threads": 1, "load_average": [0.0, 0.0, 0.0],
                "sizes": {"8x8": {"ms_per_iteration": ms, "iterations_per_s": 1000.0 / ms, "kernel_share": ms / 100,
                                  "phases_ms": {"other": ms}}}}

    monkeypatch.setattr(bench, "run_bench", lambda **kw: fake(cur_ms, "current"))
    monkeypatch.setattr(bench, "run_baseline", lambda *a: {**fake(base_ms, "baseline"), "commit": "abc"})
    out = bench.run_rounds(3, baseline=tmp_path)
    assert calls == ["baseline", "current"] * 3
    row = out["sizes"]["8x8"]
    assert row["rounds_ms_per_iteration"] == [10.0, 30.0, 20.0] and row["round"] == 2
    assert row["ms_per_iteration"] == 20.0 and row["rounds_kernel_share"] == [0.1, 0.3, 0.2]
    assert out["rounds"] == 3 and out["baseline"]["commit"] == "abc"
    assert out["baseline"]["sizes"]["8x8"]["ms_per_iteration"] == 30.0
    cmp = out["compared"]["8x8"]
    assert cmp["speedups"] == pytest.approx([2.0, 1.0, 3.0])
    assert cmp["speedup"] == pytest.approx(2.0)  # the median pair, not 30 / 20 = 1.5
    # an even count takes the lower of the middle two
    two = bench.median_round([fake(iter([40.0]), "x"), fake(iter([10.0]), "x")])
    assert two["sizes"]["8x8"]["ms_per_iteration"] == 10.0
    with pytest.raises(ValueError, match="rounds must be >= 1"):
        bench.run_rounds(0)
    assert main(["bench", "fit", "--rounds", "0"]) == 2


def test_density_statistics_kernel_matches_torch_lines():
    """add_stats' fused pass gives bit for bit the statistics of its masked torch updates."""
    from trace3d.training import strategy as st

    g = torch.Generator().manual_seed(0)
    n = 5000
    accum = torch.rand(n, generator=g)
    count = torch.randint(0, 5, (n,), generator=g).float()
    radii_max = torch.randint(0, 9, (n,), generator=g).float()
    norms = torch.rand(n, generator=g) * 1e-3
    visible = torch.rand(n, generator=g) < 0.3
    radii = torch.randint(0, 12, (n,), generator=g, dtype=torch.int32)
    assert st._stats_kernel_applies(accum, count, radii_max, norms, visible, radii)
    a, c, r = accum.clone(), count.clone(), radii_max.clone()
    st._accumulate_stats(a.numpy(), c.numpy(), r.numpy(), np.arange(n), norms.numpy(), visible.numpy(),
                         radii.numpy())
    accum[visible] += norms[visible]
    count[visible] += 1
    radii_max[visible] = torch.maximum(radii_max[visible], radii[visible].to(radii_max.dtype))
    assert torch.equal(a, accum) and torch.equal(c, count) and torch.equal(r, radii_max)
    assert not torch.equal(r, torch.maximum(radii_max, radii.float()))  # hidden rows kept their maxima
    assert not st._stats_kernel_applies(accum, count, radii_max, norms.double(), visible, radii)


def test_adam_rows_kernel_matches_its_twin_and_leaves_other_rows():
    """The visible-Adam row kernel against its torch twin over several steps; rows not selected keep
    their parameters and moments bit for bit."""
    import math

    from trace3d.training.adam_kernel import adam_rows, adam_rows_torch

    g = torch.Generator().manual_seed(0)
    n = 3000
    start = torch.randn(n, 16, 3, generator=g)
    ours, twin = start.clone(), start.clone()
    m1, v1 = torch.zeros_like(start), torch.zeros_like(start)
    m2, v2 = torch.zeros_like(start), torch.zeros_like(start)
    picked = torch.zeros(n, dtype=torch.bool)
    for t in range(1, 6):
        rows = torch.nonzero(torch.rand(n, generator=g) < 0.3).squeeze(1)
        picked[rows] = True
        grad = torch.randn(n, 16, 3, generator=g)
        step_size, inv = 0.01 / (1 - 0.9 ** t), 1 / math.sqrt(1 - 0.999 ** t)
        adam_rows(ours, grad, m1, v1, rows, step_size, 0.9, 0.999, inv, 1e-15)
        adam_rows_torch(twin, grad, m2, v2, rows, step_size, 0.9, 0.999, inv, 1e-15)
    for a, b in ((ours, twin), (m1, m2), (v1, v2)):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    assert 0 < int(picked.sum()) < n
    assert torch.equal(ours[~picked], start[~picked]) and bool((m1[~picked] == 0).all())
    assert bool((ours[picked] != start[picked]).any())


def test_visible_adam_equals_torch_adam_when_everything_is_visible():
    """GaussianOptimizer.step(visible) with visible_adam: all rows visible = torch's Adam; some rows
    hidden = those rows untouched (parameters and moments) while the others still match Adam."""
    from trace3d.gaussians import GaussianModel
    from trace3d.training.optimizer import GaussianOptimizer
    from trace3d.training.params import TrainParams

    g = torch.Generator().manual_seed(1)
    n = 400
    model = GaussianModel(means=torch.randn(n, 3, generator=g), quats=torch.randn(n, 4, generator=g),
                          log_scales=torch.randn(n, 2, generator=g), opacity_logits=torch.randn(n, generator=g),
                          sh_dc=torch.randn(n, 1, 3, generator=g), sh_rest=torch.randn(n, 15, 3, generator=g))
    lrs = {"means": 0.01, "quats": 0.002, "log_scales": 0.005, "opacity_logits": 0.05, "sh_dc": 0.0025,
           "sh_rest": 0.000125}
    dense = GaussianOptimizer(model, lrs, TrainParams(fused_adam=False), 1.0)
    vis = GaussianOptimizer(model, lrs, TrainParams(fused_adam=False, visible_adam=True), 1.0)
    hidden = torch.arange(n) % 4 == 0
    for step in range(4):
        grads = {name: torch.randn(getattr(model, name).shape, generator=g) for name in lrs}
        for state in (dense, vis):
            for name in lrs:
                state.model.get(name).grad = grads[name].clone()
        before = {name: vis.model.get(name).detach().clone() for name in lrs}
        dense.step()
        visible = torch.ones(n, dtype=torch.bool) if step < 2 else ~hidden
        vis.step(visible)
        for name in lrs:
            a, b = vis.model.get(name).detach(), dense.model.get(name).detach()
            if step < 2:
                torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6, msg=name)
            else:
                assert torch.equal(a[hidden], before[name][hidden]), name
                # each element's update is its own, so the rendered rows still follow dense Adam
                torch.testing.assert_close(a[~hidden], b[~hidden], rtol=1e-5, atol=1e-6, msg=name)
            assert vis.model.get(name).grad is None


def test_bulk_phases_do_not_depend_on_the_torch_thread_count():
    """Adam (torch's fused kernel) and the default density control run with the process's torch
    threads inside the fit: their results must be bit-identical to one thread's."""
    import hashlib

    from trace3d.gaussians import GaussianModel
    from trace3d.threads import torch_threads
    from trace3d.training.optimizer import GaussianOptimizer, learning_rates
    from trace3d.training.params import TrainParams
    from trace3d.training.strategy import densify_and_prune, reset_stats

    g = torch.Generator().manual_seed(3)
    n = 60_000  # large enough for torch to split its loops between threads
    model = GaussianModel(means=torch.randn(n, 3, generator=g), quats=torch.randn(n, 4, generator=g),
                          log_scales=torch.randn(n, 2, generator=g) - 4.0, opacity_logits=torch.randn(n, generator=g),
                          sh_dc=torch.randn(n, 1, 3, generator=g), sh_rest=torch.randn(n, 15, 3, generator=g))
    params = TrainParams(max_gaussians=n + 5000)
    stats = torch.rand(n, generator=g) * 2e-3

    def run(threads: int) -> str:
        state = GaussianOptimizer(model, learning_rates(params, 2.0), params, 2.0)
        state.bulk_threads = threads
        noise = torch.Generator().manual_seed(7)
        for _ in range(3):
            for group in state.optimizer.param_groups:
                p = group["params"][0]
                p.grad = torch.randn(p.shape, generator=noise) * 1e-2
            state.step()
        reset_stats(state)
        state.statistics["grad_accum"] += stats
        state.statistics["grad_count"] += 1
        with torch_threads(threads):
            event = densify_and_prune(state, True, torch.Generator().manual_seed(0))
        assert event["cloned"] + event["split"] > 0 and event["pruned"] > 0
        h = hashlib.sha1()
        for name, t in sorted(state.model.tensors().items()):
            h.update(name.encode())
            h.update(t.detach().contiguous().numpy().tobytes())
        for group in state.optimizer.param_groups:
            for key in ("exp_avg", "exp_avg_sq"):
                h.update(state.optimizer.state[group["params"][0]][key].numpy().tobytes())
        return h.hexdigest()

    assert run(1) == run(2)


def _append_reference(state, new):
    """GaussianOptimizer.append as written before edit(): concatenate, zero moments, fill statistics."""
    for name in state.model.names:
        old = state.model.get(name)
        extra = new.get(name).detach()
        state.replace(name, torch.cat([old.detach(), extra]),
                      lambda moment, extra=extra: torch.cat([moment, torch.zeros_like(extra)]))
    for name, value in state.statistics.items():
        state.statistics[name] = torch.cat([value, torch.full((len(new),), state._fills[name], dtype=value.dtype)])


def _keep_reference(state, mask):
    """GaussianOptimizer.keep as written before edit(): boolean indexing of everything."""
    for name in state.model.names:
        state.replace(name, state.model.get(name).detach()[mask], lambda moment: moment[mask])
    for name, value in state.statistics.items():
        state.statistics[name] = value[mask]


def _densify_reference(state, use_size_limits, generator, prune_by_opacity=True):
    """densify_and_prune as three edits (clone: append, split: append + keep, prune: keep), the
    way it was written before the single-copy edit, with the edits as they were written then: its
    twin."""
    from trace3d.training.strategy import densify_candidates, reset_stats, split_gaussians

    p = state.params
    clone_mask, split_mask = densify_candidates(state)
    cloned = int(clone_mask.sum())
    if cloned:
        _append_reference(state, state.model.subset(clone_mask))
        split_mask = torch.cat([split_mask, torch.zeros(cloned, dtype=torch.bool)])
    split = int(split_mask.sum())
    if split:
        _append_reference(state, split_gaussians(state.model.subset(split_mask), p.split_count, generator))
        _keep_reference(state, torch.cat([~split_mask, torch.ones(split * p.split_count, dtype=torch.bool)]))
    prune_mask = state.model.opacities < p.opacity_cull
    if not prune_by_opacity:
        prune_mask[:] = False
    if use_size_limits:
        prune_mask |= state.statistics["max_radii"] > p.max_screen_size
        prune_mask |= state.model.scales.max(dim=1).values > p.max_world_size * state.extent
    if bool(prune_mask.all()):
        prune_mask[:] = False
    pruned = int(prune_mask.sum())
    if pruned:
        _keep_reference(state, ~prune_mask)
    reset_stats(state)
    return {"cloned": cloned, "split": split, "pruned": pruned, "total": len(state)}


@pytest.mark.parametrize("case", ["all", "no_split", "nothing_pruned", "size_limits_off", "extras"])
def test_densify_single_edit_equals_append_and_keep(case):
    """densify_and_prune's one-copy edit gives bit for bit the parameters, Adam moments, statistics
    and counts of clone, split and prune done one after another with append and keep."""
    from trace3d.gaussians import GaussianModel
    from trace3d.training.optimizer import GaussianOptimizer, learning_rates
    from trace3d.training.params import TrainParams
    from trace3d.training.strategy import densify_and_prune, reset_stats

    g = torch.Generator().manual_seed(5)
    n = 3000
    log_scales = torch.randn(n, 2, generator=g) - 4.0
    if case == "no_split":
        log_scales = log_scales.clamp_max(-6.0)  # all small: clones only
    extras = {"features": torch.randn(n, 4, generator=g)} if case == "extras" else {}
    model = GaussianModel(means=torch.randn(n, 3, generator=g), quats=torch.randn(n, 4, generator=g),
                          log_scales=log_scales, opacity_logits=torch.randn(n, generator=g) * 3,
                          sh_dc=torch.randn(n, 1, 3, generator=g), sh_rest=torch.randn(n, 15, 3, generator=g),
                          extras=extras)
    if case == "nothing_pruned":
        model.opacity_logits = model.opacity_logits.abs() + 1.0
    params = TrainParams(max_gaussians=n + 700, max_screen_size=15.0, max_world_size=0.01)
    stats = (torch.rand(n, generator=g) * 1.2e-3, torch.randint(0, 30, (n,), generator=g).float())
    grads = {name: torch.randn(getattr(model, name).shape, generator=g) * 1e-2 for name in GaussianModel.PARAM_NAMES}
    results = []
    for fn in (densify_and_prune, _densify_reference):
        state = GaussianOptimizer(model, learning_rates(params, 2.0), params, 2.0)
        for name, grad in grads.items():
            state.model.get(name).grad = grad.clone()
        state.step()
        reset_stats(state)
        state.add_statistic("other", fill=7.0)
        state.statistics["grad_accum"] += stats[0]
        state.statistics["grad_count"] += 1
        state.statistics["max_radii"] += stats[1] if case != "nothing_pruned" else 0
        state.statistics["other"] += torch.arange(n, dtype=torch.float32)
        use_limits = case not in ("size_limits_off", "nothing_pruned")
        event = fn(state, use_limits, torch.Generator().manual_seed(0))
        moments = [state.optimizer.state[gr["params"][0]][k] for gr in state.optimizer.param_groups
                   for k in ("exp_avg", "exp_avg_sq")]
        results.append((event, state.model.tensors(), moments, dict(state.statistics)))
    (e1, t1, m1, s1), (e2, t2, m2, s2) = results
    assert e1 == e2
    assert e1["cloned"] > 0 and (e1["split"] > 0) == (case != "no_split")
    assert (e1["pruned"] > 0) == (case != "nothing_pruned")
    assert t1.keys() == t2.keys() and s1.keys() == s2.keys()
    for name in t1:
        assert torch.equal(t1[name].detach(), t2[name].detach()), name
    for a, b in zip(m1, m2):
        assert torch.equal(a, b)
    for name in s1:
        assert torch.equal(s1[name], s2[name]), name


# ----------------------------------------------------------------------------------------------
# Compact gradients (trace3d.training.sparse)
# ----------------------------------------------------------------------------------------------


def test_row_copies_equal_torch_index_operations():
    from trace3d.training.sparse import clear_rows, gather_rows, scatter_rows

    g = torch.Generator().manual_seed(0)
    n = 500
    tensors = [torch.randn(n, 3, generator=g), torch.randn(n, 15, 3, generator=g), torch.randn(n, generator=g),
               torch.randint(0, 9, (n, 2), generator=g), torch.randn(n, 4, generator=g, dtype=torch.float64)]
    rows = torch.nonzero(torch.rand(n, generator=g) < 0.3).squeeze(1)
    gathered = gather_rows(tensors, rows)
    for t, out in zip(tensors, gathered):
        assert out.dtype == t.dtype and torch.equal(out, t.index_select(0, rows))
    ours = [t.clone() for t in tensors]
    twin = [t.clone() for t in tensors]
    sources = [torch.randn(out.shape, generator=g).to(out.dtype) for out in gathered]
    scatter_rows(ours, rows, sources)
    for t, s in zip(twin, sources):
        t.index_copy_(0, rows, s)
    assert all(torch.equal(a, b) for a, b in zip(ours, twin))
    clear_rows(ours, rows)
    for t in twin:
        t.index_fill_(0, rows, 0)
    assert all(torch.equal(a, b) for a, b in zip(ours, twin))
    assert not torch.equal(ours[1], tensors[1]) and torch.equal(ours[1][0 if 0 not in rows else 1], tensors[1][0 if 0 not in rows else 1])


@pytest.mark.parametrize("overrides", [{}, {"visible_adam": True}])
def test_compact_gradients_give_the_dense_fit_bit_for_bit(overrides, monkeypatch):
    """A fit with compact gradients (the default on the CPU) equals the dense autograd path exactly:
    parameters, history and density events, through clones, splits, prunes and an opacity reset, with
    views that see only part of the Gaussians."""
    from trace3d.training import loop, sparse

    cameras, images = plane_views(6)
    model = init_from_points(plane_points(), np.full((300, 3), 0.5), sh_degree=1, seed=0)
    rows, _, _ = sparse.visible_rows(model, cameras[0], 0.01)
    assert 0 < rows.numel() < len(model)  # the views see part of the plane
    params = dict(iterations=90, densify_from=20, densify_until=80, densify_interval=10, opacity_reset_interval=40,
                  normal_from=30, sh_degree_interval=30, log_interval=1, **overrides)
    views = []
    monkeypatch.setattr(loop, "CompactView", lambda *a: views.append(1) or sparse.CompactView(*a))
    states = {False: [], True: []}

    def record(kind):
        def callback(iteration, state):  # every iteration: density statistics and the means' Adam moments
            moments = state.optimizer.state[state.model.means]
            states[kind].append([t.clone() for t in state.statistics.values()]
                                + [moments["exp_avg"].clone(), moments["exp_avg_sq"].clone()])
        return callback

    dense = fit(model, cameras, images, tiny_params(sparse_grad=False, **params), progress=False,
                callback=record(False))
    assert not views
    compact = fit(model, cameras, images, tiny_params(**params), progress=False, callback=record(True))
    assert len(views) == 90
    assert len(states[True]) == 90
    for a, b in zip(states[False], states[True]):
        assert all(torch.equal(x, y) for x, y in zip(a, b))
    assert any(e["split"] + e["cloned"] > 0 for e in compact.densify_events)
    assert any(e.get("pruned", 0) > 0 for e in compact.densify_events)
    for name in GaussianModel.PARAM_NAMES:
        assert torch.equal(getattr(dense.model, name), getattr(compact.model, name)), name
    assert [{k: v for k, v in r.items() if k != "seconds"} for r in dense.history] == \
        [{k: v for k, v in r.items() if k != "seconds"} for r in compact.history]
    assert dense.densify_events == compact.densify_events


def test_surface_depth_kernel_is_the_torch_operations_bit_for_bit():
    """The fused surface depth against the loop's former torch lines: values and the gradients of
    depth, alpha and median, exactly, with alpha at, below and just above the 1e-6 cut-off."""
    from trace3d.loss_kernels import surface_depth, surface_depth_torch

    g = torch.Generator().manual_seed(3)
    h, w = 37, 53
    alpha = torch.rand(h, w, generator=g)
    alpha[:5] = 0.0
    alpha[5:8] = 1e-6
    alpha[8:10] = torch.tensor(1e-6).nextafter(torch.tensor(1.0))
    alpha[10:12] = 3e-7
    depth = torch.rand(h, w, generator=g) * 4 * alpha
    median = torch.rand(h, w, generator=g) * 4
    up = torch.randn(h, w, generator=g)
    for ratio in (0.0, 0.3):
        values, grads = [], []
        for fn in (surface_depth, surface_depth_torch):
            leaves = [t.clone().requires_grad_() for t in (depth, alpha, median)]
            out = fn(*leaves, ratio)
            values.append(out.detach())
            grads.append(torch.autograd.grad((out * up).sum(), leaves))
        assert torch.equal(values[0], values[1])
        for a, b in zip(*grads):
            assert torch.equal(a, b)
        assert bool((values[0][:5] == ratio * median[:5]).all())


def test_compact_gradients_with_a_view_that_sees_nothing():
    """A training view facing away from every Gaussian: the compact path renders zero rows and still
    gives the dense fit exactly (and the row copies accept empty row sets)."""
    from trace3d.training.sparse import clear_rows, gather_rows, scatter_rows, visible_rows

    cameras, images = plane_views(4)
    c = cameras[0]
    away = Camera("away", "train", c.width, c.height, c.K,
                  look_at(np.zeros(3), np.array([0.0, 0.0, -PLANE_Z])))
    cameras.append(away)
    images.append(torch.zeros_like(images[0]))
    model = init_from_points(plane_points(), np.full((300, 3), 0.5), sh_degree=1, seed=0)
    assert visible_rows(model, away, 0.01)[0].numel() == 0
    fits = [fit(model, cameras, images, tiny_params(iterations=40, densify_from=10, densify_interval=10,
                                                     sparse_grad=sparse), progress=False) for sparse in (False, True)]
    for name in GaussianModel.PARAM_NAMES:
        assert torch.equal(getattr(fits[0].model, name), getattr(fits[1].model, name)), name
    empty = torch.zeros(0, dtype=torch.int64)
    t = torch.randn(10, 3)
    assert gather_rows([t], empty)[0].shape == (0, 3)
    before = t.clone()
    scatter_rows([t], empty, [torch.zeros(0, 3)])
    clear_rows([t], empty)
    assert torch.equal(t, before)
