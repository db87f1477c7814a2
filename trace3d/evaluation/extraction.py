"""3D object extraction (paper Table 2; supplementary "Evaluation Details").

"We render the extracted 3D object into novel views to generate its corresponding RGB image. The
regions where the RGB values exceed zero are utilized as a mask to compute the IoU with the
ground-truth mask. For PSNR calculation, we restrict the computation to a specific region defined by
the bounding box of the ground-truth mask, expanded outward by 10 pixels."

Here: only the object's Gaussians are rendered, on black; the predicted mask is where that render's
alpha exceeds ``alpha_eps`` (alpha rather than RGB so that a black object still counts); the PSNR
compares the render with the ground-truth image in which everything but the object is black, over
the ground-truth box grown by ``psnr_margin`` pixels.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from ..gaussians import GaussianModel
from ..scene import Camera
from .metrics import confusion, grown_box, psnr


@torch.no_grad()
def render_alone(model: GaussianModel, camera: Camera, near: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """The Gaussians of ``model`` rendered on black.

    Returns:
        rgb [H, W, 3] float32 in [0, 1] (clipped) and alpha [H, W] float32.
    """
    from ..render import render

    if len(model) == 0:
        return (np.zeros((camera.height, camera.width, 3), np.float32),
                np.zeros((camera.height, camera.width), np.float32))
    colors = model.colors(torch.as_tensor(camera.center, dtype=model.means.dtype))
    out = render(model.splats(), camera, colors, near=near)
    return out.features.clamp(0.0, 1.0).numpy().astype(np.float32), out.alpha.numpy().astype(np.float32)


def score_view(rgb: np.ndarray, alpha: np.ndarray, truth: np.ndarray, image: np.ndarray, alpha_eps: float,
               margin: int) -> dict:
    """IoU and PSNR of one view.

    Args:
        rgb: [H, W, 3] the object rendered alone on black; alpha: [H, W] its alpha.
        truth: [H, W] bool ground-truth mask; image: [H, W, 3] ground-truth image in [0, 1].
    """
    pred = alpha > alpha_eps
    c = confusion(pred, truth)
    target = image * truth[..., None]
    return {"iou": c.iou, "psnr": psnr(rgb, target, grown_box(truth, margin)), "pixels": int(truth.sum()),
            "predicted_pixels": int(pred.sum())}


def evaluate_extraction(model: GaussianModel, keep: np.ndarray, cameras: Sequence[Camera], truths: Sequence[np.ndarray],
                        images: Sequence[np.ndarray], alpha_eps: float, margin: int, near: float = 0.01) -> list[dict]:
    """Per-view scores of the object made of ``model``'s Gaussians ``keep`` [N] bool."""
    obj = model.subset(torch.from_numpy(np.asarray(keep, bool)))
    out = []
    for cam, truth, image in zip(cameras, truths, images):
        rgb, alpha = render_alone(obj, cam, near)
        out.append({"frame": cam.name, **score_view(rgb, alpha, truth, image, alpha_eps, margin)})
    return out
