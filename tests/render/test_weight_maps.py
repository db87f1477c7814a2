"""A view's feature map, instance maps and object masks from its blend-order pixel weights
(render/weight_maps.py) against their twins, the rasterizer's renders: every bit."""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads OpenMP (spinning waits stall a busy box)

import numpy as np
import pytest
import torch

from tests.tracing.test_tracing import concat, grid_model, two_objects
from trace3d.errors import Trace3DError
from trace3d.extract import object_mask
from trace3d.lifting.contrastive import instance_map as rendered_instance_map
from trace3d.lifting.contrastive import render_feature_map
from trace3d.render import weight_maps
from trace3d.render.pixel_weights import pixel_weights, pixel_weights_blend_order


def layered_scene(back_first: bool):
    """Two overlapping layers seen from oblique cameras: pixels blend several splats, some past the
    transmittance floor (``back_first``: the far layer's Gaussians get the lower indices)."""
    model, _, cameras = two_objects()
    back = grid_model(-0.7, 0.7, -0.5, 0.5, 2.6, step=0.07)
    back.set("opacity_logits", torch.full((len(back),), 0.3))
    model.set("opacity_logits", torch.full((len(model),), 2.5))
    return (concat(back, model) if back_first else concat(model, back)), cameras


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("back_first", [False, True])
def test_maps_from_weights_are_the_rasterizers_bits(back_first, threads):
    import numba

    model, cameras = layered_scene(back_first)
    rng = np.random.default_rng(3)
    n = len(model)
    saved = numba.get_num_threads()
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    try:
        for cam in cameras[:2]:
            with torch.no_grad():
                w = pixel_weights_blend_order(model.splats(), cam)
            assert w.blend_order and w.nnz > cam.width * cam.height  # several splats per pixel
            for dim in (3, 16, 21):  # below, at and past the forward kernel's 8 fixed channel planes
                feats = rng.normal(size=(n, dim)).astype(np.float32)
                ours = weight_maps.feature_map(w, feats)
                twin = render_feature_map(model, cam, feats)
                assert ours.shape == twin.shape and ours.dtype == np.float32
                np.testing.assert_array_equal(ours.view(np.uint32), twin.view(np.uint32))
            for count in (1, 2, 5, 12):
                instance = rng.integers(0, count + 1, n)
                instance[: n // 3] = rng.integers(1, min(count, 2) + 1, n // 3)  # near-ties between instances 1 and 2
                ours = weight_maps.instance_map(w, instance, count)
                np.testing.assert_array_equal(ours, rendered_instance_map(model, cam, instance, count))
                assert (ours > 0).any()
            for share in (0.05, 0.5, 0.95):
                keep = rng.random(n) < share
                mask = weight_maps.set_mask(w, keep)
                np.testing.assert_array_equal(mask, object_mask(model, cam, keep))
                assert mask.any() and not mask.all()
            np.testing.assert_array_equal(weight_maps.instance_map(w, np.zeros(n, np.int64), 0), 0)
    finally:
        numba.set_num_threads(saved)


def test_maps_refuse_weights_they_cannot_read():
    model, cameras = layered_scene(False)
    cam = cameras[0]
    feats = np.zeros((len(model), 4), np.float32)
    with torch.no_grad():
        by_gaussian = pixel_weights(model.splats(), cam)  # rows by Gaussian: other float32 sums
        subset = pixel_weights_blend_order(model.splats(), cam).rows(np.arange(10))
        w = pixel_weights_blend_order(model.splats(), cam)
    for bad in (by_gaussian, subset):
        with pytest.raises(Trace3DError, match="blending order"):
            weight_maps.feature_map(bad, feats)
    with pytest.raises(Trace3DError, match="features must be"):
        weight_maps.feature_map(w, feats[1:])
    with pytest.raises(Trace3DError, match="instance ids"):
        weight_maps.instance_map(w, np.full(len(model), 3), 2)


def test_feature_lifted_reads_its_maps_from_the_kept_weights():
    """FeatureLifted.feature_map is the rendered map (the twin); the weights of a view asked for outside
    the pass are kept under their budget and then give the map, the instance map and the masks."""
    from trace3d.lifting.query import FeatureLifted

    model, cameras = layered_scene(True)
    feats = np.random.default_rng(0).normal(size=(len(model), 6)).astype(np.float32)
    lifted = FeatureLifted(model, feats, cameras[:1], map_budget_mb=0)
    cam = cameras[1]
    np.testing.assert_array_equal(lifted.feature_map(cam).view(np.uint32),
                                  render_feature_map(model, cam, feats).view(np.uint32))
    assert lifted.blend_weights(cam) is lifted.blend_weights(cam)  # kept
    none_kept = FeatureLifted(model, feats, cameras[:1], weights_budget_mb=0)
    assert none_kept.blend_weights(cam) is not none_kept.blend_weights(cam)
