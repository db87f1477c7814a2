"""Pictures of the evaluation: the per-scene figure (``pictures.png``) and each extracted object's
multi-view render (``objects/<id>.png``)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from ..gaussians import GaussianModel
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


PANEL_HEIGHT = 240  # pixels of one picture panel (images are scaled by whole factors, nearest neighbour)
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def _text_width(text: str, scale: float) -> int:
    return cv2.getTextSize(text, _FONT, scale, 1)[0][0]


def _fit_text(text: str, width: int, scale: float) -> str:
    """``text`` cut (with "...") to fit ``width`` pixels at font ``scale``."""
    if _text_width(text, scale) <= width:
        return text
    while text and _text_width(text + "...", scale) > width:
        text = text[:-1]
    return text + "..."


def _put(canvas: np.ndarray, text: str, x: int, baseline: int, width: int, scale: float) -> None:
    if text:
        cv2.putText(canvas, _fit_text(text, width, scale), (x, baseline), _FONT, scale, (0, 0, 0), 1, cv2.LINE_AA)


def _panel(image: np.ndarray, height: int) -> np.ndarray:
    """[height', W', 3] uint8 of ``image`` [H, W, 3] in [0, 1], scaled by a whole factor (at least 1) to at
    most ``height`` rows (nearest neighbour: a mask's pixels stay visible as pixels)."""
    rgb = (np.clip(np.asarray(image, np.float32), 0, 1) * 255 + 0.5).astype(np.uint8)
    factor = max(1, height // max(1, rgb.shape[0]))
    return np.repeat(np.repeat(rgb, factor, axis=0), factor, axis=1)


def write_pictures(path: Path, rows: list[dict], title: str) -> None:
    """The scene figure (PNG, drawn with OpenCV: an evaluation job spends no second on a plotting
    library): one row per object.

    Each row: ``reference`` (image [H, W, 3] in [0, 1]), ``query`` ([H, W] bool), ``render`` (the
    extracted object alone at ``frame``), ``truth_image`` (ground-truth image at ``frame``, object
    only), ``nvs`` (predicted mask), ``truth`` (ground-truth mask), ``image`` (image at ``frame``),
    and the texts ``label`` (under the first panel), ``extraction_text`` (second) and ``nvs_text``
    (fourth). Columns: the reference view with the query tinted, the extracted object alone, the
    ground-truth object, the NVS mask (TP yellow, FP red, FN green).
    """
    columns = ("reference view + query", "extracted object alone", "ground truth object", "NVS mask: TP / FP / FN")
    gap, line, margin, scale = 6, 18, 8, 0.42
    panels = [[_panel(p, PANEL_HEIGHT) for p in (overlay(r["reference"], r["query"]), r["render"], r["truth_image"],
                                                 confusion_picture(r["image"], r["nvs"], r["truth"]))]
              for r in rows]
    pw = max((p.shape[1] for row in panels for p in row), default=320)
    ph = max((p.shape[0] for row in panels for p in row), default=60)
    width = 2 * margin + 4 * pw + 3 * gap
    top = margin + 2 * line  # the title, then the column headings
    height = top + max(1, len(rows)) * (ph + line + gap) + margin
    canvas = np.full((height, width, 3), 255, np.uint8)
    _put(canvas, title, margin, margin + line - 5, width - 2 * margin, 0.55)
    for c, name in enumerate(columns):
        _put(canvas, name, margin + c * (pw + gap), top - 5, pw, scale)
    if not rows:
        _put(canvas, "no object could be evaluated", margin, top + ph // 2, width - 2 * margin, 0.55)
    for r, (row, row_panels) in enumerate(zip(rows, panels)):
        y = top + r * (ph + line + gap)
        for c, p in enumerate(row_panels):
            x = margin + c * (pw + gap)
            canvas[y: y + p.shape[0], x: x + p.shape[1]] = p
        for c, key in ((0, "label"), (1, "extraction_text"), (3, "nvs_text")):
            _put(canvas, str(row.get(key, "")), margin + c * (pw + gap), y + ph + line - 5, pw, scale)
    write_rgb(path, canvas)
