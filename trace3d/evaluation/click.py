"""Click-extract IoU: one click per object returns the whole object (``trace3d extract``'s selection).

For every evaluated object with a reference view (the training view the query protocols use,
:meth:`~trace3d.evaluation.groundtruth.GroundTruth.reference`), the click is the deepest pixel of its
ground-truth mask there (:func:`~trace3d.lifting.query.deepest_pixel`: the pixel farthest from the
mask's border). :class:`~trace3d.extract.ClickScene` selects the object's Gaussians from that click
alone (the rendered feature at the pixel and the Gaussians under it; nothing else of the mask is
used; ``selection: region``, the 2D region growing of before, uses the rendered feature map of the
clicked view). The selection is scored at the object's novel-view (NVS) views, the test views that show it
with at least ``min_pixels`` pixels: its mask there is where the selected Gaussians hold more of the
rendered weight than the rest of the scene (:func:`~trace3d.extract.object_mask`, occluders
included; read from the view's blend-order pixel weights, :func:`trace3d.render.weight_maps.set_mask`,
the same bits, when the lifted scene keeps them at this ``near``), against the ground-truth mask. An
object's click IoU is the mean over its views; the figure is the mean over the objects that have a
reference and an NVS view (an empty selection scores 0).
"""

from __future__ import annotations

import logging
import time

import numpy as np

log = logging.getLogger(__name__)


def click_scene(lifted, params):
    """The :class:`~trace3d.extract.ClickScene` that :func:`evaluate_clicks` selects in (its kNN graph is
    the segment score's too when their ``neighbours`` agree: the evaluation makes it once)."""
    import dataclasses

    from ..extract import ClickScene

    return ClickScene(lifted.model.means.detach().double().numpy(), lifted.features, lifted.visibility(),
                      dataclasses.replace(params, selection="features") if params.selection == "region" else params)


def evaluate_clicks(lifted, gt, by_name: dict, params, min_pixels: int, near: float = 0.01, click=None) -> dict:
    """Click IoU of a feature-lifted scene (module docstring).

    Args:
        lifted: a :class:`~trace3d.lifting.query.FeatureLifted` (``model``, ``features``, ``visibility()``,
            ``feature_map``, ``view_weights``); gt: the evaluation's ground truth; by_name: frame -> camera;
            params: :class:`~trace3d.extract.ExtractParams` (``selection``, threshold, graph);
            min_pixels: the protocol's ``min_pixels`` (recorded; the views are the ground truth's NVS views);
            click: :func:`click_scene` of ``lifted`` and ``params`` if made already.
    """
    import dataclasses

    from ..extract import _select_region, click_seeds, click_weights, object_mask
    from ..lifting.query import deepest_pixel, iou
    from ..render.weight_maps import set_mask

    start = time.perf_counter()
    model = lifted.model
    # the views' weights that the lifted scene keeps (FeatureLifted: the pass's test views, while they fit
    # its weights budget): a mask is read from them; a view whose weights are not kept is rendered (the
    # loop visits each view once per object, and recomputing a dropped view's weights costs more than a
    # two-channel render)
    kept = getattr(getattr(lifted, "_shared", None), "weights", None) \
        if getattr(getattr(lifted, "params", None), "near", None) == near else None

    def mask_of(camera, keep):
        weights = kept.get(camera.name) if kept is not None else None
        return set_mask(weights, keep) if weights is not None else object_mask(model, camera, keep, near)
    click = click_scene(lifted, params) if click is None else click
    objects = []
    for oid in gt.object_ids:
        query = gt.query(oid)
        views = gt.nvs_views(oid)
        if query is None or not views:
            continue
        camera = by_name[query.reference]
        x, y = deepest_pixel(query.mask)
        if params.selection == "region":
            keep = _select_region(lifted, model, camera, lifted.feature_map(camera), x, y,
                                  dataclasses.replace(params, view=query.reference))[0]
        else:
            # the clicked view's weights when the lifted scene keeps them (the reference views': the pass
            # made them for the query points), else the 3x3 pixels' traced alone: the same seeds and sums
            full = kept.get(camera.name) if kept is not None else None
            seeds, weights = click_seeds(full if full is not None else click_weights(model, camera, x, y, near=near),
                                         x, y)
            keep = click.select(lifted.feature_map(camera)[y, x], seeds, weights)
        scores = [iou(mask_of(by_name[f], keep), gt.mask(oid, f)) for f in views]
        objects.append({"id": oid, "reference": query.reference, "point": [int(x), int(y)],
                        "gaussians": int(keep.sum()), "threshold": float(click.last_threshold),
                        "iou": float(np.mean(scores)),
                        "views": [{"frame": f, "iou": float(v)} for f, v in zip(views, scores)]})
    miou = float(np.mean([o["iou"] for o in objects])) if objects else None
    out = {"mIoU": miou, "objects": len(objects), "selection": params.selection, "threshold": click.threshold,
           "data_threshold": click.data_threshold, "min_pixels": int(min_pixels), "per_object": objects,
           "seconds": time.perf_counter() - start}
    log.info("click extract (%s selection, threshold %.3g): mIoU %s over %d objects, %.1f s", params.selection,
             click.threshold, "n/a" if miou is None else f"{miou:.3f}", len(objects), out["seconds"])
    return out
