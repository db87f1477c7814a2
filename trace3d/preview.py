"""Pictures for a quick visual check: contact sheets of canonical scenes, and label maps and masks
painted over their images (:func:`label_overlay`, :func:`mask_overlay`: the patches' and the merge's
previews).

The scene's contact sheet shows what an importer wrote, one row per view (a few views spread over the
sequence): the RGB image, the ground-truth instance map in random distinct colours (when the scene has
``instances/``) and the depth map (when it has ``depth/``); each panel is titled with the frame name and
split.
"""

from __future__ import annotations

import logging
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .io import atomic_file  # noqa: E402
from .scene import Scene  # noqa: E402

log = logging.getLogger(__name__)

PANEL_WIDTH_PX = 320  # every panel is this wide; its height follows the image aspect ratio
TITLE_PX = 28  # room for the panel title above each image
DPI = 100


def instance_colors(max_id: int, seed: int = 0) -> np.ndarray:
    """[max_id + 1, 3] float RGB: id 0 black, the other ids well-separated random colours.

    Hues follow the golden-ratio sequence from a seeded random start (neighbouring ids get distant
    hues); saturation and value alternate so that equal hues at different ids still differ.
    """
    rng = np.random.default_rng(seed)
    ids = np.arange(max_id + 1)
    hue = (rng.uniform() + ids * 0.618033988749895) % 1.0
    sat = 0.55 + 0.4 * ((ids * 7) % 3) / 2
    val = 0.65 + 0.35 * ((ids * 5) % 4) / 3
    colors = matplotlib.colors.hsv_to_rgb(np.stack([hue, sat, val], axis=1))
    colors[0] = 0.0
    return colors


def colorize_instances(ids: np.ndarray, seed: int = 0) -> np.ndarray:
    """[H, W] integer ids -> [H, W, 3] float RGB (0 black)."""
    ids = np.asarray(ids, dtype=np.int64)
    return instance_colors(int(ids.max(initial=0)), seed)[ids]


def _colour_table(count: int, seed: int = 0) -> np.ndarray:
    """[count + 1, 3] float colours in [0.15, 1], row 0 black."""
    rng = np.random.default_rng(seed)
    table = rng.uniform(0.15, 1.0, size=(count + 1, 3))
    table[0] = 0.0
    return table


def mask_overlay(image: np.ndarray, masks: np.ndarray, alpha: float = 0.55) -> np.ndarray:
    """[H, W, 3] float image with every mask painted in its own colour, finest on top.

    Args:
        image: [H, W, 3] uint8.
        masks: [M, H, W] bool.
    """
    out = image.astype(np.float64) / 255.0
    colours = _colour_table(len(masks), seed=1)[1:]
    areas = masks.sum(axis=(1, 2))
    for m in np.argsort(-areas, kind="stable"):  # largest first, so finer masks stay visible
        out[masks[m]] = (1 - alpha) * out[masks[m]] + alpha * colours[m]
    return out


def label_overlay(image: np.ndarray, labels: np.ndarray, alpha: float = 0.7) -> np.ndarray:
    """[H, W, 3] float image with label ids [H, W] in random colours (0 left dark)."""
    colours = _colour_table(int(labels.max(initial=0)), seed=2)
    base = image.astype(np.float64) / 255.0
    out = (1 - alpha) * base + alpha * colours[labels]
    out[labels == 0] = 0.3 * base[labels == 0]
    return out


def pick_views(scene: Scene, max_views: int) -> list:
    """Up to ``max_views`` cameras spread evenly over the sequence; includes a test view if any."""
    cams = scene.cameras
    n = min(max_views, len(cams))
    picks = [cams[i] for i in np.linspace(0, len(cams) - 1, n).round().astype(int)]
    tests = scene.test_cameras
    if tests and not any(c.split == "test" for c in picks) and n > 1:
        picks[-1] = tests[len(tests) // 2]
    seen, out = set(), []
    for c in picks:
        if c.name not in seen:
            seen.add(c.name)
            out.append(c)
    return out


def preview_size(scene: Scene, max_views: int = 4) -> tuple[int, int]:
    """(width, height) in pixels of the PNG that :func:`scene_preview` writes for ``scene``."""
    views = pick_views(scene, max_views)
    cols = 1 + int(scene.has_instances) + int(scene.has_depth)
    panel_h = max(round(PANEL_WIDTH_PX * c.height / c.width) for c in views) + TITLE_PX
    return cols * PANEL_WIDTH_PX, len(views) * panel_h


def scene_preview(scene: Scene, out_png: Path, max_views: int = 4) -> None:
    """Write a contact sheet PNG of up to ``max_views`` views of ``scene`` to ``out_png`` (atomically).

    Columns: RGB, instance ids (if the scene has instances/), depth (if it has depth/).
    """
    views = pick_views(scene, max_views)
    width, height = preview_size(scene, max_views)
    cols = width // PANEL_WIDTH_PX
    panel_h = height // len(views)
    # +0.25 px: matplotlib truncates figsize * dpi, and w / DPI * DPI can land just below w
    fig = plt.figure(figsize=((width + 0.25) / DPI, (height + 0.25) / DPI), dpi=DPI)
    fig.patch.set_facecolor("white")
    for row, cam in enumerate(views):
        panels = [("rgb", scene.image(cam.name))]
        if scene.has_instances:
            ids = scene.instances(cam.name)
            panels.append((f"instances ({len(np.unique(ids[ids > 0]))} ids)", colorize_instances(ids)))
        if scene.has_depth:
            depth = scene.depth(cam.name)
            valid = depth > 0
            shown = np.ma.masked_where(~valid, depth)
            hi = float(depth[valid].max()) if valid.any() else 1.0
            panels.append((f"depth (max {hi:.2f})", shown))
        for col, (label, image) in enumerate(panels):
            # axes in figure fractions: exact panel placement, no tight_layout (fixed output size)
            left = col * PANEL_WIDTH_PX / width
            bottom = 1.0 - ((row + 1) * panel_h) / height
            ax = fig.add_axes((left, bottom, PANEL_WIDTH_PX / width, (panel_h - TITLE_PX) / height))
            if label.startswith("depth"):
                ax.imshow(image, cmap="turbo", interpolation="nearest", vmin=0.0, vmax=hi)
            else:
                ax.imshow(image, interpolation="nearest")
            ax.set_aspect("auto")
            ax.set_axis_off()
            ax.set_title(f"{cam.name} [{cam.split}] {label}", fontsize=8, pad=3)
    out_png = Path(out_png)
    with atomic_file(out_png) as tmp:
        fig.savefig(tmp, dpi=DPI, format="png", facecolor="white")
    plt.close(fig)
    log.info("wrote preview %s (%d views)", out_png, len(views))
