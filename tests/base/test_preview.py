"""Tests of the scene contact sheet (trace3d.preview)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from trace3d import preview
from trace3d.scene import Camera, Scene, write_cameras, write_frame


def _write_scene(root: Path, n_views: int, width: int, height: int, instances: bool, depth: bool) -> Scene:
    rng = np.random.default_rng(0)
    K = np.array([[50.0, 0, width / 2], [0, 50.0, height / 2], [0, 0, 1]])
    cams = []
    for i in range(n_views):
        w2c = np.eye(4)
        w2c[0, 3] = 0.1 * i
        cams.append(Camera(f"f{i:02d}", "test" if i % 3 == 1 else "train", width, height, K, w2c))
        rgb = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
        ids = rng.integers(0, 20, (height, width)).astype(np.uint16) if instances else None
        dep = rng.uniform(0.5, 4.0, (height, width)) if depth else None
        if dep is not None:
            dep[:2] = 0.0  # invalid pixels are masked
        write_frame(root, cams[-1].name, rgb, ids, dep)
    write_cameras(root, cams)
    return Scene.read(root)


@pytest.mark.parametrize(
    "n_views, instances, depth, cols",
    [(6, True, True, 3), (6, True, False, 2), (2, False, False, 1), (5, False, True, 2)],
)
def test_preview_png_has_expected_size(tmp_path, n_views, instances, depth, cols):
    scene = _write_scene(tmp_path / "scene", n_views, 40, 30, instances, depth)
    out = tmp_path / "preview.png"
    preview.scene_preview(scene, out, max_views=4)
    rows = min(4, n_views)
    expected = (cols * preview.PANEL_WIDTH_PX, rows * (round(preview.PANEL_WIDTH_PX * 30 / 40) + preview.TITLE_PX))
    assert preview.preview_size(scene, 4) == expected
    with Image.open(out) as im:
        assert im.size == expected
        pixels = np.asarray(im.convert("RGB"))
    assert pixels.std() > 10  # not a blank page
    assert not list(tmp_path.glob(".preview.png.tmp*"))  # written atomically


def test_picked_views_are_spread_and_include_a_test_view(tmp_path):
    scene = _write_scene(tmp_path / "scene", 9, 16, 12, False, False)
    views = preview.pick_views(scene, 3)
    assert len(views) == 3 and views[0].name == "f00"
    assert any(v.split == "test" for v in views)
    assert len({v.name for v in views}) == 3


def test_instance_colors_are_distinct_and_zero_is_black():
    colors = preview.instance_colors(200)
    assert colors.shape == (201, 3)
    assert np.all(colors[0] == 0)
    # every pair of the first 60 ids differs clearly
    sub = colors[1:61]
    dist = np.linalg.norm(sub[:, None] - sub[None], axis=-1) + np.eye(60)
    assert dist.min() > 0.05
    ids = np.array([[0, 3], [3, 7]])
    rgb = preview.colorize_instances(ids)
    assert rgb.shape == (2, 2, 3) and np.allclose(rgb[0, 1], rgb[1, 0]) and not np.allclose(rgb[0, 1], rgb[1, 1])
