"""``trace3d bench lift``: the cost of one contrastive-lifting iteration, sparse path vs rasterizer.

Figures (one JSON object), on a fitted room (scene/, poses/, gaussians/, consistent instance maps):

- ``sparse_ms`` / ``raster_ms``: ms per iteration (sample pixels of one view, render them, loss,
  backward, Adam step), median over repeats (the sparse path timed over 150 iterations after 60 of
  warm-up), for the preset's pixel count and for ``pixels`` of the measured step params, both with
  the step's loss (the fused kernel unless ``fused: false``);
  ``lift_speedup`` = raster_ms / sparse_ms (goal >= 20, whole iteration); ``sparse_autograd_ms``: the
  sparse path with the fused loss through autograd instead of the hand-written fast step (its twin);
  ``sparse_torch_loss_ms``: the sparse path with the torch autograd loss (the fused kernel's twin);
  ``render_speedup`` the same for the render + its backward alone (no loss).
- ``weights``: nnz and bytes of the per-view pixel-weight pools, and of one full view's weights.
- ``step_seconds``: wall time of the contrastive lift with the given step params (precompute + train).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch

from ..errors import Trace3DError

log = logging.getLogger(__name__)


def _labels_dir(room: Path) -> Path:
    # the consistent instance maps; the ground-truth instance maps stand in while a room has no merge yet
    for cand in ("merge-paper/instances", "merge-official/instances", "scene/instances"):
        if (room / cand).is_dir():
            return room / cand
    raise Trace3DError(f"{room}: no instance maps (merge-paper/instances, merge-official/instances or "
                       f"scene/instances); "
                       f"run the merge step for this room first.")


def _time_calls(step, count: int) -> float:
    """Median ms of ``count`` calls of ``step()``."""
    times = []
    for _ in range(count):
        start = time.perf_counter()
        step()
        times.append(time.perf_counter() - start)
    return float(np.median(times)) * 1000.0


def _time_iterations(trainer, path: str, count: int) -> float:
    return _time_calls(lambda: trainer.step(path), count)


def _time_autograd(trainer, count: int) -> float:
    # the sparse path through autograd (the fast step's twin: same loss kernel, gather and Adam)
    trainer.autograd_step("sparse")
    return _time_calls(lambda: trainer.autograd_step("sparse"), count)


def _time_render_only(trainer, path: str, count: int) -> float:
    from ..lifting.contrastive import render_pixels

    times = []
    for _ in range(count):
        v, rows = trainer.sample()
        start = time.perf_counter()
        if path == "sparse":
            out = trainer.pools.weights[v].render_rows(trainer.features, rows)
        else:
            out = render_pixels(trainer.model, trainer.pools.cameras[v], trainer.features,
                                trainer.pools.pixels[v][rows])
        out.sum().backward()
        times.append(time.perf_counter() - start)
    trainer.features.grad = None
    return float(np.median(times)) * 1000.0


def run_bench(room: Path, quick: bool = False, params: dict | None = None) -> dict:
    from ..lifting.contrastive import ContrastiveParams, ContrastiveTrainer, lift_features
    from ..params import from_mapping, to_dict
    from ..render.pixel_weights import pixel_weights
    from ..scene import Scene
    from ..tracing.git import load_fitted, load_label_maps

    room = Path(room)
    for part in ("scene", "poses", "gaussians/point_cloud.ply"):
        if not (room / part).exists():
            raise Trace3DError(f"{room / part}: missing; fit a room first or pass --room.")
    labels_dir = _labels_dir(room)
    scene = Scene.read(room / "scene")
    model, cameras = load_fitted(scene, room / "poses", room / "gaussians")
    train = [c for c in cameras if c.split == "train"]
    maps = load_label_maps(labels_dir, [c.name for c in train], "instance map")
    step = from_mapping(ContrastiveParams, {k: v for k, v in (params or {}).items() if k != "method"}, "bench params")
    result = {"room": str(room), "labels": str(labels_dir), "gaussians": len(model), "views": len(train),
              "width": train[0].width, "height": train[0].height, "torch_threads": torch.get_num_threads(),
              "step_params": to_dict(step)}
    start = time.perf_counter()
    full = pixel_weights(model.splats(), train[0])
    result["full_view_weights"] = {"seconds": time.perf_counter() - start, "nnz": full.nnz, "bytes": full.nbytes,
                                   "nnz_per_pixel": full.nnz / max(1, full.pixels.size),
                                   "all_views_bytes_estimate": full.nbytes * len(train)}
    repeats = 5 if quick else 15
    rows = []
    for pixels in sorted({step.pixels, 4096}):
        p = from_mapping(ContrastiveParams, {**to_dict(step), "pixels": pixels, "iterations": 1, "query": {}})
        trainer = ContrastiveTrainer(model, train[:2] if quick else train, maps[:2] if quick else maps, p)
        for _ in range(repeats * 4):  # warm-up: the first pass over the views' pools runs from cold memory
            trainer.step("sparse")
        trainer.step("raster")
        sparse_ms = _time_iterations(trainer, "sparse", repeats * 10)
        raster_ms = _time_iterations(trainer, "raster", repeats)
        autograd_ms = _time_autograd(trainer, repeats * 2)
        trainer.params.fused = False  # the torch autograd loss (the fused kernel's twin) on the sparse path
        trainer.step("sparse")
        torch_loss_ms = _time_iterations(trainer, "sparse", repeats * 2)
        trainer.params.fused = p.fused
        sparse_r = _time_render_only(trainer, "sparse", repeats * 4)
        raster_r = _time_render_only(trainer, "raster", repeats)
        rows.append({"pixels": pixels, "sparse_ms": sparse_ms, "raster_ms": raster_ms,
                     "lift_speedup": raster_ms / sparse_ms, "sparse_autograd_ms": autograd_ms,
                     "sparse_torch_loss_ms": torch_loss_ms,
                     "sparse_render_ms": sparse_r,
                     "raster_render_ms": raster_r, "render_speedup": raster_r / sparse_r,
                     "pool_nnz": trainer.pools.nnz, "pool_bytes": trainer.pools.nbytes,
                     "precompute_seconds": trainer.precompute_seconds})
    result["iterations"] = rows
    main = next(r for r in rows if r["pixels"] == step.pixels)
    result["lift_speedup"] = main["lift_speedup"]
    result["sparse_ms"] = main["sparse_ms"]
    result["raster_ms"] = main["raster_ms"]
    if not quick:
        start = time.perf_counter()
        _, history, info = lift_features(model, train, maps, step)
        result["step_seconds"] = time.perf_counter() - start
        result["step_info"] = info
        result["step_final_loss"] = float(np.mean([v for _, v in history[-max(1, len(history) // 20):]]))
    return result


FORMS = {
    "official": {"preset": "official"},
    "printed_lr1e-5": {"kernel": "printed", "temperature": 0.01, "lr": 1e-5},
    "printed_lr5e-3": {"kernel": "printed", "temperature": 0.01, "lr": 0.005},
    "gaussian_t1_lr5e-3": {"kernel": "gaussian", "temperature": 1.0, "lr": 0.005},
}


def compare_forms(room: Path, iterations: int = 1500, pixels: int = 1024, max_objects: int = 8) -> dict:
    """``trace3d bench lift-forms``: train each loss form (:data:`FORMS`) on ``room`` with the ground-truth
    instance maps as labels, then query each of up to ``max_objects`` objects from the training view
    where it is largest (its ground-truth mask) and score the predicted masks on the test views where
    the object has at least 200 pixels (mean IoU)."""
    from ..lifting import ObjectQuery
    from ..lifting.contrastive import ContrastiveParams, lift_features
    from ..lifting.query import FeatureLifted, iou
    from ..scene import Scene
    from ..tracing.git import load_fitted, load_label_maps

    room = Path(room)
    scene = Scene.read(room / "scene")
    if not scene.has_instances:
        raise Trace3DError(f"{room / 'scene'}: no ground-truth instance maps to score the forms against.")
    model, cameras = load_fitted(scene, room / "poses", room / "gaussians")
    train = [c for c in cameras if c.split == "train"]
    test = [c for c in cameras if c.split == "test"]
    names = [c.name for c in train]
    maps = load_label_maps(room / "scene" / "instances", names, "instance map")
    best: dict[int, tuple[int, str]] = {}
    for cam, m in zip(train, maps):
        ids, counts = np.unique(m[m > 0], return_counts=True)
        for i, k in zip(ids.tolist(), counts.tolist()):
            if k >= 400 and k > best.get(i, (0, ""))[0]:
                best[i] = (k, cam.name)
    objects = sorted(best)[:: max(1, len(best) // max_objects)][:max_objects]
    truths = {c.name: scene.instances(c.name) for c in test}
    out = {"room": str(room), "iterations": iterations, "pixels": pixels, "objects": objects, "forms": {}}
    for name, kw in FORMS.items():
        p = ContrastiveParams(**{"iterations": iterations, "pixels": pixels, **kw})
        start = time.perf_counter()
        features, history, info = lift_features(model, train, maps, p)
        seconds = time.perf_counter() - start
        lifted = FeatureLifted(model, features, train)
        scores = []
        for o in objects:
            ref = best[o][1]
            query = ObjectQuery(ref, maps[names.index(ref)] == o, o)
            for cam, mask in zip(test, lifted.object_masks(query, test)):
                truth = truths[cam.name] == o
                if truth.sum() >= 200:
                    scores.append(iou(mask, truth))
        out["forms"][name] = {"params": kw, "seconds": seconds, "loss_first": history[0][1],
                              "loss_last": float(np.mean([v for _, v in history[-10:]])),
                              "test_miou": float(np.mean(scores)) if scores else None, "pairs": len(scores), **info}
        log.info("%s: test mIoU %s in %.1f s", name, out["forms"][name]["test_miou"], seconds)
    return out
