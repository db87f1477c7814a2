"""Image losses and metrics of the 2DGS fit (pure torch, differentiable).

Images are ``[H, W, C]`` tensors (channels last, as the renderer returns them) with values in
[0, 1]; batched helpers accept ``[B, H, W, C]``.

- :func:`ssim`: structural similarity with an 11x11 Gaussian window (sigma 1.5), the 3DGS/2DGS
  training loss formulation (zero-padded "same" convolution, constants C1 = 0.01^2, C2 = 0.03^2).
- :func:`photometric_loss`: ``(1 - lambda_dssim) * L1 + lambda_dssim * (1 - SSIM)`` (2DGS: 0.2); on
  the CPU its SSIM is the fused numba kernel of :mod:`trace3d.training.kernels.losses` (:func:`ssim` is its twin).
- :func:`normal_consistency_loss`: the 2DGS regulariser ``mean(1 - <n_rendered, alpha * N_depth>)``;
  :func:`depth_normal_consistency` takes the depth map itself (fused numba kernel on the CPU, the
  torch composition ``depth_to_normal`` + :func:`normal_consistency_loss` as its twin elsewhere).
- :func:`photometric_terms`: the loss, its terms and the running PSNR of the training loop (one fused
  numba pass on the CPU, the same values and gradients).
- :func:`psnr`.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from ..geometry import depth_to_normal, depth_to_points  # noqa: F401  (their home is trace3d.geometry; kept importable here)
from .kernels.losses import (fused_normal_consistency, fused_normal_consistency_applies, fused_photometric,
                             fused_photometric_applies, fused_ssim, fused_ssim_applies)

SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2


def gaussian_window(size: int = 11, sigma: float = 1.5, dtype=torch.float32, device=None) -> torch.Tensor:
    """[size, size] normalised 2D Gaussian window (outer product of the 1D window)."""
    coords = torch.arange(size, dtype=torch.float64) - (size - 1) / 2.0
    g = torch.exp(-(coords**2) / (2.0 * sigma**2))
    g = g / g.sum()
    return torch.outer(g, g).to(dtype=dtype, device=device)


def _to_bchw(image: torch.Tensor) -> torch.Tensor:
    if image.ndim == 3:
        return image.permute(2, 0, 1)[None]
    if image.ndim == 4:
        return image.permute(0, 3, 1, 2)
    raise ValueError(f"expected an image [H, W, C] or a batch [B, H, W, C], got shape {tuple(image.shape)}")


def ssim_map(
    image: torch.Tensor, target: torch.Tensor, window_size: int = 11, sigma: float = 1.5
) -> torch.Tensor:
    """Per-pixel SSIM.

    Args:
        image, target: [H, W, C] or [B, H, W, C].
    Returns:
        [B, C, H, W] SSIM values (B = 1 for unbatched input).
    """
    if image.shape != target.shape:
        raise ValueError(f"ssim: shapes differ, {tuple(image.shape)} vs {tuple(target.shape)}")
    x = _to_bchw(image)
    y = _to_bchw(target)
    channels = x.shape[1]
    # The 2D Gaussian window is separable: blur the five statistics maps at once with a vertical
    # and a horizontal 1D pass (zero padding, identical to the 2D "same" convolution).
    coords = torch.arange(window_size, dtype=torch.float64) - (window_size - 1) / 2.0
    g = torch.exp(-(coords**2) / (2.0 * sigma**2))
    g = (g / g.sum()).to(dtype=x.dtype, device=x.device)
    stacked = torch.cat([x, y, x * x, y * y, x * y], dim=1)  # [B, 5C, H, W]
    groups = stacked.shape[1]
    pad = window_size // 2
    blurred = F.conv2d(stacked, g.view(1, 1, -1, 1).expand(groups, 1, window_size, 1), padding=(pad, 0), groups=groups)
    blurred = F.conv2d(blurred, g.view(1, 1, 1, -1).expand(groups, 1, 1, window_size), padding=(0, pad), groups=groups)
    mu_x, mu_y, e_xx, e_yy, e_xy = blurred.split(channels, dim=1)
    mu_x2, mu_y2, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    sigma_x2 = e_xx - mu_x2
    sigma_y2 = e_yy - mu_y2
    sigma_xy = e_xy - mu_xy
    numerator = (2.0 * mu_xy + SSIM_C1) * (2.0 * sigma_xy + SSIM_C2)
    denominator = (mu_x2 + mu_y2 + SSIM_C1) * (sigma_x2 + sigma_y2 + SSIM_C2)
    return numerator / denominator


def _ssim_map_reference(image: torch.Tensor, target: torch.Tensor, window_size: int = 11,
                        sigma: float = 1.5) -> torch.Tensor:
    """Slow twin of :func:`ssim_map`: five separate 2D convolutions with the full window."""
    x = _to_bchw(image)
    y = _to_bchw(target)
    channels = x.shape[1]
    window = gaussian_window(window_size, sigma, x.dtype, x.device).expand(channels, 1, window_size, window_size)

    def blur(t: torch.Tensor) -> torch.Tensor:
        return F.conv2d(t, window, padding=window_size // 2, groups=channels)

    mu_x, mu_y = blur(x), blur(y)
    sigma_x2 = blur(x * x) - mu_x * mu_x
    sigma_y2 = blur(y * y) - mu_y * mu_y
    sigma_xy = blur(x * y) - mu_x * mu_y
    return ((2 * mu_x * mu_y + SSIM_C1) * (2 * sigma_xy + SSIM_C2)) / (
        (mu_x * mu_x + mu_y * mu_y + SSIM_C1) * (sigma_x2 + sigma_y2 + SSIM_C2)
    )


def ssim(image: torch.Tensor, target: torch.Tensor, window_size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Mean SSIM (scalar) of ``image`` against ``target``, both [H, W, C] or [B, H, W, C]."""
    return ssim_map(image, target, window_size, sigma).mean()


def l1_loss(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean absolute error (scalar)."""
    return (image - target).abs().mean()


def photometric_loss(
    image: torch.Tensor, target: torch.Tensor, lambda_dssim: float = 0.2
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The 2DGS colour loss ``(1 - lambda) * L1 + lambda * (1 - SSIM)``.

    Args:
        image, target: [H, W, C].
    Returns:
        (loss, l1, ssim) scalars.
    """
    l1 = l1_loss(image, target)
    s = fused_ssim(image, target) if fused_ssim_applies(image, target) else ssim(image, target)
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - s), l1, s


def photometric_terms(image: torch.Tensor, target: torch.Tensor, lambda_dssim: float = 0.2
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, float]:
    """:func:`photometric_loss` and the running PSNR of the training loop in one call.

    Returns:
        (loss, l1, ssim, psnr): the first three as :func:`photometric_loss` gives them,
        psnr = ``psnr(image.detach().clamp(0, 1), target, exact=False)``; on the CPU from the fused
        numba pass (:func:`trace3d.training.kernels.losses.fused_photometric`, the same values and gradients bit
        for bit), else from those functions.
    """
    if fused_photometric_applies(image, target):
        l1, s, mse = fused_photometric(image, target)
        mse = float(mse)
        return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - s), l1, s, (math.inf if mse <= 0.0
                                                                            else -10.0 * math.log10(mse))
    loss, l1, s = photometric_loss(image, target, lambda_dssim)
    return loss, l1, s, psnr(image.detach().clamp(0, 1), target, exact=False)


def psnr(image: torch.Tensor, target: torch.Tensor, exact: bool = True) -> float:
    """Peak signal-to-noise ratio in dB of images in [0, 1] (``inf`` for identical images).

    ``exact`` computes the error in float64; otherwise in the images' dtype (for running logs).
    """
    if exact:
        image, target = image.double(), target.double()
    mse = float(((image.detach() - target.detach()) ** 2).mean())
    if mse <= 0.0:
        return math.inf
    return -10.0 * math.log10(mse)


def normal_consistency_loss(
    rendered_normal: torch.Tensor, surface_normal: torch.Tensor, alpha: torch.Tensor
) -> torch.Tensor:
    """The 2DGS normal-consistency term ``mean_x (1 - <n_rendered(x), alpha(x) N_depth(x)>)``.

    The rendered normal is the alpha-weighted sum of splat normals (not renormalised); the depth
    normal is weighted by the detached alpha, as in 2DGS.

    Args:
        rendered_normal: [H, W, 3] camera space.
        surface_normal: [H, W, 3] unit normals from the depth map (camera space).
        alpha: [H, W] accumulated opacity.
    Returns:
        scalar loss.
    """
    weighted = surface_normal * alpha.detach()[..., None]
    return (1.0 - (rendered_normal * weighted).sum(dim=-1)).mean()


def depth_normal_consistency(rendered_normal: torch.Tensor, depth: torch.Tensor, alpha: torch.Tensor,
                             K: np.ndarray | torch.Tensor) -> torch.Tensor:
    """:func:`normal_consistency_loss` against the normals of ``depth`` ([H, W], camera z) under
    intrinsics ``K``: the fused numba kernel on the CPU, else ``depth_to_normal`` + the torch loss."""
    if fused_normal_consistency_applies(rendered_normal, depth, alpha):
        return fused_normal_consistency(rendered_normal, depth, alpha, K)
    return normal_consistency_loss(rendered_normal, depth_to_normal(depth, K), alpha)
