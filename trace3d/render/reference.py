"""Dense pure-torch 2DGS renderer: the test oracle of the tile kernels.

Every splat in front of the camera is evaluated at every pixel, sorted by centre depth (stable, so
ties keep index order), and blended with a cumulative product; torch autograd differentiates it.  It
applies exactly the thresholds of the kernels: skip alpha < 1/255, clamp alpha at 0.99, stop once the
transmittance would fall below 1e-4 (the splat that would cross it is not blended), skip a pair whose
ray meets the splat's plane closer than ``near`` or parallel to it.  Slow and memory-hungry
(O(N x H x W)); pixels are processed in chunks under activation checkpointing to bound memory.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from .projection import (ALPHA_MAX, ALPHA_MIN, FILTER_INV_SQUARE, TRANSMITTANCE_MIN, Projected,
                         pixel_centres)


def _blend_chunk(coeffs: Tensor, tw: Tensor, means2d: Tensor, opacities: Tensor, normals: Tensor,
                 features: Tensor, xs: Tensor, ys: Tensor, near: float) -> tuple[Tensor, ...]:
    """Blend M depth-sorted splats at P pixels.

    Args:
        coeffs: [M, 9]; tw: [M, 3] (T_w rows); means2d: [M, 2]; opacities: [M]; normals: [M, 3];
        features: [M, C]; xs, ys: [P] pixel centres.
    Returns:
        features [P, C], alpha [P], depth [P], normal [P, 3], depth2 [P] (sum w (z - z_ref)^2),
        z_ref [P] (depth of the first blended splat, 0 if none), median_depth [P], final transmittance [P].
    """
    x = xs[None, :]
    y = ys[None, :]
    # same operation order as the kernels: (A + y D) + x B
    c0 = (coeffs[:, 0:1] + coeffs[:, 6:7] * y) + coeffs[:, 3:4] * x  # [M, P]
    c1 = (coeffs[:, 1:2] + coeffs[:, 7:8] * y) + coeffs[:, 4:5] * x
    c2 = (coeffs[:, 2:3] + coeffs[:, 8:9] * y) + coeffs[:, 5:6] * x
    nonparallel = c2 != 0
    c2 = torch.where(nonparallel, c2, torch.ones_like(c2))
    inv_c2 = 1.0 / c2
    u = c0 * inv_c2
    v = c1 * inv_c2
    sigma_disk = 0.5 * (u * u + v * v)
    dx = x - means2d[:, 0:1]
    dy = y - means2d[:, 1:2]
    sigma_filter = 0.5 * FILTER_INV_SQUARE * (dx * dx + dy * dy)
    sigma = torch.minimum(sigma_disk, sigma_filter)
    alpha = (opacities[:, None] * torch.exp(-sigma)).clamp(max=ALPHA_MAX)
    # 2DGS: the plane intersection's depth where the disk term wins, the centre's where the filter does
    use_disk = sigma_disk <= sigma_filter
    z = torch.where(use_disk, u * tw[:, 0:1] + v * tw[:, 1:2] + tw[:, 2:3], tw[:, 2:3].expand_as(u))
    keep = nonparallel & (alpha >= ALPHA_MIN) & (z > near)
    alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
    # a splat is blended while the transmittance after it stays >= 1e-4
    after = torch.cumprod(1.0 - alpha, dim=0)
    blended = after >= TRANSMITTANCE_MIN
    alpha = torch.where(blended, alpha, torch.zeros_like(alpha))
    one_minus = 1.0 - alpha
    after = torch.cumprod(one_minus, dim=0)
    before = torch.cat([torch.ones_like(after[:1]), after[:-1]], dim=0)
    w = alpha * before  # [M, P]
    final_t = after[-1] if after.shape[0] else torch.ones_like(xs)
    feat = w.T @ features
    alpha_px = w.sum(0)
    depth = (w * z).sum(0)
    # distortion sums relative to the depth of the pixel's first blended splat (well conditioned)
    blended_any = alpha > 0
    m = alpha.shape[0]
    first = torch.where(blended_any, torch.arange(m, 0, -1, device=xs.device)[:, None], 0).argmax(0) if m else None
    ref = z.detach().gather(0, first[None, :])[0] if m else torch.zeros_like(xs)
    ref = torch.where(blended_any.any(0), ref, torch.zeros_like(ref)) if m else ref
    dz = z - ref[None, :]
    depth2 = (w * dz * dz).sum(0)
    normal = w.T @ normals
    # median depth: z of the last blended splat whose transmittance before it exceeds 0.5
    is_median = (alpha > 0) & (before > 0.5)
    m = is_median.shape[0]
    order = torch.arange(1, m + 1, device=xs.device)[:, None]
    last = (is_median * order).amax(0) if m else torch.zeros_like(xs, dtype=torch.long)
    has = last > 0
    gathered = z.gather(0, (last - 1).clamp_min(0)[None, :])[0] if m else torch.zeros_like(xs)
    median = torch.where(has, gathered, torch.zeros_like(gathered))
    return feat, alpha_px, depth, normal, depth2, ref, median, final_t


def render_reference(proj: Projected, features: Tensor, width: int, height: int, background: Tensor,
                     near: float = 0.01, chunk_pixels: int = 4096) -> dict[str, Tensor]:
    """Dense render of projected splats.

    Args:
        proj: output of :func:`~trace3d.render.projection.project`.
        features: [N, C].
        background: [C].
    Returns:
        dict with features [H, W, C] (background added), alpha, depth, depth2 (sum w (z - depth_ref)^2),
        depth_ref (depth of each pixel's first blended splat), median_depth [H, W], normal [H, W, 3].
    """
    dev, dt = features.device, features.dtype
    keep = proj.depths > near
    idx = torch.nonzero(keep).flatten()
    order = torch.sort(proj.depths[idx], stable=True).indices
    idx = idx[order]
    tw = proj.ray_transforms[idx, 2]
    args = (proj.coeffs[idx], tw, proj.means2d[idx], proj.opacities[idx], proj.normals[idx], features[idx])
    xs, ys = pixel_centres(width, height, dev, dt)
    outs = []
    use_ckpt = torch.is_grad_enabled() and any(a.requires_grad for a in args)
    for start in range(0, xs.shape[0], chunk_pixels):
        cx, cy = xs[start:start + chunk_pixels], ys[start:start + chunk_pixels]
        if use_ckpt:
            outs.append(checkpoint(_blend_chunk, *args, cx, cy, near, use_reentrant=False))
        else:
            outs.append(_blend_chunk(*args, cx, cy, near))
    feat, alpha, depth, normal, depth2, ref, median, final_t = (torch.cat(parts, 0) for parts in zip(*outs))
    feat = feat + final_t[:, None] * background[None, :]
    c = features.shape[1]
    return {
        "features": feat.reshape(height, width, c),
        "alpha": alpha.reshape(height, width),
        "depth": depth.reshape(height, width),
        "depth2": depth2.reshape(height, width),
        "depth_ref": ref.reshape(height, width),
        "normal": normal.reshape(height, width, 3),
        "median_depth": median.reshape(height, width),
    }
