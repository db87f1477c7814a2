"""Tests of the 2DGS rasterizer: numba tile kernels against the dense torch reference, the reference
against finite differences, Gaussian Instance Tracing, and edge cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from trace3d.errors import Trace3DError
from trace3d.render import Splats, render, trace, trace_argmax, trace_by_backward
from trace3d.render.projection import footprint_boxes, footprint_boxes_fast, project
from trace3d.scene import Camera

OUTPUTS = ("features", "alpha", "depth", "normal", "median_depth", "distortion")


def make_camera(width: int = 40, height: int = 30, focal: float = 36.0, rotate: bool = False) -> Camera:
    w2c = np.eye(4)
    if rotate:  # a small rotation and translation so that the world frame is not the camera frame
        a = 0.2
        w2c[:3, :3] = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
        w2c[:3, 3] = [0.1, -0.05, 0.2]
    K = np.array([[focal, 0, width / 2 + 0.3], [0, focal * 1.05, height / 2 - 0.2], [0, 0, 1]])
    return Camera("test", "train", width, height, K, w2c)


def make_scene(seed: int, n: int = 120, camera: Camera | None = None, channels: int = 3):
    """Random splats mixing the hard cases: tiny (sub-pixel) disks, oblique disks, splats behind the
    camera, off-screen splats, and pairs at exactly equal depth that overlap."""
    camera = camera or make_camera()
    gen = torch.Generator().manual_seed(seed)
    c2w = torch.as_tensor(camera.camera_to_world, dtype=torch.float32)

    def rand(*shape):
        return torch.rand(*shape, generator=gen)

    z = 1.5 + 3.0 * rand(n)
    x = (rand(n) - 0.5) * 1.3 * z * camera.width / camera.K[0, 0]
    y = (rand(n) - 0.5) * 1.3 * z * camera.height / camera.K[1, 1]
    cam_pts = torch.stack([x, y, z], 1)
    scales = torch.exp(math.log(0.01) + math.log(20.0) * rand(n, 2))
    quats = torch.randn(n, 4, generator=gen)
    opac = 0.05 + 0.9 * rand(n)
    k = n // 8
    if n >= 32:
        scales[:k] = 1e-3 + 1e-3 * rand(k, 2)  # tiny: the low-pass filter wins
        quats[k:2 * k] = torch.tensor([math.cos(0.78), math.sin(0.78), 0.0, 0.0])  # tilted 90 deg about x: edge-on
        quats[k:2 * k] += 0.05 * torch.randn(k, 4, generator=gen)
        cam_pts[2 * k:2 * k + 4, 2] = -cam_pts[2 * k:2 * k + 4, 2]  # behind the camera
        cam_pts[2 * k + 4:2 * k + 8, 0] += 50.0  # far off-screen
        # equal depth, overlapping
        cam_pts[2 * k + 9:2 * k + 13] = cam_pts[2 * k + 8] + torch.tensor([0.01, 0.0, 0.0]) * torch.arange(1, 5)[:, None]
        cam_pts[2 * k + 9:2 * k + 13, 2] = cam_pts[2 * k + 8, 2]
    means = cam_pts @ c2w[:3, :3].T + c2w[:3, 3]
    features = rand(n, channels)
    return Splats(means, quats, scales, opac), camera, features


def with_grad(splats: Splats, features: torch.Tensor, dtype=torch.float32):
    sp = Splats(*(t.detach().clone().to(dtype).requires_grad_() for t in splats))
    return sp, features.detach().clone().to(dtype).requires_grad_()


def weighted_loss(out, seed: int = 7) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    total = 0.0
    for name in OUTPUTS:
        t = getattr(out, name)
        total = total + (t * torch.randn(t.shape, generator=gen).to(t.dtype)).sum()
    return total


def run_backend(splats, camera, features, background, backend, dtype=torch.float32):
    sp, feats = with_grad(splats, features, dtype)
    bg = background.detach().clone().to(dtype).requires_grad_()
    out = render(sp, camera, feats, bg, with_distortion=True, backend=backend)
    weighted_loss(out).backward()
    grads = {"means": sp.means.grad, "quats": sp.quats.grad, "scales": sp.scales.grad,
             "opacities": sp.opacities.grad, "features": feats.grad, "background": bg.grad,
             "means2d": out.means2d.grad}
    return out, grads


def rel_err(a: torch.Tensor | None, b: torch.Tensor | None) -> float:
    a = torch.zeros(()) if a is None else a.double()
    b = torch.zeros(()) if b is None else b.double()
    return float((a - b).norm() / b.norm().clamp_min(1e-12))


class TestKernelAgainstReference:
    @pytest.mark.parametrize("seed", [0, 1, 2, 3])
    def test_forward_and_gradients(self, seed):
        camera = make_camera(rotate=seed % 2 == 1, width=40 if seed < 2 else 37, height=30 if seed < 2 else 21)
        splats, camera, features = make_scene(seed, camera=camera)
        background = torch.rand(3, generator=torch.Generator().manual_seed(seed))
        out_r, grads_r = run_backend(splats, camera, features, background, "reference")
        out_k, grads_k = run_backend(splats, camera, features, background, "numba")
        assert out_r.alpha.max() > 0.5, "the scene should cover the image"
        for name in OUTPUTS:
            a, b = getattr(out_k, name), getattr(out_r, name)
            assert a.shape == b.shape, name
            err = float((a - b).detach().abs().max())
            assert err <= 1e-4, f"{name}: max abs error {err:.2e}"
        assert torch.equal(out_k.visible, out_r.visible)
        for name, g in grads_r.items():
            err = rel_err(grads_k[name], g)
            assert err <= 1e-3, f"gradient of {name}: relative error {err:.2e}"

    def test_many_channels(self):
        splats, camera, features = make_scene(5, n=60, channels=37)
        background = torch.rand(37, generator=torch.Generator().manual_seed(0))
        out_r, grads_r = run_backend(splats, camera, features, background, "reference")
        out_k, grads_k = run_backend(splats, camera, features, background, "numba")
        assert float((out_k.features - out_r.features).detach().abs().max()) <= 1e-4
        assert rel_err(grads_k["features"], grads_r["features"]) <= 1e-3
        assert rel_err(grads_k["means"], grads_r["means"]) <= 1e-3

    def test_opaque_stack_terminates_early(self):
        # many opaque splats at one spot: transmittance falls below 1e-4 and blending stops
        n = 40
        means = torch.zeros(n, 3)
        means[:, 2] = 2.0 + 0.01 * torch.arange(n)
        splats = Splats(means, torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.full((n, 2), 0.3),
                        torch.full((n,), 0.95))
        camera = make_camera(24, 16)
        features = torch.rand(n, 3, generator=torch.Generator().manual_seed(1))
        out_r, grads_r = run_backend(splats, camera, features, torch.zeros(3), "reference")
        out_k, grads_k = run_backend(splats, camera, features, torch.zeros(3), "numba")
        for name in OUTPUTS:
            assert float((getattr(out_k, name) - getattr(out_r, name)).detach().abs().max()) <= 1e-4, name
        for name in ("means", "quats", "scales", "opacities", "features"):
            assert rel_err(grads_k[name], grads_r[name]) <= 1e-3, name
        # blending stopped at the centre: the transmittance left there is just above 1e-4
        cy, cx = int(camera.K[1, 2]), int(camera.K[0, 2])
        assert 1.0 - 1e-3 < float(out_k.alpha[cy, cx].detach()) <= 1.0 - 1e-4 + 1e-6

    def test_float64_inputs(self):
        splats, camera, features = make_scene(12, n=40)
        out32, g32 = run_backend(splats, camera, features, torch.zeros(3), "numba")
        out64, g64 = run_backend(splats, camera, features, torch.zeros(3), "numba", dtype=torch.float64)
        assert out64.features.dtype == torch.float64 and g64["means"].dtype == torch.float64
        assert float((out64.features - out32.features.double()).detach().abs().max()) <= 1e-4
        assert rel_err(g64["means"], g32["means"]) <= 1e-3

    @pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
    def test_cuda_tensors_round_trip(self):
        splats, camera, features = make_scene(13, n=40)
        cuda = Splats(*(t.cuda() for t in splats))
        out = render(cuda, camera, features.cuda())
        assert out.features.is_cuda and out.means2d.is_cuda
        ref = render(splats, camera, features)
        assert float((out.features.cpu() - ref.features).abs().max()) <= 1e-5

    def test_deterministic(self):
        splats, camera, features = make_scene(11)
        _, g1 = run_backend(splats, camera, features, torch.zeros(3), "numba")
        _, g2 = run_backend(splats, camera, features, torch.zeros(3), "numba")
        for name in g1:
            if g1[name] is not None:
                assert torch.equal(g1[name], g2[name]), name


class TestProjection:
    @pytest.mark.parametrize("seed", [0, 1])
    def test_fast_boxes_match_numpy(self, seed):
        splats, camera, _ = make_scene(seed, n=300, camera=make_camera(rotate=bool(seed)))
        proj = project(splats, camera)
        front = proj.depths > 0.01
        args = (proj.ray_transforms.detach(), proj.means2d.detach(), splats.opacities, front, camera.width, camera.height)
        fast, slow = footprint_boxes_fast(*args), footprint_boxes(*args)
        assert np.array_equal(fast, slow)
        assert np.array_equal(fast, proj.boxes)
        assert (fast[:, 2:] <= [camera.width, camera.height]).all() and (fast[:, :2] >= 0).all()

    def test_rotation_and_normals(self):
        splats, camera, _ = make_scene(9, n=50, camera=make_camera(rotate=True))
        proj = project(splats, camera)
        assert torch.allclose(proj.normals.norm(dim=-1), torch.ones(50), atol=1e-5)
        # normals face the camera: n . p_c <= 0
        p_cam = splats.means @ torch.as_tensor(camera.rotation, dtype=torch.float32).T + torch.as_tensor(
            camera.translation, dtype=torch.float32)
        assert ((proj.normals * p_cam).sum(-1) <= 1e-6).all()


class TestReference:
    def test_finite_differences(self):
        camera = make_camera(12, 10, focal=10.0)
        splats, camera, features = make_scene(3, n=6, camera=camera)
        splats = Splats(splats.means, splats.quats, splats.scales.clamp_min(0.05), splats.opacities.clamp(0.1, 0.8))
        keep = project(splats, camera).visible
        splats = Splats(*(t[keep] for t in splats))
        features = features[keep]
        assert splats.means.shape[0] >= 2

        def fn(means, quats, scales, opacities, feats):
            out = render(Splats(means, quats, scales, opacities), camera, feats, with_distortion=True,
                         backend="reference")
            return weighted_loss(out)

        inputs = tuple(t.detach().double().requires_grad_() for t in (*splats, features))
        assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


class TestTrace:
    def test_matches_backward_of_one_hot(self):
        splats, camera, _ = make_scene(4)
        gen = torch.Generator().manual_seed(3)
        labels = torch.randint(-1, 6, (camera.height, camera.width), generator=gen)
        weights = trace(splats, camera, labels, 6)
        assert weights.is_sparse and weights.shape == (splats.means.shape[0], 6)
        dense = weights.to_dense()
        by_backward = trace_by_backward(splats, camera, labels, 6, backend="numba")
        by_reference = trace_by_backward(splats, camera, labels, 6, backend="reference")
        assert float((dense - by_backward).abs().max()) <= 1e-5
        assert float((dense - by_reference).abs().max()) <= 1e-4
        assert float((trace(splats, camera, labels, 6, backend="reference").to_dense() - by_reference).abs().max()) == 0

    def test_many_labels(self):
        splats, camera, _ = make_scene(7)
        labels = torch.randint(0, 300, (camera.height, camera.width), generator=torch.Generator().manual_seed(5))
        dense = trace(splats, camera, labels, 300).to_dense()
        assert float((dense - trace_by_backward(splats, camera, labels, 300, backend="numba")).abs().max()) <= 1e-5

    def test_sums_per_pixel_to_alpha(self):
        splats, camera, features = make_scene(6, camera=make_camera(24, 18))
        labels = torch.arange(camera.height * camera.width).reshape(camera.height, camera.width)
        weights = trace(splats, camera, labels, camera.height * camera.width).to_dense()
        with torch.no_grad():
            alpha = render(splats, camera, features).alpha
        assert float((weights.sum(0).reshape(camera.height, camera.width) - alpha).abs().max()) <= 1e-5

    def test_argmax(self):
        weights = torch.tensor([[0.1, 0.3, 0.0], [0.0, 0.0, 0.0], [0.2, 0.2, 0.6], [0.5, 0.5, 0.0]])
        for w in (weights, weights.to_sparse()):
            label, prob, total = trace_argmax(w)
            assert label.tolist() == [1, -1, 2, 0]
            assert torch.allclose(prob, torch.tensor([0.75, 0.0, 0.6, 0.5]))
            assert torch.allclose(total, torch.tensor([0.4, 0.0, 1.0, 1.0]))

    def test_argmax_of_trace(self):
        splats, camera, _ = make_scene(8)
        labels = torch.randint(0, 4, (camera.height, camera.width), generator=torch.Generator().manual_seed(0))
        weights = trace(splats, camera, labels, 4)
        label, prob, total = trace_argmax(weights)
        dense = weights.to_dense()
        seen = dense.sum(1) > 0
        assert torch.equal(label[seen], dense[seen].argmax(1))
        assert torch.all(label[~seen] == -1)
        assert torch.allclose(total, dense.sum(1))

    def test_bad_labels(self):
        splats, camera, _ = make_scene(0, n=10)
        with pytest.raises(Trace3DError):
            trace(splats, camera, torch.zeros(3, 3, dtype=torch.int64), 2)
        with pytest.raises(Trace3DError):
            trace(splats, camera, torch.full((camera.height, camera.width), 5), 3)


class TestEdgeCases:
    @pytest.mark.parametrize("backend", ["numba", "reference"])
    def test_empty_scene(self, backend):
        camera = make_camera(20, 12)
        splats = Splats(torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 2), torch.zeros(0))
        bg = torch.tensor([0.2, 0.4, 0.6])
        out = render(splats, camera, torch.zeros(0, 3), bg, with_distortion=True, backend=backend)
        assert torch.allclose(out.features, bg.expand(12, 20, 3))
        for name in ("alpha", "depth", "normal", "median_depth", "distortion"):
            assert float(getattr(out, name).abs().max()) == 0.0, name
        assert trace(splats, camera, torch.zeros(12, 20, dtype=torch.int64), 3, backend=backend)._nnz() == 0

    @pytest.mark.parametrize("backend", ["numba", "reference"])
    def test_all_culled(self, backend):
        splats, camera, features = make_scene(2, n=16)
        means = splats.means.clone()
        means[:, 2] = -means[:, 2].abs() - 1.0  # every splat behind the camera
        sp, feats = with_grad(Splats(means, *splats[1:]), features)
        out = render(sp, camera, feats, with_distortion=True, backend=backend)
        assert not out.visible.any() and int(out.radii.max()) == 0
        assert float(out.alpha.abs().max()) == 0.0 and float(out.features.abs().max()) == 0.0
        weighted_loss(out).backward()
        for t in (sp.means, sp.quats, sp.scales, sp.opacities, feats):
            assert t.grad is None or float(t.grad.abs().max()) == 0.0

    def test_single_gaussian(self):
        camera = make_camera(24, 16)
        splats = Splats(torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
                        torch.tensor([[0.1, 0.1]]), torch.tensor([0.8]))
        features = torch.tensor([[1.0, 0.5, 0.25]])
        outs = {b: render(splats, camera, features, backend=b) for b in ("numba", "reference")}
        out = outs["numba"]
        # facing the camera at depth 2: the peak alpha is the opacity, the depth 2, the normal -z
        cy, cx = int(camera.K[1, 2]), int(camera.K[0, 2])
        assert 0.75 < float(out.alpha.max()) <= 0.8  # the centre is 0.2 / 0.3 px off a pixel centre
        assert abs(float(out.depth[cy, cx] / out.alpha[cy, cx]) - 2.0) < 1e-4
        assert torch.allclose(out.normal[cy, cx] / out.alpha[cy, cx], torch.tensor([0.0, 0.0, -1.0]), atol=1e-5)
        assert float(out.median_depth[cy, cx]) == pytest.approx(2.0, abs=1e-4)
        assert out.visible.tolist() == [True] and int(out.radii[0]) > 0
        for name in OUTPUTS[:-1]:
            assert float((getattr(out, name) - getattr(outs["reference"], name)).abs().max()) <= 1e-5

    def test_bad_input(self):
        camera = make_camera(8, 8)
        ok = Splats(torch.zeros(2, 3), torch.ones(2, 4), torch.ones(2, 2), torch.ones(2) * 0.5)
        with pytest.raises(Trace3DError):
            render(Splats(torch.zeros(2, 3), torch.ones(3, 4), torch.ones(2, 2), torch.ones(2)), camera, torch.zeros(2, 3))
        with pytest.raises(Trace3DError):
            render(ok, camera, torch.zeros(3, 3))
        with pytest.raises(Trace3DError):
            render(ok, camera, torch.zeros(2, 3), background=torch.zeros(4))
        with pytest.raises(Trace3DError):
            render(ok, camera, torch.zeros(2, 3), backend="cuda-magic")

    def test_means2d_gradient_is_screen_space(self):
        # moving a splat right in the image should be what means2d's gradient measures
        camera = make_camera(24, 16)
        splats = Splats(torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
                        torch.tensor([[0.08, 0.08]]), torch.tensor([0.8]))
        sp, feats = with_grad(splats, torch.ones(1, 1))
        out = render(sp, camera, feats)
        weight = torch.linspace(0, 1, camera.width)[None, :].expand(camera.height, -1)
        (out.features[..., 0] * weight).sum().backward()
        g = out.means2d.grad[0]
        assert g[0] > 0 and abs(float(g[1])) < 1e-2 * float(g[0])
