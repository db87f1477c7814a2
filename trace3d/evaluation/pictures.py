"""Pictures of the evaluation: the per-scene figure (``pictures.png``) and each extracted object's
multi-view render (``objects/<id>.png``)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import numpy as np

from ..gaussians import GaussianModel
from ..io import atomic_file
from ..scene import Camera, write_rgb
from .extraction import render_alone

TP_COLOR = np.array([1.0, 0.85, 0.0])  # yellow, as the paper's figures
FP_COLOR = np.array([0.9, 0.1, 0.1])  # red
FN_COLOR = np.array([0.1, 0.8, 0.2])  # green


def overlay(image: np.ndarray, mask: np.ndarray, color=TP_COLOR, strength: float = 0.55) -> np.ndarray:
    """[H, W, 3] ``image`` in [0, 1] with ``mask`` [H, W] tinted."""
    out = image.astype(np.float32).copy()
    out[mask] = (1 - strength) * out[mask] + strength * np.asarray(color, np.float32)
    return out


def confusion_picture(image: np.ndarray, pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """[H, W, 3]: TP yellow, FP red, FN green over a dimmed ``image``."""
    out = image.astype(np.float32) * 0.45
    for mask, color in ((pred & truth, TP_COLOR), (pred & ~truth, FP_COLOR), (~pred & truth, FN_COLOR)):
        out[mask] = 0.25 * out[mask] + 0.75 * color
    return out


def look_at(position: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """[4, 4] world_to_camera (OpenCV: x right, y down, z forward) looking from ``position`` at ``target``."""
    forward = target - position
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-6:
        right = np.cross(forward, np.array([1.0, 0.0, 0.0]) if abs(forward[0]) < 0.9 else np.array([0.0, 1.0, 0.0]))
    right = right / np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])
    w2c = np.eye(4)
    w2c[:3, :3] = rotation
    w2c[:3, 3] = -rotation @ position
    return w2c


def world_up(cameras: Sequence[Camera]) -> np.ndarray:
    """[3] mean "up" of the cameras (minus their y axis in world coordinates)."""
    up = -np.mean([c.rotation[1] for c in cameras], axis=0) if cameras else np.array([0.0, 0.0, 1.0])
    norm = np.linalg.norm(up)
    return up / norm if norm > 1e-9 else np.array([0.0, 0.0, 1.0])


def turntable_cameras(model: GaussianModel, up: np.ndarray, views: int, size: int, elevation_deg: float = 25.0,
                      fov_deg: float = 40.0) -> list[Camera]:
    """``views`` cameras on a circle around the Gaussians' centre, all framing them."""
    means = model.means.detach().double().numpy()
    center = np.median(means, axis=0) if len(means) else np.zeros(3)
    radius = float(np.percentile(np.linalg.norm(means - center, axis=1), 95)) if len(means) else 1.0
    radius = max(radius, 1e-3)
    distance = radius / math.tan(math.radians(fov_deg) / 2) * 1.15
    a = np.cross(up, [1.0, 0.0, 0.0])
    if np.linalg.norm(a) < 1e-3:
        a = np.cross(up, [0.0, 1.0, 0.0])
    a = a / np.linalg.norm(a)
    b = np.cross(up, a)
    focal = size / 2 / math.tan(math.radians(fov_deg) / 2)
    K = np.array([[focal, 0, size / 2], [0, focal, size / 2], [0, 0, 1]])
    el = math.radians(elevation_deg)
    cams = []
    for k in range(views):
        az = 2 * math.pi * k / views
        direction = math.cos(el) * (math.cos(az) * a + math.sin(az) * b) + math.sin(el) * up
        cams.append(Camera(f"turntable_{k:02d}", "test", size, size, K, look_at(center + distance * direction, center, up)))
    return cams


def turntable_strip(model: GaussianModel, up: np.ndarray, views: int, size: int, near: float = 0.01) -> np.ndarray:
    """[size, views * size, 3] uint8: the Gaussians alone (on black) from ``views`` directions."""
    tiles = []
    for cam in turntable_cameras(model, up, views, size):
        rgb, _ = render_alone(model, cam, near)
        tiles.append(rgb)
    strip = np.concatenate(tiles, axis=1) if tiles else np.zeros((size, size, 3))
    return (np.clip(strip, 0, 1) * 255 + 0.5).astype(np.uint8)


def write_turntable(path: Path, model: GaussianModel, up: np.ndarray, views: int, size: int, near: float = 0.01) -> None:
    write_rgb(path, turntable_strip(model, up, views, size, near))


def write_pictures(path: Path, rows: list[dict], title: str) -> None:
    """The scene figure: one row per object.

    Each row: ``reference`` (image [H, W, 3] in [0, 1]), ``query`` ([H, W] bool), ``render`` (the
    extracted object alone at ``frame``), ``truth_image`` (ground-truth image at ``frame``, object
    only), ``nvs`` (predicted mask), ``truth`` (ground-truth mask), ``image`` (image at ``frame``),
    and ``label`` text.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    columns = ("reference view + query", "extracted object alone", "ground truth object", "NVS mask: TP / FP / FN")
    n = max(1, len(rows))
    fig, axes = plt.subplots(n, 4, figsize=(12, 2.6 * n), squeeze=False)
    for r in range(n):
        for c in range(4):
            axes[r, c].axis("off")
    for r, row in enumerate(rows):
        panels = [overlay(row["reference"], row["query"]), row["render"], row["truth_image"],
                  confusion_picture(row["image"], row["nvs"], row["truth"])]
        for c, panel in enumerate(panels):
            ax = axes[r, c]
            ax.imshow(np.clip(panel, 0, 1), interpolation="nearest")
            if r == 0:
                ax.set_title(columns[c], fontsize=9)
        axes[r, 0].text(0, -0.04, row["label"], transform=axes[r, 0].transAxes, fontsize=8, va="top")
        axes[r, 1].text(0, -0.04, row["extraction_text"], transform=axes[r, 1].transAxes, fontsize=8, va="top")
        axes[r, 3].text(0, -0.04, row["nvs_text"], transform=axes[r, 3].transAxes, fontsize=8, va="top")
    if not rows:
        axes[0, 0].text(0.0, 0.5, "no object could be evaluated", fontsize=12)
    fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    with atomic_file(path) as tmp:
        fig.savefig(tmp, format="png", dpi=90, bbox_inches="tight", metadata={"Software": None})
    plt.close(fig)
