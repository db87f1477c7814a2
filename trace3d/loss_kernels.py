"""Fused numba SSIM (forward + analytic backward) for the training loss.

:func:`trace3d.losses.ssim` in torch builds five statistics maps, blurs them with two grouped 1D
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


@njit(parallel=True, cache=True)
def _blur(src, g, tmp, out):
    """Zero-padded separable blur of every [H, W] plane of src [M, H, W] into out (tmp: scratch).

    The inner loops run along a row with unsigned indices: numba then drops its negative-index
    wrap-around and the loops vectorise (about 4x faster than signed indices, measured)."""
    m, h, w = src.shape
    r = g.shape[0] // 2
    uw = np.uint64(w)
    # vertical pass, one (plane, row) per iteration
    for job in prange(m * h):
        p = job // h
        y = job % h
        row = tmp[p, y]
        for x in range(uw):
            row[x] = 0.0
        for k in range(g.shape[0]):
            yy = y + k - r
            if yy < 0 or yy >= h:
                continue
            gk = g[k]
            srow = src[p, yy]
            for x in range(uw):
                row[x] += gk * srow[x]
    # horizontal pass: tap k reads x + k - r
    for job in prange(m * h):
        p = job // h
        y = job % h
        row = out[p, y]
        trow = tmp[p, y]
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


@njit(parallel=True, cache=True)
def _ssim_terms(x, y, g, c1, c2, two, want_grad):
    """SSIM per value of x, y [C, H, W] and, with want_grad, the three per-pixel partials
    (dS/dmx, dS/dexx, dS/dexy) stacked as [3C, H, W].  The constants come in the images' dtype, so
    float32 stays float32 (numba would promote a float literal to float64)."""
    c, h, w = x.shape
    stats = np.empty((5 * c, h, w), x.dtype)
    uw = np.uint64(w)
    for job in prange(c * h):
        ch = job // h
        i = job % h
        for j in range(uw):
            a = x[ch, i, j]
            b = y[ch, i, j]
            stats[ch, i, j] = a
            stats[c + ch, i, j] = b
            stats[2 * c + ch, i, j] = a * a
            stats[3 * c + ch, i, j] = b * b
            stats[4 * c + ch, i, j] = a * b
    tmp = np.empty_like(stats)
    blurred = np.empty_like(stats)
    _blur(stats, g, tmp, blurred)
    s_map = np.empty((c, h, w), x.dtype)
    partials = np.empty((3 * c if want_grad else 0, h, w), x.dtype)
    for job in prange(c * h):
        ch = job // h
        i = job % h
        for j in range(uw):
            mx = blurred[ch, i, j]
            my = blurred[c + ch, i, j]
            sx = blurred[2 * c + ch, i, j] - mx * mx
            sy = blurred[3 * c + ch, i, j] - my * my
            sxy = blurred[4 * c + ch, i, j] - mx * my
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


@njit(parallel=True, cache=True)
def _ssim_input_grad(x, y, blurred_partials, scale, out):
    c, h, w = x.shape
    uw = np.uint64(w)
    for job in prange(c * h):
        ch = job // h
        i = job % h
        for j in range(uw):
            out[ch, i, j] = scale * (blurred_partials[ch, i, j] + (x[ch, i, j] + x[ch, i, j]) * blurred_partials[c + ch, i, j]
                                     + y[ch, i, j] * blurred_partials[2 * c + ch, i, j])


class _FusedSSIM(torch.autograd.Function):
    @staticmethod
    def forward(ctx, image, target):
        dt = np.float64 if image.dtype == torch.float64 else np.float32
        x = np.ascontiguousarray(image.detach().numpy().astype(dt, copy=False).transpose(2, 0, 1))
        y = np.ascontiguousarray(target.detach().numpy().astype(dt, copy=False).transpose(2, 0, 1))
        g = _window(dt)
        s_map, partials = _ssim_terms(x, y, g, dt(SSIM_C1), dt(SSIM_C2), dt(2.0), ctx.needs_input_grad[0])
        ctx.saved = (x, y, g, partials)
        # the mean in float64, then the image's dtype
        return torch.tensor(float(s_map.astype(np.float64).mean()), dtype=image.dtype)

    @staticmethod
    def backward(ctx, g_out):
        x, y, g, partials = ctx.saved
        if not ctx.needs_input_grad[0]:
            return None, None
        blurred = np.empty_like(partials)
        _blur(partials, g, np.empty_like(partials), blurred)
        grad = np.empty_like(x)
        _ssim_input_grad(x, y, blurred, x.dtype.type(float(g_out) / x.size), grad)
        return torch.from_numpy(grad.transpose(1, 2, 0).copy()), None


def fused_ssim_applies(image: torch.Tensor, target: torch.Tensor) -> bool:
    """Whether :func:`fused_ssim` handles these inputs: [H, W, C] CPU float32/float64 pairs of one
    shape, the target without gradient, the fused kernels switched on."""
    from .render.glue_kernels import use_fused

    return (image.ndim == 3 and image.shape == target.shape and image.dtype == target.dtype
            and not target.requires_grad and use_fused(image, target))


def fused_ssim(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of ``image`` against ``target`` ([H, W, C]; differentiable w.r.t. ``image``);
    equal to :func:`trace3d.losses.ssim` (its twin) up to float rounding."""
    if not fused_ssim_applies(image, target):
        raise ValueError(f"fused_ssim: needs [H, W, C] CPU float32/64 images of one shape and dtype and a target "
                         f"without gradient, got {tuple(image.shape)} {image.dtype} and {tuple(target.shape)} "
                         f"{target.dtype}")
    return _FusedSSIM.apply(image, target)

