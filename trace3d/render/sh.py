"""Real spherical harmonics up to degree 3 (the 3DGS / Plenoxels convention): the basis constants,
the coefficient count per degree and :func:`eval_sh`, the torch evaluation that the fused kernel
:func:`trace3d.render.kernels.glue.sh_colors` is tested against.  (Moved here from ``gaussians.py``,
unchanged, so that the render package no longer imports the model: the model imports the render.)"""

from __future__ import annotations

import torch

# Real spherical-harmonic basis constants (the 3DGS / Plenoxels convention).
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)
MAX_SH_DEGREE = 3


def num_sh_rest(degree: int) -> int:
    """Number K of non-DC SH coefficients per channel for ``degree`` (0..3)."""
    return (degree + 1) ** 2 - 1


def eval_sh(degree: int, coeffs: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """Evaluate real spherical harmonics up to ``degree``.

    Args:
        degree: 0..3.
        coeffs: [N, (degree_max + 1)^2, C] coefficients, degree_max >= degree (extra ones ignored).
        directions: [N, 3] unit viewing directions (from the camera to the Gaussian).
    Returns:
        [N, C] the SH value (without the +0.5 offset).
    """
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"SH degree must be in 0..{MAX_SH_DEGREE}, got {degree}")
    if coeffs.shape[1] < (degree + 1) ** 2:
        raise ValueError(f"eval_sh: degree {degree} needs {(degree + 1) ** 2} coefficients, got {coeffs.shape[1]}")
    result = SH_C0 * coeffs[:, 0]
    if degree == 0:
        return result
    x, y, z = directions[:, 0:1], directions[:, 1:2], directions[:, 2:3]
    result = result - SH_C1 * y * coeffs[:, 1] + SH_C1 * z * coeffs[:, 2] - SH_C1 * x * coeffs[:, 3]
    if degree == 1:
        return result
    xx, yy, zz = x * x, y * y, z * z
    xy, yz, xz = x * y, y * z, x * z
    result = (
        result
        + SH_C2[0] * xy * coeffs[:, 4]
        + SH_C2[1] * yz * coeffs[:, 5]
        + SH_C2[2] * (2.0 * zz - xx - yy) * coeffs[:, 6]
        + SH_C2[3] * xz * coeffs[:, 7]
        + SH_C2[4] * (xx - yy) * coeffs[:, 8]
    )
    if degree == 2:
        return result
    return (
        result
        + SH_C3[0] * y * (3.0 * xx - yy) * coeffs[:, 9]
        + SH_C3[1] * xy * z * coeffs[:, 10]
        + SH_C3[2] * y * (4.0 * zz - xx - yy) * coeffs[:, 11]
        + SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * coeffs[:, 12]
        + SH_C3[4] * x * (4.0 * zz - xx - yy) * coeffs[:, 13]
        + SH_C3[5] * z * (xx - yy) * coeffs[:, 14]
        + SH_C3[6] * x * (xx - 3.0 * yy) * coeffs[:, 15]
    )
