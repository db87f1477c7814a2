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
        cam_pts[2 * k + 9:2 * k + 13] = (cam_pts[2 * k + 8]
                                         + torch.tensor([0.01, 0.0, 0.0]) * torch.arange(1, 5)[:, None])
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


def pair_terms(splats: Splats, camera: Camera) -> dict[str, np.ndarray]:
    """Every (pixel, splat) pair evaluated from the 2DGS formulas in float64, written independently of
    the renderer (docs/2dgs-math.md): the ray through the pixel centre meets the disk's plane at
    c = (x T_w - T_x) x (y T_w - T_y).

    Returns [H, W, N] arrays sigma_disk, sigma_filter, alpha (clamped, 0 where skipped), z, and [N]
    centre depths ``depth``.
    """
    q = splats.quats.detach().double().numpy()
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    rot = np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                    np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                    np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)  # [N, 3, 3]
    scales = splats.scales.detach().double().numpy()
    opac = splats.opacities.detach().double().numpy()
    K, R_cw, t_cw = camera.K, camera.rotation, camera.translation
    p_c = splats.means.detach().double().numpy() @ R_cw.T + t_cw  # [N, 3]
    axes = np.einsum("ij,njk->nik", R_cw, rot)  # [N, 3, 3] camera-space t_u, t_v, t_w as columns
    T = np.einsum("ij,njk->nik", K, np.stack([axes[:, :, 0] * scales[:, :1], axes[:, :, 1] * scales[:, 1:],
                                               p_c], axis=-1))  # rows T_x, T_y, T_w
    centre = (p_c @ K.T)[:, :2] / p_c[:, 2:3]
    xs = np.arange(camera.width) + 0.5
    ys = np.arange(camera.height) + 0.5
    px, py = np.meshgrid(xs, ys)  # [H, W]
    h_u = px[..., None, None] * T[None, None, :, 2] - T[None, None, :, 0]  # [H, W, N, 3]
    h_v = py[..., None, None] * T[None, None, :, 2] - T[None, None, :, 1]
    c = np.cross(h_u, h_v)
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = c[..., 0] / c[..., 2], c[..., 1] / c[..., 2]
    sigma_disk = 0.5 * (u * u + v * v)
    sigma_filter = (px[..., None] - centre[:, 0]) ** 2 + (py[..., None] - centre[:, 1]) ** 2
    disk = sigma_disk <= sigma_filter
    alpha = np.minimum(0.99, opac * np.exp(-np.minimum(sigma_disk, sigma_filter)))
    depth = np.where(disk, u * T[:, 2, 0] + v * T[:, 2, 1] + T[:, 2, 2], T[:, 2, 2])
    keep = (c[..., 2] != 0) & (alpha >= 1 / 255) & (depth > 0.01) & (p_c[:, 2] > 0.01)
    return {"sigma_disk": sigma_disk, "sigma_filter": sigma_filter, "alpha": np.where(keep, alpha, 0.0),
            "z": depth, "depth": p_c[:, 2]}


def trace_bruteforce(splats: Splats, camera: Camera, labels: torch.Tensor, num_labels: int,
                     count_pixels: bool = False) -> torch.Tensor:
    """Slow, obviously-correct twin of :func:`trace`: for every pixel, blend its splats front to back
    (by centre depth, ties by index) in a Python loop and add each weight w_k = alpha_k T_k (or 1 with
    ``count_pixels``) to W[k, label]; stop before a splat that would leave a transmittance below 1e-4.

    Returns: dense [N, num_labels] float64.
    """
    terms = pair_terms(splats, camera)
    order = np.argsort(terms["depth"], kind="stable")
    out = np.zeros((splats.means.shape[0], num_labels))
    for row in range(camera.height):
        for col in range(camera.width):
            label = int(labels[row, col])
            transmittance = 1.0
            for k in order:
                alpha = terms["alpha"][row, col, k]
                if alpha == 0.0:
                    continue
                if transmittance * (1.0 - alpha) < 1e-4:
                    break
                if label >= 0:
                    out[k, label] += 1.0 if count_pixels else alpha * transmittance
                transmittance *= 1.0 - alpha
    return torch.from_numpy(out)


def opaque_scene(seed: int, n: int = 60):
    """Random large splats with opacities in [0.995, 1]: pairs near a disk's centre hit the 0.99 alpha
    clamp, and pixels behind a few of them stop blending early."""
    splats, camera, features = make_scene(seed, n=n)
    gen = torch.Generator().manual_seed(seed + 100)
    scales = 0.25 + 0.25 * torch.rand(n, 2, generator=gen)
    opac = 1.0 - 0.005 * torch.rand(n, generator=gen)
    return Splats(splats.means, splats.quats, scales, opac), camera, features


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

    @pytest.mark.parametrize("channels", [5, 37])
    def test_many_channels(self, channels):
        # with the 3 normal channels: 8 (the backward's one-pass case, every fixed plane in use) and 40
        # (the two-pass case, channels past the first 8)
        splats, camera, features = make_scene(5, n=60, channels=channels)
        background = torch.rand(channels, generator=torch.Generator().manual_seed(0))
        out_r, grads_r = run_backend(splats, camera, features, background, "reference")
        out_k, grads_k = run_backend(splats, camera, features, background, "numba")
        assert float((out_k.features - out_r.features).detach().abs().max()) <= 1e-4
        # the normals are blended as channels after the features, so here beyond the first 8 too
        assert float((out_k.normal - out_r.normal).detach().abs().max()) <= 1e-4
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
        # float64 splats through the kernels (float32 inside) against the reference computed in float64
        splats, camera, features = make_scene(12, n=40)
        out_r, g_r = run_backend(splats, camera, features, torch.zeros(3), "reference", dtype=torch.float64)
        out_k, g_k = run_backend(splats, camera, features, torch.zeros(3), "numba", dtype=torch.float64)
        for name in OUTPUTS:
            a, b = getattr(out_k, name), getattr(out_r, name)
            assert a.dtype == torch.float64 and b.dtype == torch.float64, name
            assert float((a - b).detach().abs().max()) <= 1e-4, name
        for name, g in g_r.items():
            assert g is not None and g.dtype == torch.float64 and g_k[name].dtype == torch.float64, name
            assert rel_err(g_k[name], g) <= 1e-3, name

    def test_alpha_clamp(self):
        # opacities near 1: many pairs are clamped to alpha 0.99, where alpha has no gradient
        splats, camera, features = opaque_scene(14)
        assert (pair_terms(splats, camera)["alpha"] == 0.99).sum() >= 10, "the scene must reach the clamp"
        background = torch.rand(3, generator=torch.Generator().manual_seed(14))
        out_r, grads_r = run_backend(splats, camera, features, background, "reference")
        out_k, grads_k = run_backend(splats, camera, features, background, "numba")
        for name in OUTPUTS:
            assert float((getattr(out_k, name) - getattr(out_r, name)).detach().abs().max()) <= 1e-4, name
        for name, g in grads_r.items():
            assert rel_err(grads_k[name], g) <= 1e-3, name

    @pytest.mark.parametrize("backend", ["numba", "reference"])
    def test_alpha_clamp_single_splat(self, backend):
        # one opaque disk centred on pixel (12, 8): alpha there is clamped to exactly 0.99 and carries no
        # opacity gradient; the next pixel is below the clamp and does
        K = np.array([[20.0, 0, 12.5], [0, 20.0, 8.5], [0, 0, 1]])
        camera = Camera("clamp", "train", 24, 16, K, np.eye(4))
        splats = Splats(torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
                        torch.tensor([[0.1, 0.1]]), torch.tensor([1.0]))
        grads = []
        for pixel in ((8, 12), (8, 13)):
            sp, feats = with_grad(splats, torch.ones(1, 1))
            out = render(sp, camera, feats, backend=backend)
            out.alpha[pixel].backward()
            grads.append(float(sp.opacities.grad[0]))
            if pixel == (8, 12):
                assert float(out.alpha[pixel].detach()) == pytest.approx(0.99, abs=1e-7)
        # the neighbour: 1 px off the centre is 1 / (20 * 0.1 / 2) = 1 disk unit, alpha = exp(-1/2)
        assert grads[0] == 0.0
        assert grads[1] == pytest.approx(math.exp(-0.5), rel=1e-4)

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
        args = (proj.ray_transforms.detach(), proj.means2d.detach(), splats.opacities, front, camera.width,
                camera.height)
        fast, slow = footprint_boxes_fast(*args), footprint_boxes(*args)
        assert np.array_equal(fast, slow)
        assert np.array_equal(fast, proj.boxes)
        assert (fast[:, 2:] <= [camera.width, camera.height]).all() and (fast[:, :2] >= 0).all()

    @staticmethod
    def crossing_scene(seed: int, n: int = 80):
        """Large disks whose centres sit a few centimetres to half a metre in front of the camera
        plane, so that most of them cross it (their projection is unbounded): the case whose boxes
        are bounded by the part of the disk in front of the near plane."""
        camera = make_camera(rotate=True)
        gen = torch.Generator().manual_seed(seed)
        z = 0.02 + 0.5 * torch.rand(n, generator=gen) ** 2
        lateral = (torch.rand(n, 2, generator=gen) - 0.5) * 2.0 * torch.tensor([0.8, 0.6])
        lateral[: n // 2] *= z[: n // 2, None] * 0.7  # half near the optical axis: their disks reach the image
        cam_pts = torch.cat([lateral, z[:, None]], 1)
        c2w = torch.as_tensor(camera.camera_to_world, dtype=torch.float32)
        means = cam_pts @ c2w[:3, :3].T + c2w[:3, 3]
        scales = 0.05 + 0.6 * torch.rand(n, 2, generator=gen)
        quats = torch.randn(n, 4, generator=gen)
        opac = 0.05 + 0.9 * torch.rand(n, generator=gen)
        return Splats(means, quats, scales, opac), camera, torch.rand(n, 3, generator=gen)

    @pytest.mark.parametrize("seed", [0, 1, 2])
    def test_boxes_of_disks_crossing_the_camera_plane(self, seed):
        splats, camera, _ = self.crossing_scene(seed)
        proj = project(splats, camera)
        T = proj.ray_transforms.detach().double()
        level = torch.log(splats.opacities.double() * 255.0)
        crossing = (2 * level * (T[:, 2, 0] ** 2 + T[:, 2, 1] ** 2) - T[:, 2, 2] ** 2 >= 0) & (proj.depths > 0.01)
        assert int(crossing.sum()) >= 10, "the scene should have disks crossing the camera plane"
        # every pair that blends (float64, written independently) lies inside its splat's box
        alpha = pair_terms(splats, camera)["alpha"]  # [H, W, N]
        ys, xs, ks = np.nonzero(alpha > 0)
        b = proj.boxes[ks]
        assert ((xs >= b[:, 0]) & (xs < b[:, 2]) & (ys >= b[:, 1]) & (ys < b[:, 3])).all()
        # and the boxes are bounded: crossing disks no longer take the whole image
        full = ((proj.boxes[:, 2] - proj.boxes[:, 0] == camera.width)
                & (proj.boxes[:, 3] - proj.boxes[:, 1] == camera.height))
        assert int(full[crossing.numpy()].sum()) < int(crossing.sum())
        front = proj.depths > 0.01
        args = (proj.ray_transforms.detach(), proj.means2d.detach(), splats.opacities, front, camera.width,
                camera.height)
        assert np.array_equal(footprint_boxes_fast(*args), footprint_boxes(*args))

    def test_crossing_disks_render_as_the_reference(self):
        splats, camera, features = self.crossing_scene(3)
        background = torch.rand(3, generator=torch.Generator().manual_seed(3))
        out_r, grads_r = run_backend(splats, camera, features, background, "reference")
        out_k, grads_k = run_backend(splats, camera, features, background, "numba")
        assert float(out_r.alpha.detach().max()) > 0.5
        for name in OUTPUTS:
            err = float((getattr(out_k, name) - getattr(out_r, name)).detach().abs().max())
            assert err <= 1e-4, f"{name}: max abs error {err:.2e}"
        for name, g in grads_r.items():
            err = rel_err(grads_k[name], g)
            assert err <= 1e-3, f"gradient of {name}: relative error {err:.2e}"

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

    def test_finite_differences_low_pass_filter(self):
        # sub-pixel disks (scales 1-2 mm at 2-3 m, focal 10 px): the filter's exponent is the smaller one
        # at every pixel the splats reach, so its gradient (to means2d, hence the means) is what is checked
        camera = make_camera(12, 10, focal=10.0)
        gen = torch.Generator().manual_seed(21)
        n = 5
        z = 2.0 + torch.rand(n, generator=gen, dtype=torch.float64)
        xy = (torch.rand(n, 2, generator=gen, dtype=torch.float64) - 0.5) * 0.8 * z[:, None]
        means = torch.cat([xy, z[:, None]], 1) @ torch.as_tensor(camera.camera_to_world[:3, :3]).T + torch.as_tensor(
            camera.camera_to_world[:3, 3])
        splats = Splats(means, torch.randn(n, 4, generator=gen, dtype=torch.float64),
                        1e-3 + 1e-3 * torch.rand(n, 2, generator=gen, dtype=torch.float64),
                        0.3 + 0.5 * torch.rand(n, generator=gen, dtype=torch.float64))
        features = torch.rand(n, 3, generator=gen, dtype=torch.float64)
        terms = pair_terms(splats, camera)
        reached = terms["alpha"] > 0
        assert reached.sum() >= 3 * n and (terms["sigma_filter"] < terms["sigma_disk"])[reached].all()

        def fn(means, quats, scales, opacities, feats):
            out = render(Splats(means, quats, scales, opacities), camera, feats, with_distortion=True,
                         backend="reference")
            return weighted_loss(out)

        inputs = tuple(t.detach().clone().requires_grad_() for t in (*splats, features))
        assert all(t.dtype == torch.float64 for t in inputs)
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

    @pytest.mark.parametrize("scene", ["random", "opaque"])
    @pytest.mark.parametrize("backend", ["numba", "reference"])
    @pytest.mark.parametrize("top", [3, 6])  # at most 4 labels per tile (their own vector passes) or more
    def test_matches_per_pixel_loop(self, scene, backend, top):
        # the opaque scene reaches the 0.99 clamp and stops blending early at many pixels
        splats, camera, _ = make_scene(4) if scene == "random" else opaque_scene(15)
        labels = torch.randint(-1, top, (camera.height, camera.width), generator=torch.Generator().manual_seed(3))
        oracle = trace_bruteforce(splats, camera, labels, 6)
        assert (oracle > 0).sum() >= 20
        if scene == "opaque":
            assert (pair_terms(splats, camera)["alpha"] == 0.99).sum() >= 10, "the scene must reach the clamp"
        dense = trace(splats, camera, labels, 6, backend=backend).to_dense().double()
        assert float((dense - oracle).abs().max()) <= 1e-4

    def test_count_pixels_matches_per_pixel_loop(self):
        splats, camera, _ = opaque_scene(16)
        labels = torch.randint(0, 4, (camera.height, camera.width), generator=torch.Generator().manual_seed(4))
        counts = trace(splats, camera, labels, 4, count_pixels=True).to_dense().double()
        assert torch.equal(counts, trace_bruteforce(splats, camera, labels, 4, count_pixels=True))

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

    def test_coalesce_sums_repeats_in_the_order_they_come(self):
        from trace3d.render.kernels.coalesce import coalesce_triplets

        # 1 + 2^-24 rounds back to 1 in float32, 2^-24 + 2^-24 = 2^-23 does not: the order shows
        e = np.float32(2.0 ** -24)
        for w, expected in (([1.0, e, e], 1.0), ([e, e, 1.0], 1.0 + 2.0 ** -23)):
            rows, cols, vals, indptr = coalesce_triplets(np.zeros(3, np.int64), np.full(3, 2, np.int64),
                                                         np.array(w, np.float32), 2)
            assert rows.tolist() == [0] and cols.tolist() == [2] and indptr.tolist() == [0, 1, 1]
            assert vals[0] == np.float32(expected)

    @pytest.mark.parametrize("per_row", [5, 200])  # rows sorted by insertion, and by merge sort
    def test_coalesce_matches_a_dictionary(self, per_row):
        from trace3d.render.kernels.coalesce import coalesce_triplets

        rng = np.random.default_rng(per_row)
        n, size = 40, 40 * per_row
        rows = rng.integers(0, n - 3, size)  # the last rows stay empty
        cols = rng.integers(0, per_row // 2 + 2, size)  # many repeats
        vals = rng.random(size).astype(np.float32)
        sums: dict = {}
        for r, c, v in zip(rows.tolist(), cols.tolist(), vals):
            sums[(r, c)] = sums[(r, c)] + v if (r, c) in sums else v  # float32 adds, in order
        keys = sorted(sums)
        out_rows, out_cols, out_vals, indptr = coalesce_triplets(rows, cols, vals, n)
        assert list(zip(out_rows.tolist(), out_cols.tolist())) == keys
        assert np.array_equal(out_vals, np.array([sums[k] for k in keys], np.float32))
        assert np.array_equal(indptr, np.searchsorted(out_rows, np.arange(n + 1)))

    @pytest.mark.parametrize("count_pixels", [False, True])
    def test_trace_reduced_is_trace_argmax_of_trace(self, count_pixels):
        from trace3d.render import trace_reduced

        splats, camera, _ = make_scene(9, n=300)  # with splats behind the camera and off-screen
        labels = torch.randint(-1, 5, (camera.height, camera.width), generator=torch.Generator().manual_seed(2))
        label, prob, total = trace_argmax(trace(splats, camera, labels, 5, count_pixels=count_pixels))
        assert bool((label == -1).any()) and bool((label >= 0).any())
        table = (np.zeros((300, 3), np.int32), np.zeros((300, 3), np.float32), np.zeros((300, 3), np.float32))
        out = trace_reduced(splats, camera, labels, 5, count_pixels=count_pixels, out=tuple(t[:, 1] for t in table))
        for got, want in zip(out, (label.numpy().astype(np.int32), prob.numpy(), total.numpy())):
            assert got.dtype == want.dtype and np.array_equal(got, want)  # bit for bit
        assert np.array_equal(table[0][:, 1], label.numpy()) and not table[0][:, 0].any()  # the column only
        with pytest.raises(Trace3DError, match="out must be"):
            trace_reduced(splats, camera, labels, 5, out=(np.zeros(300, np.int64),) + out[1:])

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
        assert float(out.alpha.detach().abs().max()) == 0.0 and float(out.features.detach().abs().max()) == 0.0
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
            render(Splats(torch.zeros(2, 3), torch.ones(3, 4), torch.ones(2, 2), torch.ones(2)), camera,
                   torch.zeros(2, 3))
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


class TestValuesOnlyBackward:
    """With the geometry frozen (nothing upstream of the projection needs a gradient: lifting's features,
    GIT through autograd) the backward runs ``backward_values_kernel``: the value gradients alone."""

    @staticmethod
    def _feature_grad(splats, camera, features, upstream, background, kernels, monkeypatch, frozen: bool):
        """d sum(upstream * F) / d features, with the geometry frozen or not; asserts which backward ran."""
        ran = []
        for name in ("backward_kernel", "backward_values_kernel"):
            fn = getattr(kernels, name)
            monkeypatch.setattr(kernels, name, lambda *a, _fn=fn, _name=name: ran.append(_name) or _fn(*a))
        sp = splats if frozen else Splats(splats.means.clone().requires_grad_(), *splats[1:])
        feats = features.clone().requires_grad_()
        out = render(sp, camera, feats, background)
        (g,) = torch.autograd.grad((out.features * upstream).sum(), feats)
        monkeypatch.undo()
        assert ran == ["backward_values_kernel" if frozen else "backward_kernel"]
        return g

    @pytest.mark.parametrize("channels", [3, 5, 16, 37])  # with the normals: 6, 8 (every fixed plane), 19, 40
    def test_same_bits_as_the_full_backward(self, channels, monkeypatch):
        from trace3d.render.kernels import rasterize as kernels  # where the autograd Function looks them up

        splats, camera, features = make_scene(channels, channels=channels)
        gen = torch.Generator().manual_seed(channels)
        upstream = torch.randn(camera.height, camera.width, channels, generator=gen)
        background = torch.rand(channels, generator=gen) if channels == 3 else torch.zeros(channels)
        frozen = self._feature_grad(splats, camera, features, upstream, background, kernels, monkeypatch, True)
        full = self._feature_grad(splats, camera, features, upstream, background, kernels, monkeypatch, False)
        assert float(full.abs().max()) > 0.1
        # the same blended lanes in the same order: the same value gradients to the bit
        assert torch.equal(frozen, full)

    @pytest.mark.parametrize("seed", [0, 1])
    def test_against_reference(self, seed):
        splats, camera, features = make_scene(seed + 20, camera=make_camera(rotate=seed == 1), channels=16)
        gen = torch.Generator().manual_seed(seed)
        upstream = torch.randn(camera.height, camera.width, 16, generator=gen)
        grads = {}
        for backend in ("numba", "reference"):
            feats = features.clone().requires_grad_()
            out = render(splats, camera, feats, backend=backend)
            (grads[backend],) = torch.autograd.grad((out.features * upstream).sum(), feats)
        assert rel_err(grads["numba"], grads["reference"]) <= 1e-4

    def test_every_column_and_unblended_pixels(self):
        # the kernel's tail columns (the normals' values, after the features) through the autograd function
        # directly, against the full backward; a non-finite upstream gradient at pixels no splat blended
        # changes nothing (the full backward ignores it there as well)
        from trace3d.render.kernels.binning import Binning
        from trace3d.render.kernels.rasterize import _Rasterize
        from trace3d.render.kernels.tiles import pack_geometry

        splats, camera, features = make_scene(9, n=60, channels=5)
        proj = project(splats, camera, 0.01)
        binning = Binning(proj, camera.width, camera.height)
        vals = torch.cat([features, proj.normals], 1)
        gen = torch.Generator().manual_seed(9)
        up_head = torch.randn(camera.height, camera.width, 5, generator=gen)
        up_tail = torch.randn(camera.height, camera.width, 3, generator=gen)
        grads = {}
        for frozen in (True, False):
            geom = pack_geometry(proj).detach()
            geom = geom if frozen else geom.requires_grad_()
            v = vals.detach().clone().requires_grad_()
            head, tail, _, _, final_t, _, _ = _Rasterize.apply(geom, v, binning, 0.01, 5, None, None)
            empty = (final_t == 1.0).detach()
            assert bool(empty.any()) and not bool(empty.all())
            h = torch.where(empty[..., None], torch.full_like(up_head, float("nan")), up_head)
            (grads[frozen],) = torch.autograd.grad((head * h).sum() + (tail * up_tail).sum(), v)
        assert bool(torch.isfinite(grads[True]).all()) and float(grads[True][:, 5:].abs().max()) > 0.01
        assert torch.equal(grads[True], grads[False])


def test_backward_bits_do_not_depend_on_the_thread_count():
    """The backward deals its tiles to a fixed number of gradient buffers (``gradient_buffers``), not
    one per thread: the same gradients to the bit at 1 and 2 numba threads, which lets the fit and the
    refine run as 1-thread jobs with the files of a 2-thread run. Another buffer count sums in another
    order: the same gradients up to rounding, not to the bit."""
    import numba

    from trace3d.render import GRADIENT_BUFFERS, gradient_buffer_count, gradient_buffers

    # 80x64 pixels: 5x4 tiles, most splats on several of them
    splats, camera, features = make_scene(31, n=300, camera=make_camera(80, 64, focal=60.0))
    before = numba.get_num_threads()

    def grads(threads: int, buffers: int = 0):
        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
        try:
            with gradient_buffers(buffers):
                sp, feats = with_grad(splats, features)
                out = render(sp, camera, feats, with_distortion=True, backend="numba")
                weighted_loss(out).backward()
                return [t.grad.clone() for t in (*sp, feats)]
        finally:
            numba.set_num_threads(before)

    one, two = grads(1), grads(2)
    assert all(torch.equal(a, b) for a, b in zip(one, two))
    assert gradient_buffer_count() == GRADIENT_BUFFERS  # the context restored it
    three = grads(1, 3)
    assert max(rel_err(b, a) for a, b in zip(one, three)) <= 1e-5
    assert not all(torch.equal(a, b) for a, b in zip(one, three))


@pytest.mark.parametrize("n_chunks", [1, 2, 3])
def test_backward_chunk_sum_matches_numpy(n_chunks):
    """The backward's per-worker buffers, summed and split in one numba pass, against numpy's sum."""
    from trace3d.render.kernels.backward import sum_chunks
    from trace3d.render.kernels.tiles import GEOM_GRAD_COLS

    grads = np.random.default_rng(n_chunks).normal(size=(n_chunks, 57, GEOM_GRAD_COLS + 4)).astype(np.float32)
    g_geom, g_vals = sum_chunks(grads)
    total = grads.sum(axis=0)
    np.testing.assert_allclose(g_geom, total[:, :GEOM_GRAD_COLS], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(g_vals, total[:, GEOM_GRAD_COLS:], rtol=1e-6, atol=1e-6)
    assert g_geom.flags.c_contiguous and g_vals.shape == (57, 4)


@pytest.mark.parametrize("n_chunks", [1, 2, 3])
def test_value_chunk_sum_matches_numpy(n_chunks):
    """The values-only backward's per-worker buffers summed in chunk order, the columns nobody asked for zero."""
    from trace3d.render.kernels.backward_values import sum_value_chunks

    grads = np.random.default_rng(n_chunks).normal(size=(n_chunks, 57, 5)).astype(np.float32)
    out = sum_value_chunks(grads, 8)
    assert out.shape == (57, 8) and not out[:, 5:].any()
    np.testing.assert_allclose(out[:, :5], grads.sum(axis=0), rtol=1e-6, atol=1e-6)


def test_radix_argsort_is_numpys_stable_order():
    """The binning's depth order (radix sort of float32 bits) is numpy's stable argsort exactly: random
    depths, many ties, negative values, denormals, +-0.0 (equal for numpy), NaNs (last) and infinities."""
    from trace3d.render.kernels.binning import stable_argsort_f32

    rng = np.random.default_rng(11)
    special = np.array([0.0, -0.0, 1.0, -1.0, np.nan, -np.nan, np.inf, -np.inf, 0.0, np.nan, -0.0, 2.0], np.float32)
    cases = [rng.uniform(0.5, 6.0, 20000), rng.standard_normal(5000), rng.integers(0, 5, 3000),
             rng.standard_normal(2000) * 1e-40, special, np.tile(special, 50)[rng.permutation(600)], np.zeros(0),
             np.ones(1)]
    for keys in cases:
        keys = np.asarray(keys, np.float32)
        np.testing.assert_array_equal(stable_argsort_f32(keys), np.argsort(keys, kind="stable"))


def test_row_gather_equals_numpy_fancy_indexing():
    from trace3d.render.kernels.binning import gather_rows_as

    rng = np.random.default_rng(0)
    boxes = rng.integers(-5, 500, (3000, 4))
    geom = rng.normal(size=(3000, 16)).astype(np.float32)
    rows = rng.integers(0, 3000, 20000)
    assert np.array_equal(gather_rows_as(boxes, rows, np.int32), boxes[rows].astype(np.int32))
    out = gather_rows_as(geom, rows, np.float32)
    assert out.dtype == np.float32 and out.flags.c_contiguous and np.array_equal(out, geom[rows])
    assert gather_rows_as(geom, rows[:0], np.float32).shape == (0, 16)


# ----------------------------------------------------------------------------------------------
# A twin that shares no projection code with the renderer: brute force, per pixel, from the 2DGS paper
# ----------------------------------------------------------------------------------------------


def _rotation_from_quaternion(q: torch.Tensor) -> torch.Tensor:
    """[N, 4] (w, x, y, z), any norm -> [N, 3, 3] rotation matrices (the unit quaternion's)."""
    w, x, y, z = (q / q.norm(dim=1, keepdim=True)).unbind(1)
    return torch.stack([
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], 1)


def brute_force_render(splats: Splats, camera: Camera, features: torch.Tensor, background: torch.Tensor,
                       near: float = 0.01) -> dict[str, torch.Tensor]:
    """2DGS written from the paper, in float64, one ray per pixel and no tiles, boxes or ray transforms.

    Each pixel centre (x + 0.5, y + 0.5) casts the camera ray d = K^-1 (x, y, 1) (camera space, OpenCV).
    A splat is the disk through its camera-space centre p spanned by its rotated tangent axes a_u, a_v,
    scaled by s_u, s_v; the ray meets its plane at H = d (n . p) / (n . d), n = a_u x a_v, with disk
    coordinates u = (H - p) . a_u / s_u, v = (H - p) . a_v / s_v.  With the object-space low-pass filter
    of radius sqrt(2)/2 px around the projected centre m = (K p)_xy / p_z (2DGS, eq. 11),
    sigma = min((u^2 + v^2) / 2, |pixel - m|^2), alpha = min(0.99, o exp(-sigma)); the depth is H_z where
    the disk term wins and p_z where the filter does.  A pair is skipped when alpha < 1/255 or the
    depth <= near; splats whose centre is not in front of ``near`` are culled.  Splats are blended front to
    back in order of centre depth (ties by index) and a pixel stops before the splat that would take its
    transmittance below 1e-4.  Outputs as :func:`trace3d.render.render`'s: features (background added),
    alpha, depth (sum of w z), normal (sum of w n, n facing the camera) and median depth (z of the last
    blended splat whose transmittance before it is above 0.5; 0 where there is none).
    """
    dt = torch.float64
    w2c = torch.as_tensor(camera.world_to_camera, dtype=dt)
    K = torch.as_tensor(camera.K, dtype=dt)
    means, quats, scales, opac = (t.to(dt) for t in splats)
    feats = features.to(dt)
    p = means @ w2c[:3, :3].T + w2c[:3, 3]  # [N, 3] centres, camera space
    axes = w2c[:3, :3][None] @ _rotation_from_quaternion(quats.to(dt))  # [N, 3, 3]: a_u, a_v, a_w as columns
    a_u, a_v = axes[:, :, 0], axes[:, :, 1]
    n_plane = torch.linalg.cross(a_u, a_v)
    facing = torch.where(((axes[:, :, 2] * p).sum(1) > 0)[:, None], -axes[:, :, 2], axes[:, :, 2])
    m = (p @ K.T)[:, :2] / p[:, 2:3]
    ys, xs = torch.meshgrid(torch.arange(camera.height, dtype=dt) + 0.5, torch.arange(camera.width, dtype=dt) + 0.5,
                            indexing="ij")
    pix = torch.stack([xs.flatten(), ys.flatten()], 1)  # [P, 2]
    rays = torch.cat([pix, torch.ones(len(pix), 1, dtype=dt)], 1) @ torch.linalg.inv(K).T  # [P, 3], z = 1
    c = feats.shape[1]
    out_f = torch.zeros(len(pix), c, dtype=dt)
    out_a = torch.zeros(len(pix), dtype=dt)
    out_z = torch.zeros(len(pix), dtype=dt)
    out_n = torch.zeros(len(pix), 3, dtype=dt)
    out_med = torch.zeros(len(pix), dtype=dt)
    trans = torch.ones(len(pix), dtype=dt)
    stopped = torch.zeros(len(pix), dtype=torch.bool)
    depth_c = p[:, 2].detach()
    order = [int(k) for k in torch.sort(depth_c, stable=True).indices if float(depth_c[k]) > near]
    for k in order:
        lam = (n_plane[k] @ p[k]) / (rays @ n_plane[k])  # ray parameter of the plane hit
        hit = rays * lam[:, None]
        u = ((hit - p[k]) @ a_u[k]) / scales[k, 0]
        v = ((hit - p[k]) @ a_v[k]) / scales[k, 1]
        s_disk = 0.5 * (u * u + v * v)
        s_filter = ((pix - m[k]) ** 2).sum(1)
        disk = s_disk <= s_filter
        z = torch.where(disk, hit[:, 2], p[k, 2].expand(len(pix)))
        alpha = torch.clamp(opac[k] * torch.exp(-torch.minimum(s_disk, s_filter)), max=0.99)
        take = (alpha >= 1.0 / 255.0) & (z > near) & ~stopped
        stopped = stopped | (take & (trans * (1.0 - alpha) < 1e-4))
        take = take & ~stopped
        w = torch.where(take, alpha * trans, torch.zeros_like(alpha))
        out_med = torch.where(take & (trans > 0.5), z, out_med)
        out_f = out_f + w[:, None] * feats[k]
        out_a = out_a + w
        out_z = out_z + w * z
        out_n = out_n + w[:, None] * facing[k]
        trans = torch.where(take, trans * (1.0 - alpha), trans)
    out_f = out_f + trans[:, None] * background.to(dt)
    h, wd = camera.height, camera.width
    return {"features": out_f.reshape(h, wd, c), "alpha": out_a.reshape(h, wd), "depth": out_z.reshape(h, wd),
            "normal": out_n.reshape(h, wd, 3), "median_depth": out_med.reshape(h, wd)}


@pytest.mark.parametrize("seed,rotate", [(3, False), (4, True)])
def test_kernels_match_a_brute_force_per_pixel_twin(seed, rotate):
    """render() (projection, binning, tile kernels, hand-written backward) against
    :func:`brute_force_render`, which computes every pixel's ray-splat intersection from the world-space
    parameters and shares no code with trace3d.render: the outputs and the gradients of all five inputs.
    An error in the projection or its constants moves both the kernels and the dense reference, so only
    a twin like this one can catch it."""
    camera = make_camera(rotate=rotate)
    splats, camera, features = make_scene(seed, n=60, camera=camera)
    background = torch.tensor([0.2, 0.5, 0.7])
    names = ("features", "alpha", "depth", "normal", "median_depth")
    results = {}
    for kind in ("kernel", "brute"):
        sp, feats = with_grad(splats, features, torch.float32)
        if kind == "kernel":
            out = render(sp, camera, feats, background)
            outs = {name: getattr(out, name) for name in names}
        else:
            outs = brute_force_render(sp, camera, feats, background)
        gen = torch.Generator().manual_seed(seed)
        loss = sum((outs[name].double() * torch.randn(outs[name].shape, generator=gen, dtype=torch.float64)).sum()
                   for name in names)
        grads = torch.autograd.grad(loss, [*sp, feats])
        results[kind] = ({name: outs[name].detach().double() for name in names}, [g.double() for g in grads])
    (k_out, k_grads), (b_out, b_grads) = results["kernel"], results["brute"]
    assert float(b_out["alpha"].max()) > 0.8 and float((b_out["alpha"] > 0.01).double().mean()) > 0.2
    for name in names:
        # float32 kernels against float64, every pixel (measured: at most 4e-6 of the largest value)
        err = float((k_out[name] - b_out[name]).abs().max())
        assert err <= 2e-5 * float(b_out[name].abs().max()) + 1e-6, (name, err)
    for i, (a, b) in enumerate(zip(k_grads, b_grads)):  # means, quats, scales, opacities, features
        assert float(b.abs().max()) > 1.0, i
        assert rel_err(a, b) < 2e-4, (i, rel_err(a, b))  # measured: at most 3.3e-5


def test_frozen_view_gives_the_bits_of_render_and_trace():
    """FrozenView (a view's projection and tile lists built once, for self-prompting's many renders and
    traces of the same views) against render() and trace(), which build both on every call."""
    from trace3d.render import trace
    from trace3d.render.core import FrozenView

    splats, camera, _ = make_scene(41, n=300, camera=make_camera(80, 64, focal=60.0))
    gen = torch.Generator().manual_seed(41)
    view = FrozenView(splats, camera)
    assert view.rows is not None and 0 < view.seen.size < 300 and view.nbytes > 0
    seen = Splats(*(t.index_select(0, torch.from_numpy(view.seen)) for t in splats))
    everything = FrozenView(seen, camera)  # every splat seen: no row selection
    assert everything.rows is None
    for v, sp in ((view, splats), (everything, seen)):
        n = sp.means.shape[0]
        for channels in (1, 5):
            f = torch.rand(n, channels, generator=gen)
            assert torch.equal(v.render_features(f), render(sp, camera, f, backend="numba").features)
        labels = torch.randint(-1, 4, (camera.height, camera.width), generator=gen)
        a, b = v.trace(labels, 4), trace(sp, camera, labels, 4)
        assert a.shape == b.shape and a.values().numel() > 100
        assert torch.equal(a.indices(), b.indices()) and torch.equal(a.values(), b.values())
        # the binning is reused: a second render of the same features is the same again
        assert torch.equal(v.render_features(f), v.render_features(f))
