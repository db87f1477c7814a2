"""Tests of trace3d.training.losses and its kernels (trace3d.training.kernels.losses): SSIM, the photometric
terms, depth-normal consistency and the surface depth, each kernel against its torch twin."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tests.plane_scene import single_thread  # noqa: F401  (autouse fixture)
from trace3d.geometry import depth_to_normal, depth_to_points
from trace3d.training.losses import _ssim_map_reference, normal_consistency_loss, photometric_loss, psnr, ssim, ssim_map


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
        from trace3d.training.kernels.losses import fused_ssim

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
        from trace3d.training.kernels.losses import _blur, _window

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
        from trace3d.training.kernels.losses import fused_ssim, fused_ssim_applies
        from trace3d.render.kernels.glue import set_fused

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
        from trace3d.training.kernels.losses import _target_cache, _TargetStats, fused_ssim

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
        from trace3d.training.kernels.losses import _window

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
        from trace3d.training.losses import photometric_terms

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
        from trace3d.training.kernels.losses import fused_photometric

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
        from trace3d.training.kernels.losses import fused_normal_consistency

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
        from trace3d.training.losses import depth_normal_consistency
        from trace3d.training.kernels.losses import fused_normal_consistency
        from trace3d.render.kernels.glue import set_fused

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


def test_surface_depth_kernel_is_the_torch_operations_bit_for_bit():
    """The fused surface depth against the loop's former torch lines: values and the gradients of
    depth, alpha and median, exactly, with alpha at, below and just above the 1e-6 cut-off."""
    from trace3d.training.kernels.losses import surface_depth, surface_depth_torch

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
