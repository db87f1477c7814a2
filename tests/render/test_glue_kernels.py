"""The fused numba glue kernels (camera points, splat frames, SH colours) against their torch twins."""

import numpy as np
import pytest
import torch

from trace3d.render.kernels import glue as gk
from trace3d.render.projection import camera_tensors
from trace3d.scene import Camera


def _camera(seed=0):
    rng = np.random.default_rng(seed)
    from trace3d.geometry import quat_to_rotmat

    R = quat_to_rotmat(torch.as_tensor(rng.normal(size=4))).numpy()
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = rng.normal(size=3) * 0.3
    K = np.array([[90.0, 0.7, 41.0], [0.0, 85.0, 33.0], [0.0, 0.0, 1.0]])  # skew, to catch K^T slips
    return Camera(name="c", split="train", width=80, height=64, K=K, world_to_camera=w2c)


def _frames_inputs(n, dtype, seed=0):
    g = torch.Generator().manual_seed(seed)
    quats = (torch.randn(n, 4, generator=g, dtype=torch.float64) * 1.7).to(dtype)  # not unit length
    scales = torch.rand(n, 2, generator=g, dtype=torch.float64).to(dtype) * 0.2 + 0.01
    means2d = (torch.rand(n, 2, generator=g, dtype=torch.float64) * 80).to(dtype)
    z = (torch.rand(n, generator=g, dtype=torch.float64) * 4 + 0.5).to(dtype)
    p_cam = torch.randn(n, 3, generator=g, dtype=torch.float64).to(dtype)  # both sides of every disk
    return [t.requires_grad_() for t in (quats, scales, means2d, z)], p_cam


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-10), (torch.float32, 1e-4)])
def test_splat_frames_match_torch_twin(dtype, tol):
    cam = _camera()
    K, R, _ = camera_tensors(cam, torch.device("cpu"), dtype)
    (q, s, m, z), p_cam = _frames_inputs(300, dtype)
    outs = gk.splat_frames(q, s, m, z, p_cam, K, R)
    refs = gk.splat_frames_torch(q, s, m, z, p_cam, K, R)
    for a, b in zip(outs, refs):
        torch.testing.assert_close(a, b, rtol=tol, atol=tol)
    g = torch.Generator().manual_seed(5)
    ups = [torch.randn(o.shape, generator=g, dtype=torch.float64).to(dtype) for o in outs]
    grads = torch.autograd.grad(sum((o * u).sum() for o, u in zip(outs, ups)), (q, s, m, z))
    grads_ref = torch.autograd.grad(sum((o * u).sum() for o, u in zip(refs, ups)), (q, s, m, z))
    for name, a, b in zip(("quats", "scales", "means2d", "z"), grads, grads_ref):
        scale = float(b.abs().max())
        assert float((a - b).abs().max()) <= tol * 10 * max(scale, 1.0), name


def test_splat_frames_partial_upstream_and_gradcheck():
    """Only the coefficients used (as the tile kernels use them), and a finite-difference check."""
    cam = _camera(1)
    K, R, _ = camera_tensors(cam, torch.device("cpu"), torch.float64)
    (q, s, m, z), p_cam = _frames_inputs(6, torch.float64, seed=3)
    # only coeffs and T_w reach the loss
    _, coeffs, _ = gk.splat_frames(q, s, m, z, p_cam, K, R)
    g1 = torch.autograd.grad(coeffs.square().sum(), (q, s, m, z))
    _, coeffs_ref, _ = gk.splat_frames_torch(q, s, m, z, p_cam, K, R)
    g2 = torch.autograd.grad(coeffs_ref.square().sum(), (q, s, m, z))
    for a, b in zip(g1, g2):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9)
    assert torch.autograd.gradcheck(lambda *a: gk.splat_frames(*a, p_cam, K, R), (q, s, m, z), eps=1e-6, atol=1e-5)


def test_splat_frames_normals_face_the_camera():
    cam = _camera(2)
    K, R, _ = camera_tensors(cam, torch.device("cpu"), torch.float64)
    (q, s, m, z), p_cam = _frames_inputs(200, torch.float64, seed=4)
    _, _, normals = gk.splat_frames(q, s, m, z, p_cam, K, R)
    assert bool(((normals * p_cam).sum(-1) <= 0).all())
    torch.testing.assert_close(normals.norm(dim=-1), torch.ones(200, dtype=torch.float64))


def _points_inputs(n, dtype, seed=0):
    """World points around the camera of :func:`_camera`: most in front, some behind or inside the near plane."""
    g = torch.Generator().manual_seed(seed)
    cam = _camera(seed)
    w2c = torch.as_tensor(cam.world_to_camera, dtype=torch.float64)
    p_cam = torch.randn(n, 3, generator=g, dtype=torch.float64)
    p_cam[:, 2] = torch.rand(n, generator=g, dtype=torch.float64) * 5 - 0.8  # about 1 in 6 at z <= 0
    p_cam[:3, 2] = torch.tensor([0.01, 0.0100001, 0.0099999])  # on and beside the near plane
    means = (p_cam - w2c[:3, 3]) @ w2c[:3, :3]  # camera to world
    return cam, means.to(dtype).requires_grad_()


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-10), (torch.float32, 2e-4)])
def test_camera_points_match_torch_twin(dtype, tol):
    cam, means = _points_inputs(400, dtype)
    K, R, t = camera_tensors(cam, torch.device("cpu"), dtype)
    outs = gk.camera_points(means, K, R, t, 0.01)
    refs = gk.camera_points_torch(means, K, R, t, 0.01)
    assert not outs[0].requires_grad
    if dtype == torch.float64:  # the near-plane cases decide the same way in both
        torch.testing.assert_close(outs[1] == 1.0, refs[1] == 1.0)
    for a, b in zip(outs, refs):
        torch.testing.assert_close(a, b, rtol=tol, atol=tol)
    g = torch.Generator().manual_seed(7)
    up_z, up_m = (torch.randn(o.shape, generator=g, dtype=torch.float64).to(dtype) for o in outs[1:])
    # only means2d, only the depth, and both: each upstream path reaches the means
    for loss_of in (lambda o: (o[2] * up_m).sum(), lambda o: (o[1] * up_z).sum(),
                    lambda o: (o[1] * up_z).sum() + (o[2] * up_m).sum()):
        (ga,) = torch.autograd.grad(loss_of(gk.camera_points(means, K, R, t, 0.01)), means)
        (gb,) = torch.autograd.grad(loss_of(gk.camera_points_torch(means, K, R, t, 0.01)), means)
        assert float((ga - gb).abs().max()) <= tol * 10 * max(float(gb.abs().max()), 1.0)


def test_camera_points_near_plane_is_exclusive():
    """A centre exactly at z = near is culled (depth 1), as ``project`` culls it; just beyond is kept."""
    K = torch.tensor([[50.0, 0.0, 20.0], [0.0, 50.0, 15.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    eye, zero = torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64)
    means = torch.tensor([[0.1, 0.2, 0.01], [0.1, 0.2, 0.0100001], [0.1, 0.2, -1.0]], dtype=torch.float64)
    for fn in (gk.camera_points, gk.camera_points_torch):
        _, z_safe, m2d = fn(means, K, eye, zero, 0.01)
        assert z_safe.tolist() == [1.0, 0.0100001, 1.0]
        torch.testing.assert_close(m2d[0], torch.tensor([50 * 0.1 + 20 * 0.01, 50 * 0.2 + 15 * 0.01],
                                                        dtype=torch.float64))


def test_camera_points_gradcheck():
    cam, means = _points_inputs(12, torch.float64, seed=2)
    K, R, t = camera_tensors(cam, torch.device("cpu"), torch.float64)
    keep = means.detach()[3:]  # away from the near plane's kink
    x = keep.clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda m: gk.camera_points(m, K, R, t, 0.01)[1:], (x,), eps=1e-6, atol=1e-6)


def _sh_inputs(n, k, dtype, seed=0):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=torch.float64).to(dtype).requires_grad_()
    dc = (torch.randn(n, 1, 3, generator=g, dtype=torch.float64) * 2).to(dtype).requires_grad_()  # some clamp at 0
    rest = (torch.randn(n, k, 3, generator=g, dtype=torch.float64) * 0.5).to(dtype).requires_grad_()
    center = torch.tensor([0.1, -0.2, 0.3], dtype=dtype)
    return means, dc, rest, center


@pytest.mark.parametrize("degree", [1, 2, 3])
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-10), (torch.float32, 1e-5)])
def test_sh_colors_match_torch_twin(degree, dtype, tol):
    means, dc, rest, center = _sh_inputs(1500, 15, dtype, seed=degree)
    out = gk.sh_colors(means, dc, rest, center, degree)
    ref = gk.sh_colors_torch(means, dc, rest, center, degree)
    torch.testing.assert_close(out, ref, rtol=tol, atol=tol)
    assert bool((ref == 0).any()) and bool((ref > 0).any())  # the clamp is exercised
    up = torch.randn(out.shape, generator=torch.Generator().manual_seed(1), dtype=dtype)
    grads = torch.autograd.grad((out * up).sum(), (means, dc, rest))
    grads_ref = torch.autograd.grad((ref * up).sum(), (means, dc, rest))
    for name, a, b in zip(("means", "dc", "rest"), grads, grads_ref):
        torch.testing.assert_close(a, b, rtol=tol * 10, atol=tol * 10, msg=name)
    # coefficients beyond the degree get no gradient
    assert bool((grads[2][:, (degree + 1) ** 2 - 1:] == 0).all())


def test_sh_gradcheck():
    means, dc, rest, center = _sh_inputs(5, 15, torch.float64, seed=9)
    with torch.no_grad():
        dc += 3.0  # away from the clamp's kink
    assert torch.autograd.gradcheck(lambda a, b, c: gk.sh_colors(a, b, c, center, 3), (means, dc, rest),
                                    eps=1e-6, atol=1e-6)


def test_fused_switch_and_determinism():
    means, dc, rest, center = _sh_inputs(3000, 15, torch.float32)
    out = gk.sh_colors(means, dc, rest, center, 3)
    g1 = torch.autograd.grad(out.sum(), (means, rest))
    g2 = torch.autograd.grad(gk.sh_colors(means, dc, rest, center, 3).sum(), (means, rest))
    for a, b in zip(g1, g2):
        assert torch.equal(a, b)
    gk.set_fused(False)
    try:
        assert not gk.use_fused(means)
        assert out.grad_fn.name() != gk.sh_colors(means, dc, rest, center, 3).grad_fn.name()
    finally:
        gk.set_fused(True)
    assert gk.use_fused(means) and not gk.use_fused(means.to(torch.float16))


def test_render_uses_fused_path_and_matches_twin():
    """A whole render (projection + SH colours + tile kernels) agrees with the torch glue."""
    from trace3d.gaussians import GaussianModel
    from trace3d.render import render

    g = torch.Generator().manual_seed(0)
    n = 400
    cam = _camera(3)
    c2w = np.linalg.inv(cam.world_to_camera)
    means = torch.as_tensor(c2w[:3, :3] @ np.stack([np.zeros(n), np.zeros(n), np.full(n, 3.0)]) + c2w[:3, 3:4]).T
    means = means.float() + torch.randn(n, 3, generator=g) * 0.6
    model = GaussianModel(means=means, quats=torch.randn(n, 4, generator=g),
                                       log_scales=torch.randn(n, 2, generator=g) * 0.3 - 3.0,
                                       opacity_logits=torch.randn(n, generator=g),
                                       sh_dc=torch.randn(n, 1, 3, generator=g),
                                       sh_rest=torch.randn(n, 15, 3, generator=g) * 0.3)
    results = []
    for fused in (True, False):
        gk.set_fused(fused)
        try:
            params = [t.detach().clone().requires_grad_() for t in (model.means, model.quats, model.log_scales,
                                                                      model.opacity_logits, model.sh_dc, model.sh_rest)]
            m = GaussianModel(means=params[0], quats=params[1], log_scales=params[2],
                                           opacity_logits=params[3], sh_dc=params[4], sh_rest=params[5])
            colors = m.colors(torch.as_tensor(cam.center, dtype=torch.float32), 3)
            out = render(m.splats(), cam, colors)
            loss = out.features.square().sum() + out.normal.sum() + out.depth.sum()
            results.append((out.features.detach(), torch.autograd.grad(loss, params)))
        finally:
            gk.set_fused(True)
    assert float(results[0][0].abs().sum()) > 0
    torch.testing.assert_close(results[0][0], results[1][0], rtol=1e-4, atol=1e-5)
    for a, b in zip(results[0][1], results[1][1]):
        torch.testing.assert_close(a, b, rtol=1e-3, atol=1e-4 * max(1.0, float(b.abs().max())))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_sh_colors_of_rows_equal_the_full_colours_rows(dtype):
    """Colours of selected rows only: the same numbers as those rows of the full evaluation, and the
    same gradients (bit for bit) as the full evaluation with zero upstream outside the rows."""
    means, dc, rest, center = _sh_inputs(2000, 15, dtype, seed=4)
    rows = torch.as_tensor(np.sort(np.random.default_rng(0).choice(2000, 600, replace=False)))
    full = gk.sh_colors(means, dc, rest, center, 3)
    part = gk.sh_colors(means, dc, rest, center, 3, rows)
    assert part.shape == (600, 3) and torch.equal(part, full[rows])
    up = torch.randn(600, 3, generator=torch.Generator().manual_seed(2), dtype=dtype)
    up_full = torch.zeros(2000, 3, dtype=dtype)
    up_full[rows] = up
    g_part = torch.autograd.grad((part * up).sum(), (means, dc, rest))
    g_full = torch.autograd.grad((full * up_full).sum(), (means, dc, rest))
    for name, a, b in zip(("means", "dc", "rest"), g_part, g_full):
        assert torch.equal(a, b), name
    others = torch.ones(2000, dtype=torch.bool)
    others[rows] = False
    assert bool((g_part[2][others] == 0).all()) and bool((g_part[2][rows] != 0).any())
    # the torch twin takes rows too
    twin = gk.sh_colors_torch(means[rows], dc[rows], rest[rows], center, 3)
    torch.testing.assert_close(part, twin, rtol=1e-5, atol=1e-5)


def _visible_and_hidden_model(n=500, seed=0):
    """A model of which part faces ``_camera(3)`` and part sits behind it."""
    from trace3d.gaussians import GaussianModel

    g = torch.Generator().manual_seed(seed)
    cam = _camera(3)
    c2w = np.linalg.inv(cam.world_to_camera)
    depth = np.where(np.arange(n) % 3 == 0, -2.0, 3.0)  # a third behind the camera
    means = torch.as_tensor(c2w[:3, :3] @ np.stack([np.zeros(n), np.zeros(n), depth]) + c2w[:3, 3:4]).T
    means = means.float() + torch.randn(n, 3, generator=g) * 0.8
    model = GaussianModel(means=means, quats=torch.randn(n, 4, generator=g),
                          log_scales=torch.randn(n, 2, generator=g) * 0.3 - 3.0,
                          opacity_logits=torch.randn(n, generator=g),
                          sh_dc=torch.randn(n, 1, 3, generator=g), sh_rest=torch.randn(n, 15, 3, generator=g) * 0.3)
    return model, cam


@pytest.mark.parametrize("backend", ["numba", "reference"])
def test_render_with_features_of_rows_is_the_same_render(backend):
    """render() with a features function (what the training loop passes: colours of the visible
    splats only) gives the same images and gradients as with the [N, C] tensor; the numba back end
    asks only for the visible rows."""
    from trace3d.gaussians import GaussianModel
    from trace3d.render import render

    model, cam = _visible_and_hidden_model()
    center = torch.as_tensor(cam.center, dtype=torch.float32)
    results, asked = [], []
    for by_rows in (False, True):
        params = [t.detach().clone().requires_grad_() for t in (model.means, model.quats, model.log_scales,
                                                                  model.opacity_logits, model.sh_dc, model.sh_rest)]
        m = GaussianModel(means=params[0], quats=params[1], log_scales=params[2], opacity_logits=params[3],
                          sh_dc=params[4], sh_rest=params[5])

        def features(rows, m=m):
            asked.append(None if rows is None else rows.clone())
            return m.colors(center, 3, rows)

        out = render(m.splats(), cam, features if by_rows else m.colors(center, 3), backend=backend)
        loss = out.features.square().sum() + out.normal.sum() + out.depth.sum() + out.median_depth.sum()
        grads = torch.autograd.grad(loss, params + [out.means2d] if backend == "numba" else params)
        results.append(([out.features, out.alpha, out.depth, out.normal, out.median_depth, out.radii, out.visible],
                        grads))
    visible = results[0][0][6]
    assert 0 < int(visible.sum()) < len(model)
    if backend == "numba":
        assert torch.equal(asked[0], torch.nonzero(visible).squeeze(1))
    else:
        assert asked[0] is None
    for a, b in zip(results[0][0], results[1][0]):
        assert torch.equal(a, b)
    for a, b in zip(results[0][1], results[1][1]):
        assert torch.equal(a, b)


def test_render_rejects_features_function_of_wrong_shape():
    from trace3d.errors import Trace3DError
    from trace3d.render import render

    model, cam = _visible_and_hidden_model(n=60)
    with pytest.raises(Trace3DError, match=r"features\(rows\)"):
        render(model.splats(), cam, lambda rows: torch.zeros(len(model) + 1, 3))


def test_visible_mask_is_the_projections_visible_bit_for_bit():
    """The one-pass visibility test of compact gradients equals project(...).visible exactly: splats
    behind, beside and in front of the camera, centres right at the near plane (float32 rounding of
    the depth decides), disks crossing the camera plane, opacities around the 1/255 cut-off and
    footprints at the image border."""
    from trace3d.render import Splats, project
    from trace3d.render.projection import visible_mask

    cam = _camera(2)
    n = 6000
    g = torch.Generator().manual_seed(7)
    w2c = np.asarray(cam.world_to_camera)
    # camera-space positions, then to the world
    p_cam = torch.cat([torch.rand(n, 2, generator=g, dtype=torch.float64) * 4 - 2,
                       torch.rand(n, 1, generator=g, dtype=torch.float64) * 5 - 1], 1)
    p_cam[:300, 2] = 0.01 + (torch.rand(300, generator=g, dtype=torch.float64) - 0.5) * 2e-8  # at the near plane
    means = (p_cam - torch.as_tensor(w2c[:3, 3])) @ torch.as_tensor(w2c[:3, :3])
    quats = torch.randn(n, 4, generator=g)
    scales = torch.rand(n, 2, generator=g) * 0.3 + 1e-3
    scales[:500] *= 20  # large disks, many cross the camera plane
    opac = torch.rand(n, generator=g)
    opac[500:900] = 1 / 255 + (torch.rand(400, generator=g) - 0.5) * 1e-5
    splats = Splats(means.float(), quats, scales, opac)
    expected = project(splats, cam, 0.01).visible
    ours = visible_mask(splats, cam, 0.01)
    assert ours.dtype == torch.bool and torch.equal(ours, expected)
    assert 0.1 * n < int(expected.sum()) < 0.9 * n
    # the float64 path is the projection itself
    splats64 = Splats(*(t.double() for t in splats))
    assert torch.equal(visible_mask(splats64, cam, 0.01), project(splats64, cam, 0.01).visible)


def test_visible_mask_at_the_image_border_is_the_projections_bit_for_bit():
    """The visibility pass skips the exact test for Gaussians whose ball lies outside the image's
    frustum widened by PREFILTER_MARGIN pixels: that skip must never drop a visible Gaussian. Small
    opaque splats (footprints the size of the low-pass filter) and disks of every size are placed
    with their centres around the image border, from 8 pixels inside to 8 pixels outside, at depths
    from just past the near plane to far away, under a camera with skew."""
    from trace3d.render import Splats, project
    from trace3d.render.projection import visible_mask

    cam = _camera(3)
    n = 20000
    g = torch.Generator().manual_seed(11)
    K = torch.as_tensor(np.asarray(cam.K))
    # a pixel position near one of the four borders, then back-projected to a random depth
    t = torch.rand(n, generator=g, dtype=torch.float64)
    off = (torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * 16.0
    side = torch.randint(0, 4, (n,), generator=g)
    u = torch.where(side == 0, off, torch.where(side == 1, cam.width + off, t * cam.width))
    v = torch.where(side == 2, off, torch.where(side == 3, cam.height + off, t * cam.height))
    depth = 0.02 + torch.rand(n, generator=g, dtype=torch.float64) ** 2 * 8.0
    rays = torch.linalg.solve(K, torch.stack([u, v, torch.ones(n, dtype=torch.float64)]))  # [3, n]
    p_cam = (rays * depth).T
    w2c = np.asarray(cam.world_to_camera)
    means = (p_cam - torch.as_tensor(w2c[:3, 3])) @ torch.as_tensor(w2c[:3, :3])
    quats = torch.randn(n, 4, generator=g)
    scales = 10.0 ** (torch.rand(n, 2, generator=g) * 3.5 - 4.0)  # 1e-4 .. 0.3
    opac = torch.where(torch.rand(n, generator=g) < 0.5, torch.full((n,), 0.999), torch.rand(n, generator=g))
    splats = Splats(means.float(), quats, scales, opac)
    expected = project(splats, cam, 0.01).visible
    assert torch.equal(visible_mask(splats, cam, 0.01), expected)
    # both outcomes are common just outside the border (the case the widened frustum must keep)
    outside = ((u < 0) | (u > cam.width) | (v < 0) | (v > cam.height)) & (off.abs() < 3.0)
    assert 0.05 < float(expected[outside].float().mean()) < 0.95


def test_visible_mask_rejects_intrinsics_without_last_row_0_0_1():
    """The visibility pass checks K as the projection does (its camera arrays are cached, the check
    with them), naming the camera."""
    from trace3d.errors import Trace3DError
    from trace3d.render import Splats
    from trace3d.render.projection import visible_mask

    cam = _camera(4)
    bad = Camera(name="tilted", split="train", width=cam.width, height=cam.height,
                 K=np.asarray(cam.K) + np.array([[0.0, 0, 0], [0, 0, 0], [0.1, 0, 0]]),
                 world_to_camera=cam.world_to_camera)
    splats = Splats(torch.zeros(3, 3), torch.tensor([[1.0, 0, 0, 0]] * 3), torch.full((3, 2), 0.1),
                    torch.full((3,), 0.5))
    with pytest.raises(Trace3DError, match=r"camera 'tilted': the renderer needs K with last row \(0, 0, 1\)"):
        visible_mask(splats, bad, 0.01)


def test_frustum_planes_bound_the_widened_image():
    """frustum_planes: a point that projects inside the image widened by the margin is inside every
    plane, one that projects beyond it is outside one; the ball test takes the radius."""
    from trace3d.render.projection import _outside_frustum, frustum_planes

    cam = _camera(1)
    planes = frustum_planes(np.asarray(cam.K), cam.width, cam.height, 4.0)
    k_inv = np.linalg.inv(np.asarray(cam.K))
    for u, v, inside in ((-3.9, 20.0, True), (-4.1, 20.0, False), (cam.width + 3.9, 5.0, True),
                         (cam.width + 4.1, 5.0, False), (30.0, -4.1, False), (30.0, cam.height + 3.9, True),
                         (40.0, 30.0, True), (-50.0, -50.0, False)):
        p = k_inv @ np.array([u, v, 1.0]) * 2.5
        assert bool(np.all(planes @ p >= 0)) == inside, (u, v)
        assert _outside_frustum(p[0], p[1], p[2], planes, 0.0) == (not inside), (u, v)
        assert not _outside_frustum(p[0], p[1], p[2], planes, 10.0)  # a ball that wide reaches in
    assert not _outside_frustum(np.nan, 0.0, 1.0, planes, 0.0)  # undecided: left to the exact test


def test_background_blended_in_the_rasterizer_is_torchs_blend_bit_for_bit():
    """A fixed colour background is blended inside the rasterizer; a background that needs a
    gradient takes the torch line. Both give the same images and the same gradients of every input,
    with the alpha and features both reaching the loss (two gradients into the transmittance)."""
    from trace3d.gaussians import GaussianModel
    from trace3d.render import render

    model, cam = _visible_and_hidden_model(seed=4)
    center = torch.as_tensor(cam.center, dtype=torch.float32)
    up = torch.randn(cam.height, cam.width, 3, generator=torch.Generator().manual_seed(1))
    results = []
    for differentiable_background in (False, True):
        params = [t.detach().clone().requires_grad_() for t in (model.means, model.quats, model.log_scales,
                                                                  model.opacity_logits, model.sh_dc, model.sh_rest)]
        m = GaussianModel(means=params[0], quats=params[1], log_scales=params[2], opacity_logits=params[3],
                          sh_dc=params[4], sh_rest=params[5])
        background = torch.tensor([0.3, 0.55, 0.9]).requires_grad_(differentiable_background)
        out = render(m.splats(), cam, lambda rows, m=m: m.colors(center, 3, rows), background)
        loss = (out.features * up).sum() + out.alpha.square().sum() + out.normal.sum()
        results.append((out.features.detach(), torch.autograd.grad(loss, params)))
    assert torch.equal(results[0][0], results[1][0])
    assert bool((results[0][0] != 0).any())
    for a, b in zip(results[0][1], results[1][1]):
        assert torch.equal(a, b)
    # 16 channels: blended inside only when the background is zero (as lifting renders)
    feats = torch.rand(len(model), 16, generator=torch.Generator().manual_seed(2))
    up16 = torch.randn(cam.height, cam.width, 16, generator=torch.Generator().manual_seed(3))
    for value in (0.0, 0.4):
        results = []
        for differentiable_background in (False, True):
            f = feats.clone().requires_grad_()
            means = model.means.detach().clone().requires_grad_()
            background = torch.full((16,), value).requires_grad_(differentiable_background)
            out = render(model.splats()._replace(means=means), cam, f, background)
            loss = (out.features * up16).sum() + out.alpha.square().sum()
            results.append((out.features.detach(), torch.autograd.grad(loss, (f, means))))
        assert torch.equal(results[0][0], results[1][0])
        for a, b in zip(results[0][1], results[1][1]):
            assert torch.equal(a, b)
