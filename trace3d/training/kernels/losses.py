"""Fused numba loss kernels (forward + analytic backward) for the training loss: SSIM, and the
normal-consistency term with the depth map's normals (at the end of this module).

:func:`trace3d.training.losses.ssim` in torch builds five statistics maps, blurs them with two grouped 1D
convolutions and combines them in about twenty elementwise operations, each a full-image temporary
with its own autograd node, on one thread (the fit runs torch single-threaded).  At an LLFF-sized
504x378 frame that was the largest phase outside the rasterizer (``trace3d bench fit``).  Here the
same quantity is one parallel pass forward and one backward:

- forward: blur x, y, x^2, y^2, xy separably (11-tap Gaussian, sigma 1.5, zero padding: the "same"
  convolution of the torch version), then S = (2 mx my + C1)(2 sxy + C2) / ((mx^2 + my^2 + C1)(sx + sy + C2))
  per pixel and channel, and its mean;
- backward (w.r.t. the image only; the target is data): with A1 = 2 mx my + C1, A2 = 2 sxy + C2,
  B1 = mx^2 + my^2 + C1, B2 = sx + sy + C2,

      dS/dmx  = (2 my (A2 - A1) - 2 mx S (B2 - B1)) / (B1 B2)
      dS/dexx = -S / B2
      dS/dexy = 2 A1 / (B1 B2)

  and since the window is symmetric, the transpose of the zero-padded blur is the same blur:
  dL/dx = blur(dS/dmx) + 2 x blur(dS/dexx) + y blur(dS/dexy), scaled by the upstream gradient over
  the number of values.

Each worker writes whole rows of its own output: race-free and deterministic.  Float32 images
are blurred in float32 (as the convolution), float64 in float64.  CPU only; the torch version is the
twin the tests compare with (values and gradients) and what other devices use.
"""

from __future__ import annotations

import weakref
from collections import OrderedDict

import numpy as np
import torch
from numba import njit, prange

SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2
WINDOW = 11
SIGMA = 1.5


def _window(dtype) -> np.ndarray:
    coords = np.arange(WINDOW, dtype=np.float64) - (WINDOW - 1) / 2.0
    g = np.exp(-(coords**2) / (2.0 * SIGMA**2))
    return (g / g.sum()).astype(dtype)


@njit(cache=True, inline="always")
def _blur_column(src, p, y, g, row):
    """The vertical pass of row y of plane p of src [M, H, W] into row [W]: taps g[k] on rows y + k - r,
    rows outside the image skipped (zero padding), added in k order from zero.

    For an interior row of the 11-tap window the taps are one expression per column instead of one
    pass over the row per tap (about half the time, measured); each value gets the same additions in
    the same order, so the result is the same to the bit (tested)."""
    h, w = src.shape[1], src.shape[2]
    r = g.shape[0] // 2
    uw = np.uint64(w)
    zero = src.dtype.type(0.0)
    if g.shape[0] == WINDOW and y >= r and y + r < h:
        s0, s1, s2, s3 = src[p, y - 5], src[p, y - 4], src[p, y - 3], src[p, y - 2]
        s4, s5, s6, s7 = src[p, y - 1], src[p, y], src[p, y + 1], src[p, y + 2]
        s8, s9, s10 = src[p, y + 3], src[p, y + 4], src[p, y + 5]
        g0, g1, g2, g3, g4, g5, g6, g7, g8, g9, g10 = g[0], g[1], g[2], g[3], g[4], g[5], g[6], g[7], g[8], g[9], g[10]
        for x in range(uw):
            acc = zero
            acc += g0 * s0[x]
            acc += g1 * s1[x]
            acc += g2 * s2[x]
            acc += g3 * s3[x]
            acc += g4 * s4[x]
            acc += g5 * s5[x]
            acc += g6 * s6[x]
            acc += g7 * s7[x]
            acc += g8 * s8[x]
            acc += g9 * s9[x]
            acc += g10 * s10[x]
            row[x] = acc
        return
    for x in range(uw):
        row[x] = zero
    for k in range(g.shape[0]):
        yy = y + k - r
        if yy < 0 or yy >= h:
            continue
        gk = g[k]
        srow = src[p, yy]
        for x in range(uw):
            row[x] += gk * srow[x]


@njit(cache=True, inline="always")
def _blur_row(trow, g, row):
    """The horizontal pass of one row: tap k reads x + k - r, columns outside skipped, k order from zero.

    The inner loops run along the row with unsigned indices: numba then drops its negative-index
    wrap-around and the loops vectorise (about 4x faster than signed indices, measured)."""
    r = g.shape[0] // 2
    uw = np.uint64(trow.shape[0])
    for x in range(uw):
        row[x] = 0.0
    for k in range(g.shape[0]):
        gk = g[k]
        if k >= r:
            off = np.uint64(k - r)
            if off < uw:
                for x in range(uw - off):
                    row[x] += gk * trow[x + off]
        else:
            off = np.uint64(r - k)
            if off < uw:
                for x in range(uw - off):
                    row[x + off] += gk * trow[x]


_BLUR_ROWS = 8  # rows per parallel job of the blur (one scratch row each)


@njit(parallel=True, cache=True)
def _blur(src, g, out):
    """Zero-padded separable blur of every [H, W] plane of src [M, H, W] into out: each (plane, row)
    is blurred vertically into a scratch row that stays in the cache, then horizontally into out."""
    m, h, w = src.shape
    jobs = m * h
    for block in prange((jobs + _BLUR_ROWS - 1) // _BLUR_ROWS):
        scratch = np.empty(w, src.dtype)
        for job in range(block * _BLUR_ROWS, min(jobs, (block + 1) * _BLUR_ROWS)):
            p = job // h
            y = job % h
            _blur_column(src, p, y, g, scratch)
            _blur_row(scratch, g, out[p, y])


@njit(parallel=True, cache=True)
def _moment_planes(a, b, cross):
    """The planes a, a^2 (and with ``cross`` a b) [2C or 3C, H, W] of a, b [H, W, C]: the statistics the
    SSIM blurs."""
    h, w, c = a.shape
    stats = np.empty(((3 if cross else 2) * c, h, w), a.dtype)
    uw = np.uint64(w)
    for job in prange(c * h):
        ch = job // h
        i = job % h
        for j in range(uw):
            v = a[i, j, ch]
            stats[ch, i, j] = v
            stats[c + ch, i, j] = v * v
            if cross:
                stats[2 * c + ch, i, j] = v * b[i, j, ch]
    return stats


@njit(cache=True)
def _target_stats(y, g):
    """The target's blurred statistics (mean of y, mean of y^2) [2C, H, W] of y [H, W, C]: they do
    not depend on the image, so a training view computes them once (:class:`_TargetStats`).  Not
    ``parallel`` itself (it has no loop of its own; numba warned about the flag): the two kernels it
    calls are."""
    stats = _moment_planes(y, y, False)
    blurred = np.empty_like(stats)
    _blur(stats, g, blurred)
    return blurred


@njit(parallel=True, cache=True)
def _ssim_terms(x, y, ystats, g, c1, c2, two, want_grad):
    """SSIM per value of x, y [H, W, C] (ystats: :func:`_target_stats` of y) and, with want_grad, the
    three per-pixel partials (dS/dmx, dS/dexx, dS/dexy) stacked as [3C, H, W].  The constants come in
    the images' dtype, so float32 stays float32 (numba would promote a float literal to float64)."""
    h, w, c = x.shape
    uw = np.uint64(w)
    stats = _moment_planes(x, y, True)
    blurred = np.empty_like(stats)
    _blur(stats, g, blurred)
    s_map = np.empty((c, h, w), np.float64)  # the values in the images' dtype, held as float64 for the mean
    partials = np.empty((3 * c if want_grad else 0, h, w), x.dtype)
    for job in prange(c * h):
        ch = job // h
        i = job % h
        for j in range(uw):
            mx = blurred[ch, i, j]
            my = ystats[ch, i, j]
            sx = blurred[c + ch, i, j] - mx * mx
            sy = ystats[c + ch, i, j] - my * my
            sxy = blurred[2 * c + ch, i, j] - mx * my
            a1 = two * mx * my + c1
            a2 = two * sxy + c2
            b1 = mx * mx + my * my + c1
            b2 = sx + sy + c2
            s = (a1 * a2) / (b1 * b2)
            s_map[ch, i, j] = s
            if want_grad:
                den = b1 * b2
                partials[ch, i, j] = two * (my * (a2 - a1) - mx * s * (b2 - b1)) / den
                partials[c + ch, i, j] = -s / b2
                partials[2 * c + ch, i, j] = two * a1 / den
    return s_map, partials


class _TargetStats:
    """The blurred target statistics of recent targets, least recently used dropped first beyond
    ``max_bytes`` (a fit's views: 33 MB for 72 views at 160x120).  An entry is valid while its tensor
    lives unmodified (a weak reference and torch's version counter)."""

    def __init__(self, max_bytes: int = 256 << 20):
        self.max_bytes = max_bytes
        self.entries: OrderedDict[int, tuple] = OrderedDict()
        self.bytes = 0

    def get(self, target: torch.Tensor, y: np.ndarray, g: np.ndarray) -> np.ndarray:
        key = id(target)
        entry = self.entries.get(key)
        if (entry is not None and entry[0]() is target and entry[1] == target._version
                and entry[2].dtype == y.dtype and entry[2].shape[1:] == y.shape[:2]):
            self.entries.move_to_end(key)
            return entry[2]
        stats = _target_stats(y, g)
        self._drop(key)
        for k in [k for k, e in self.entries.items() if e[0]() is None]:  # targets that are gone
            self._drop(k)
        if stats.nbytes <= self.max_bytes:
            while self.entries and self.bytes + stats.nbytes > self.max_bytes:
                self._drop(next(iter(self.entries)))
            self.entries[key] = (weakref.ref(target), target._version, stats)
            self.bytes += stats.nbytes
        return stats

    def _drop(self, key: int) -> None:
        entry = self.entries.pop(key, None)
        if entry is not None:
            self.bytes -= entry[2].nbytes


_target_cache = _TargetStats()


def _ssim_forward(ctx, x: np.ndarray, y: np.ndarray, target: torch.Tensor, want_grad: bool) -> float:
    """Mean SSIM of x against y ([H, W, C] arrays of one dtype; ``target`` the tensor behind y, for
    the cache); keeps what the backward needs on ``ctx``."""
    dt = x.dtype.type
    g = _window(x.dtype)
    s_map, partials = _ssim_terms(x, y, _target_cache.get(target, y, g), g, dt(SSIM_C1), dt(SSIM_C2), dt(2.0),
                                  want_grad)
    ctx.saved = (x, y, g, partials)
    return float(s_map.mean())  # the mean in float64 (the map holds the values as float64)


def _ssim_backward(ctx, g_s, g_l1: np.float32 | None = None) -> torch.Tensor:
    """dL/dx [H, W, C] from the SSIM's upstream gradient ``g_s`` (None: no SSIM term) plus, with
    ``g_l1``, the L1 term's (its upstream gradient already divided by the value count)."""
    x, y, g, partials = ctx.saved
    want_ssim = g_s is not None
    if want_ssim:
        blurred = np.empty_like(partials)
        _blur(partials, g, blurred)
        scale = x.dtype.type(float(g_s) / x.size)
    else:
        blurred, scale = partials, x.dtype.type(0.0)
    grad = np.empty_like(x)
    _photometric_grad(x, y, blurred, scale, x.dtype.type(0.0) if g_l1 is None else g_l1, want_ssim, g_l1 is not None,
                      grad)
    return torch.from_numpy(grad)


class _FusedSSIM(torch.autograd.Function):
    @staticmethod
    def forward(ctx, image, target):
        dt = np.float64 if image.dtype == torch.float64 else np.float32
        x = np.ascontiguousarray(image.detach().numpy().astype(dt, copy=False))
        y = np.ascontiguousarray(target.detach().numpy().astype(dt, copy=False))
        return torch.tensor(_ssim_forward(ctx, x, y, target, ctx.needs_input_grad[0]), dtype=image.dtype)

    @staticmethod
    def backward(ctx, g_out):
        if not ctx.needs_input_grad[0]:
            return None, None
        return _ssim_backward(ctx, g_out), None


# ----------------------------------------------------------------------------------------------
# L1 + SSIM (+ the running PSNR's error) in one function
# ----------------------------------------------------------------------------------------------
#
# The training loop's L1 term, its SSIM and its logged PSNR all read the same image pair. Here the
# element-wise maps come from one numba pass (|x - y|, and (clamp(x, 0, 1) - y)^2 for the PSNR) and
# their means are torch's means of those same maps, so every value equals the torch composition bit
# for bit; the backward adds the L1 gradient (g / n) sgn(x - y) -- torch's MeanBackward and
# AbsBackward formulas -- to the SSIM gradient in the same pass that finishes the SSIM gradient,
# instead of four full-image autograd nodes and the sum of two image gradients.


@njit(parallel=True, cache=True)
def _error_maps(x, y, absdiff, sqerr):
    h, w, c = x.shape
    zero = x.dtype.type(0.0)
    one = x.dtype.type(1.0)
    for i in prange(h):
        for j in range(w):
            for ch in range(c):
                a = x[i, j, ch]
                b = y[i, j, ch]
                absdiff[i, j, ch] = abs(a - b)
                e = min(max(a, zero), one) - b
                sqerr[i, j, ch] = e * e


@njit(parallel=True, cache=True)
def _photometric_grad(x, y, blurred_partials, scale, l1_scale, want_ssim, want_l1, out):
    """dL/dx [H, W, C] of x, y [H, W, C]: the SSIM term ``scale * (bm + 2 x bxx + y bxy)`` from the
    blurred partials [3C, H, W] (with ``want_ssim``; the array must have that shape either way, as the
    backward's partials always do) plus the L1 term ``l1_scale * sgn(x - y)`` (with ``want_l1``).

    The sign is (d > 0) - (d < 0) as numbers, not a branch: the sign of x - y is close to random in a
    fit, and the mispredicted branches made this pass 5x slower (2.2 against 0.4 ms at 504x378, the
    same values: sgn(0) and sgn(NaN) are +0 either way).  One channel per inner loop, along a row of
    the [3C, H, W] partials."""
    h, w, c = x.shape
    uw = np.uint64(w)
    zero = x.dtype.type(0.0)
    one = x.dtype.type(1.0)
    for i in prange(h):
        for ch in range(c):
            bm = blurred_partials[ch, i]
            bxx = blurred_partials[c + ch, i]
            bxy = blurred_partials[2 * c + ch, i]
            for j in range(uw):
                a = x[i, j, ch]
                b = y[i, j, ch]
                d = a - b
                g1 = l1_scale * ((one if d > zero else zero) - (one if d < zero else zero))
                if want_ssim:
                    gs = scale * (bm[j] + (a + a) * bxx[j] + b * bxy[j])
                    out[i, j, ch] = gs + g1 if want_l1 else gs
                else:
                    out[i, j, ch] = g1


class _FusedPhotometric(torch.autograd.Function):
    @staticmethod
    def forward(ctx, image, target):
        x = np.ascontiguousarray(image.detach().numpy())
        y = np.ascontiguousarray(target.detach().numpy())
        absdiff, sqerr = np.empty_like(x), np.empty_like(x)
        _error_maps(x, y, absdiff, sqerr)
        s = _ssim_forward(ctx, x, y, target, ctx.needs_input_grad[0])
        l1 = torch.from_numpy(absdiff).mean()
        mse = torch.from_numpy(sqerr).mean()
        ctx.mark_non_differentiable(mse)
        return l1, torch.tensor(s, dtype=image.dtype), mse

    @staticmethod
    def backward(ctx, g_l1, g_s, g_mse):
        if not ctx.needs_input_grad[0]:
            return None, None
        x = ctx.saved[0]
        # torch: MeanBackward g.expand() / numel, then AbsBackward grad * sgn(x - y), in float32
        l1_scale = (np.float32(0.0) if g_l1 is None
                    else np.float32(g_l1.detach().to(torch.float32).numpy()) / np.float32(x.size))
        return _ssim_backward(ctx, g_s, l1_scale), None


def fused_photometric_applies(image: torch.Tensor, target: torch.Tensor) -> bool:
    """Whether :func:`fused_photometric` handles these inputs: float32 [H, W, C] CPU pairs of one
    shape, the target without gradient, the fused kernels switched on."""
    return image.dtype == torch.float32 and fused_ssim_applies(image, target)


def fused_photometric(image: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(mean |x - y|, SSIM(x, y), mean (clamp(x, 0, 1) - y)^2)`` of ``image`` x against ``target``
    y, the first two differentiable w.r.t. the image: the values of ``l1_loss``, :func:`fused_ssim`
    and the PSNR's error, and the gradient of any combination of the first two, bit for bit (tested)."""
    if not fused_photometric_applies(image, target):
        raise ValueError(f"fused_photometric: needs [H, W, C] CPU float32 images of one shape and a target "
                         f"without gradient, got {tuple(image.shape)} {image.dtype} and {tuple(target.shape)} "
                         f"{target.dtype}")
    return _FusedPhotometric.apply(image, target)


def fused_ssim_applies(image: torch.Tensor, target: torch.Tensor) -> bool:
    """Whether :func:`fused_ssim` handles these inputs: [H, W, C] CPU float32/float64 pairs of one
    shape, the target without gradient, the fused kernels switched on."""
    from ...render.kernels.glue import use_fused

    return (image.ndim == 3 and image.shape == target.shape and image.dtype == target.dtype
            and not target.requires_grad and use_fused(image, target))


def fused_ssim(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of ``image`` against ``target`` ([H, W, C]; differentiable w.r.t. ``image``);
    equal to :func:`trace3d.training.losses.ssim` (its twin) up to float rounding."""
    if not fused_ssim_applies(image, target):
        raise ValueError(f"fused_ssim: needs [H, W, C] CPU float32/64 images of one shape and dtype and a target "
                         f"without gradient, got {tuple(image.shape)} {image.dtype} and {tuple(target.shape)} "
                         f"{target.dtype}")
    return _FusedSSIM.apply(image, target)



# ----------------------------------------------------------------------------------------------
# Normal consistency against the depth map's normals
# ----------------------------------------------------------------------------------------------
#
# L = mean_x (1 - <n_r(x), alpha(x) N(x)>), N = normalize(dP/dy x dP/dx) by central differences of
# the back-projected depth (zero on the one-pixel border), alpha without gradient.  Backward with
# u = -alpha n_r / HW (dL/dN), c = a x b (a = dP/dy, b = dP/dx):
#   dL/dc = (u - N <N, u>) / max(|c|, eps),  dL/da = b x dL/dc,  dL/db = dL/dc x a,
# gathered to each pixel's point from its four neighbours' differences, then dL/ddepth = <ray, dL/dP>.

_NORMALIZE_EPS = 1e-12  # torch.nn.functional.normalize's default


@njit(parallel=True, cache=True)
def _ray_table(K, h, w):
    """Every pixel centre's ray through K^-1 (rx [H, W], ry [H]): the kernels below read each pixel's
    ray up to five times, and recomputing its divisions each time was most of their cost."""
    rx = np.empty((h, w), np.float64)
    ry = np.empty(h, np.float64)
    for i in prange(h):
        y = (i + 0.5 - K[1, 2]) / K[1, 1]
        ry[i] = y
        for j in range(w):
            rx[i, j] = (j + 0.5 - K[0, 2] - K[0, 1] * y) / K[0, 0]
    return rx, ry


@njit(cache=True, inline="always")
def _differences(rx, ry, depth, i, j):
    """Central differences of the back-projected points at interior pixel (i, j):
    a = P[i+1, j] - P[i-1, j], b = P[i, j+1] - P[i, j-1] (rays from :func:`_ray_table`)."""
    rx1, ry1 = rx[i, j + 1], ry[i]
    rx0, ry0 = rx[i, j - 1], ry[i]
    d1, d0 = float(depth[i, j + 1]), float(depth[i, j - 1])
    rx3, ry3 = rx[i + 1, j], ry[i + 1]
    rx2, ry2 = rx[i - 1, j], ry[i - 1]
    d3, d2 = float(depth[i + 1, j]), float(depth[i - 1, j])
    return (rx3 * d3 - rx2 * d2, ry3 * d3 - ry2 * d2, d3 - d2,
            rx1 * d1 - rx0 * d0, ry1 * d1 - ry0 * d0, d1 - d0)


@njit(parallel=True, cache=True)
def _normal_forward(rnormal, depth, alpha, rx, ry, normals, clen, row_sums):
    h, w = depth.shape
    for i in prange(1, h - 1):
        acc = 0.0
        for j in range(1, w - 1):
            a0, a1, a2, b0, b1, b2 = _differences(rx, ry, depth, i, j)
            c0 = a1 * b2 - a2 * b1
            c1 = a2 * b0 - a0 * b2
            c2 = a0 * b1 - a1 * b0
            n = max(np.sqrt(c0 * c0 + c1 * c1 + c2 * c2), _NORMALIZE_EPS)
            normals[i, j, 0], normals[i, j, 1], normals[i, j, 2] = c0 / n, c1 / n, c2 / n
            clen[i, j] = n
            acc += float(alpha[i, j]) * (float(rnormal[i, j, 0]) * c0 + float(rnormal[i, j, 1]) * c1
                                         + float(rnormal[i, j, 2]) * c2) / n
        row_sums[i] = acc


@njit(parallel=True, cache=True)
def _normal_backward(rnormal, depth, alpha, rx, ry, normals, clen, scale, g_rnormal, g_depth, g_a, g_b):
    """scale = upstream / (H W).  g_a, g_b: [H, W, 3] scratch (zero on the border)."""
    h, w = depth.shape
    for i in prange(h):
        for j in range(w):
            interior = 0 < i < h - 1 and 0 < j < w - 1
            for k in range(3):
                g_a[i, j, k] = 0.0
                g_b[i, j, k] = 0.0
                g_rnormal[i, j, k] = 0.0
            if not interior:
                continue
            al = float(alpha[i, j])
            n0, n1, n2 = float(normals[i, j, 0]), float(normals[i, j, 1]), float(normals[i, j, 2])
            g_rnormal[i, j, 0] = -scale * al * n0
            g_rnormal[i, j, 1] = -scale * al * n1
            g_rnormal[i, j, 2] = -scale * al * n2
            u0 = -scale * al * float(rnormal[i, j, 0])
            u1 = -scale * al * float(rnormal[i, j, 1])
            u2 = -scale * al * float(rnormal[i, j, 2])
            n = float(clen[i, j])
            if n > _NORMALIZE_EPS:
                dot = n0 * u0 + n1 * u1 + n2 * u2
                gc0, gc1, gc2 = (u0 - n0 * dot) / n, (u1 - n1 * dot) / n, (u2 - n2 * dot) / n
            else:
                gc0, gc1, gc2 = u0 / n, u1 / n, u2 / n
            a0, a1, a2, b0, b1, b2 = _differences(rx, ry, depth, i, j)
            # dL/da = b x g_c, dL/db = g_c x a
            g_a[i, j, 0] = b1 * gc2 - b2 * gc1
            g_a[i, j, 1] = b2 * gc0 - b0 * gc2
            g_a[i, j, 2] = b0 * gc1 - b1 * gc0
            g_b[i, j, 0] = gc1 * a2 - gc2 * a1
            g_b[i, j, 1] = gc2 * a0 - gc0 * a2
            g_b[i, j, 2] = gc0 * a1 - gc1 * a0
    for i in prange(h):
        for j in range(w):
            # P[i, j] is +b of (i, j-1), -b of (i, j+1), +a of (i-1, j), -a of (i+1, j)
            p0 = p1 = p2 = 0.0
            if j >= 1:
                p0 += g_b[i, j - 1, 0]
                p1 += g_b[i, j - 1, 1]
                p2 += g_b[i, j - 1, 2]
            if j + 1 < w:
                p0 -= g_b[i, j + 1, 0]
                p1 -= g_b[i, j + 1, 1]
                p2 -= g_b[i, j + 1, 2]
            if i >= 1:
                p0 += g_a[i - 1, j, 0]
                p1 += g_a[i - 1, j, 1]
                p2 += g_a[i - 1, j, 2]
            if i + 1 < h:
                p0 -= g_a[i + 1, j, 0]
                p1 -= g_a[i + 1, j, 1]
                p2 -= g_a[i + 1, j, 2]
            g_depth[i, j] = rx[i, j] * p0 + ry[i] * p1 + p2


class _FusedNormalConsistency(torch.autograd.Function):
    @staticmethod
    def forward(ctx, rendered_normal, depth, alpha, K):
        h, w = depth.shape
        rn, dp, al = (np.ascontiguousarray(t.detach().numpy()) for t in (rendered_normal, depth, alpha))
        normals = np.empty((h, w, 3), np.float64)  # the border's values are never read
        clen = np.empty((h, w), np.float64)
        row_sums = np.zeros(h, np.float64)
        rx, ry = _ray_table(K, h, w)
        if h > 2 and w > 2:
            _normal_forward(rn, dp, al, rx, ry, normals, clen, row_sums)
        ctx.saved = (rn, dp, al, rx, ry, normals, clen)
        ctx.dtypes = (rendered_normal.dtype, depth.dtype)
        return torch.tensor(1.0 - float(row_sums.sum()) / (h * w), dtype=rendered_normal.dtype)

    @staticmethod
    def backward(ctx, g_out):
        rn, dp, al, rx, ry, normals, clen = ctx.saved
        h, w = dp.shape
        # the gradients are computed in float64 and stored in the inputs' dtypes: numba's store rounds
        # to nearest as torch's .to() did on the float64 maps, without the two extra passes
        rdt, ddt = ctx.dtypes
        g_rn, g_dp = torch.empty((h, w, 3), dtype=rdt), torch.empty((h, w), dtype=ddt)
        _normal_backward(rn, dp, al, rx, ry, normals, clen, float(g_out) / (h * w), g_rn.numpy(), g_dp.numpy(),
                         np.empty((h, w, 3), np.float64), np.empty((h, w, 3), np.float64))
        return g_rn, g_dp, None, None


def fused_normal_consistency_applies(rendered_normal: torch.Tensor, depth: torch.Tensor, alpha: torch.Tensor) -> bool:
    """Whether :func:`fused_normal_consistency` handles these inputs ([H, W, 3], [H, W], [H, W] CPU
    float32/float64, the fused kernels switched on)."""
    from ...render.kernels.glue import use_fused

    return (depth.ndim == 2 and rendered_normal.shape == (*depth.shape, 3) and alpha.shape == depth.shape
            and use_fused(rendered_normal, depth, alpha))


def fused_normal_consistency(rendered_normal: torch.Tensor, depth: torch.Tensor, alpha: torch.Tensor,
                             K) -> torch.Tensor:
    """``normal_consistency_loss(rendered_normal, depth_to_normal(depth, K), alpha)`` in one numba pass
    forward and one backward (differentiable w.r.t. the rendered normal and the depth; alpha is
    treated as detached, as there).  Its twin is that torch composition."""
    if not fused_normal_consistency_applies(rendered_normal, depth, alpha):
        raise ValueError(f"fused_normal_consistency: needs [H, W, 3], [H, W], [H, W] CPU float32/64 tensors, got "
                         f"{tuple(rendered_normal.shape)}, {tuple(depth.shape)}, {tuple(alpha.shape)}")
    Kn = np.ascontiguousarray(np.asarray(K.detach().cpu() if torch.is_tensor(K) else K, dtype=np.float64))
    return _FusedNormalConsistency.apply(rendered_normal, depth, alpha.detach(), Kn)


# ----------------------------------------------------------------------------------------------
# The surface depth the normal-consistency term differentiates
# ----------------------------------------------------------------------------------------------
#
# The training loop's eight full-image torch operations (and their eight backward nodes)
#   expected = where(alpha > 1e-6, depth / alpha.clamp_min(1e-6), 0)
#   surface  = expected * (1 - r) + median * r
# as one float32 pass each way.  Every operation is the torch one, in float32, in torch's order, and
# the backward is torch's formulas (mul: grad * scalar; where: where(c, grad, 0); div:
# grad / other and -grad * ((self / other) / other); clamp_min: where(self >= min, grad, 0)), so the
# values and gradients are torch's bit for bit (tested).

_ALPHA_EPS = 1e-6


@njit(parallel=True, cache=True)
def _surface_forward(depth, alpha, median, eps, keep, ratio, out):
    h, w = depth.shape
    zero = np.float32(0.0)
    for i in prange(h):
        for j in range(w):
            a = alpha[i, j]
            e = depth[i, j] / max(a, eps) if a > eps else zero
            out[i, j] = e * keep + median[i, j] * ratio


@njit(parallel=True, cache=True)
def _surface_backward(depth, alpha, grad, eps, keep, ratio, g_depth, g_alpha, g_median):
    h, w = depth.shape
    zero = np.float32(0.0)
    for i in prange(h):
        for j in range(w):
            g = grad[i, j]
            a = alpha[i, j]
            c = max(a, eps)
            q = g * keep if a > eps else zero
            d = depth[i, j]
            g_depth[i, j] = q / c
            g_c = -q * ((d / c) / c)
            g_alpha[i, j] = g_c if a >= eps else zero
            g_median[i, j] = g * ratio


class _SurfaceDepth(torch.autograd.Function):
    @staticmethod
    def forward(ctx, depth, alpha, median, ratio):
        f32 = np.float32
        d, a, m = (np.ascontiguousarray(t.detach().numpy()) for t in (depth, alpha, median))
        out = np.empty_like(d)
        consts = (f32(_ALPHA_EPS), f32(1.0 - ratio), f32(ratio))
        _surface_forward(d, a, m, *consts, out)
        ctx.saved = (d, a, consts)
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad):
        d, a, consts = ctx.saved
        outs = (np.empty_like(d), np.empty_like(d), np.empty_like(d))
        _surface_backward(d, a, np.ascontiguousarray(grad.detach().numpy().astype(np.float32, copy=False)), *consts,
                          *outs)
        return tuple(torch.from_numpy(o) for o in outs) + (None,)


def surface_depth_torch(depth: torch.Tensor, alpha: torch.Tensor, median: torch.Tensor, ratio: float) -> torch.Tensor:
    """The twin of :func:`surface_depth` (the torch operations the training loop ran)."""
    covered = alpha > _ALPHA_EPS
    expected = torch.where(covered, depth / alpha.clamp_min(_ALPHA_EPS), torch.zeros_like(depth))
    return expected * (1.0 - ratio) + median * ratio


def surface_depth(depth: torch.Tensor, alpha: torch.Tensor, median: torch.Tensor, ratio: float) -> torch.Tensor:
    """The 2DGS surface depth ``(1 - r) D / alpha + r D_median`` ([H, W]; 0 where alpha <= 1e-6) of a
    render, differentiable w.r.t. all three maps: one numba pass each way for float32 CPU maps, bit
    for bit :func:`surface_depth_torch` (the twin elsewhere)."""
    from ...render.kernels.glue import use_fused

    maps = (depth, alpha, median)
    if not (use_fused(*maps) and all(t.dtype == torch.float32 and t.shape == depth.shape for t in maps)
            and depth.ndim == 2):
        return surface_depth_torch(depth, alpha, median, ratio)
    return _SurfaceDepth.apply(depth, alpha, median, float(ratio))
