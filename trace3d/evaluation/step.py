"""The ``evaluate`` step: 3D object extraction and novel-view segmentation of one lifted scene.

Writes into ``out_dir``:

    metrics.json     per object (query, per-view scores, means), scene means, the protocol's
                     settings, the lifting's lift.json and the variant label given by the rule;
                     with ``single_point`` both tasks again with one query point
                     (``"single_point"``), with ``panoptic`` the PQ^scene of the lifted features
                     (``"panoptic"``, :mod:`.panoptic`)
    pictures.png     a few objects: reference view + query, the object rendered alone beside the
                     ground truth, the novel-view mask coloured TP / FP / FN
    objects/<id>.ply the object's Gaussians (the workflow puts objects/ beside eval/: --objects) (standard 3DGS/2DGS PLY layout; ``GaussianModel.read_ply``)
    objects/<id>.png the object alone from ``turntable_views`` directions

Scene means weigh every object equally: an object's score is the mean over its scored views, the
scene's mIoU / PSNR / mAcc the mean over objects with at least one scored view (objects without
one are listed under ``skipped`` with the reason). ``pooled`` gives the mean over all (object, view)
pairs as well.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import logging
import pkgutil
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from ..errors import Trace3DError
from ..io import write_json
from ..params import from_mapping, to_dict
from ..scene import Scene, scene_name
from .extraction import evaluate_extraction, render_alone
from .groundtruth import GroundTruth
from .metrics import mean_or_none
from .nvs import evaluate_nvs
from .panoptic import evaluate_panoptic
from .params import EvaluateParams
from .pictures import world_up, write_pictures, write_turntable

log = logging.getLogger(__name__)


def register_lifting_methods() -> None:
    """Import every module of :mod:`trace3d.lifting` so that each method registers its loader
    (the evaluation names no method; a method is found through ``lift.json``)."""
    from .. import lifting

    for info in sorted(pkgutil.iter_modules(lifting.__path__), key=lambda m: m.name):
        try:
            importlib.import_module(f"{lifting.__name__}.{info.name}")
        except ImportError as exc:  # a method with a missing optional dependency cannot be loaded
            log.warning("lifting method module %s is unavailable: %s", info.name, exc)


class Phases:
    """Wall and CPU seconds per named phase of one evaluation (``trace3d bench evaluate``); never
    written into metrics.json (its bytes do not depend on timing beyond the ``seconds`` fields)."""

    def __init__(self) -> None:
        self.wall: dict[str, float] = {}
        self.cpu: dict[str, float] = {}

    @contextlib.contextmanager
    def __call__(self, name: str):
        wall, cpu = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            self.wall[name] = self.wall.get(name, 0.0) + time.perf_counter() - wall
            self.cpu[name] = self.cpu.get(name, 0.0) + time.process_time() - cpu

    def to_json(self) -> dict:
        return {name: {"wall_s": round(self.wall[name], 3), "cpu_s": round(self.cpu[name], 3)} for name in self.wall}


def _means(views: list[dict], keys: tuple[str, ...]) -> dict:
    return {k: mean_or_none([v[k] for v in views]) for k in keys}


def _picture_choice(objects: list[dict], count: int) -> list[int]:
    """Indices of ``count`` evaluated objects spread from the best to the worst extraction IoU."""
    scored = [i for i, o in enumerate(objects) if o["extraction"]["iou"] is not None]
    scored.sort(key=lambda i: (-objects[i]["extraction"]["iou"], objects[i]["id"]))
    if count <= 0 or not scored:
        return []
    if len(scored) <= count:
        return scored
    picks = np.linspace(0, len(scored) - 1, count).round().astype(int)
    return [scored[k] for k in sorted(set(picks.tolist()))]


def run_evaluate(scene_dir: Path, poses_dir: Path | None, gaussians_dir: Path, lift_dir: Path, out_dir: Path,
                 params: dict, label: dict | None = None, objects_dir: Path | None = None,
                 phases: Phases | None = None) -> dict:
    """Evaluate the lifted scene of ``lift_dir`` (over ``gaussians_dir``) on the scene's ground truth;
    the object files go to ``objects_dir`` (default ``out_dir/objects``); ``phases`` (optional)
    collects the seconds of each phase."""
    from ..lifting import load_lifted
    from ..tracing.git import load_fitted

    p = from_mapping(EvaluateParams, params, "evaluate params")
    if label is not None and not isinstance(label, dict):
        raise Trace3DError(f"evaluate: --label must be a JSON mapping, got {label!r}.")
    start = time.perf_counter()
    ph = phases if phases is not None else Phases()
    with ph("load"):
        scene = Scene.read(scene_dir)
        model, cameras = load_fitted(scene, Path(poses_dir) if poses_dir else None, Path(gaussians_dir))
        train = [c for c in cameras if c.split == "train"]
        register_lifting_methods()
        lifted = load_lifted(lift_dir, model, scene, train)
        lift_info = json.loads((Path(lift_dir) / "lift.json").read_text())
    with ph("ground_truth"):
        gt = GroundTruth(scene, cameras, p)
    by_name = {c.name: c for c in cameras}
    out_dir = Path(out_dir)
    objects_dir = Path(objects_dir) if objects_dir is not None else out_dir / "objects"
    if p.object_files:
        objects_dir.mkdir(parents=True, exist_ok=True)
    up = world_up(train)
    images: dict[str, np.ndarray] = {}

    def image(frame: str) -> np.ndarray:
        if frame not in images:
            images[frame] = scene.image(frame).astype(np.float32) / 255.0
        return images[frame]

    # the single-point sibling is made first, so that its queries join the one pass over the views
    one = lifted.with_query(max_queries=1) if p.single_point and hasattr(lifted, "with_query") else None
    if hasattr(lifted, "plan"):
        with ph("object_gaussians"):
            _plan_queries(lifted, one, gt, by_name)
    objects, skipped, picture_data = [], [], {}
    bar = tqdm(gt.object_ids, desc="evaluate objects", leave=False,
               mininterval=0.5 if sys.stderr.isatty() else 30.0)
    for oid in bar:
        query = gt.query(oid)
        if query is None:
            skipped.append({"id": oid, "name": gt.name(oid),
                            "reason": f"no training view shows it with at least {p.min_pixels} pixels"})
            continue
        keep, ext_frames, nvs_frames, extraction, nvs, nvs_preds = _score_object(
            lifted, query, oid, gt, model, by_name, image, p, lift_dir, ph)
        entry = {
            "id": oid, "name": gt.name(oid), "reference": query.reference, "query_pixels": int(query.mask.sum()),
            "gaussians": int(keep.sum()),
            "extraction": {**_means(extraction, ("iou", "psnr")), "views": extraction},
            "nvs": {**_means(nvs, ("iou", "acc")), "views": nvs},
            "ground_truth_views": [v.to_json() for v in gt.info[oid]],
        }
        objects.append(entry)
        if not extraction and not nvs:
            skipped.append({"id": oid, "name": gt.name(oid),
                            "reason": f"no scored view ({p.views} views, >= {p.min_pixels} px, not occluded)"})
        obj_model = model.subset(torch.from_numpy(keep))
        if p.object_files:
            with ph("object_files"):
                obj_model.write_ply(objects_dir / f"{oid}.ply")
                write_turntable(objects_dir / f"{oid}.png", obj_model, up, p.turntable_views, p.turntable_size,
                                p.near)
        # the picture view: the scored extraction view (else NVS view) with the most ground-truth pixels
        frames = ext_frames or nvs_frames
        if frames:
            with ph("picture_renders"):
                best = _picture_frame(gt, oid, frames)
                rgb, _ = render_alone(obj_model, by_name[best], p.near)
                pred = nvs_preds[nvs_frames.index(best)] if best in nvs_frames else \
                    lifted.object_masks(query, [by_name[best]])[0]
                picture_data[oid] = {"frame": best, "render": rgb, "pred": np.asarray(pred, bool)}

    summary = _summary(objects, p)
    extra = {}
    if p.single_point:
        with ph("single_point"):
            extra["single_point"] = _single_point(lifted, lift_info, gt, model, by_name, image, p, lift_dir, one)
    if p.panoptic:
        with ph("panoptic"):
            extra["panoptic"] = _panoptic(lifted, lift_info, gt, cameras, by_name, p)
    clicks = _ClickScene(lifted, p)
    if p.segment:
        with ph("segment"):
            extra["segment"] = _segment(lifted, lift_info, gt, cameras, by_name, p, clicks)
    if p.click:
        with ph("click"):
            extra["click"] = _click(lifted, lift_info, gt, by_name, p, clicks)
    with ph("pictures"):
        rows = []
        for i in _picture_choice(objects, p.picture_objects):
            o = objects[i]
            data = picture_data.get(o["id"])
            if data is None:
                continue
            frame = data["frame"]
            truth = gt.mask(o["id"], frame)
            ext = next((v for v in o["extraction"]["views"] if v["frame"] == frame), None)
            nv = next((v for v in o["nvs"]["views"] if v["frame"] == frame), None)
            rows.append({
                "reference": image(o["reference"]), "query": gt.mask(o["id"], o["reference"]),
                "render": data["render"], "truth_image": image(frame) * truth[..., None], "image": image(frame),
                "nvs": data["pred"], "truth": truth,
                "label": f"{o['id']} {o['name']}  (ref. {o['reference']})",
                "extraction_text": f"{frame}: IoU {ext['iou']:.2f}, PSNR {ext['psnr']:.1f} dB" if ext else frame,
                "nvs_text": f"{frame}: IoU {nv['iou']:.2f}" if nv else "",
            })
        method = lift_info.get("method", "?")
        name = (label or {}).get("variant", method)
        title = f"{scene_name(scene_dir, scene.meta)} / {name}: object mIoU " \
                f"{_fmt(summary['extraction']['mIoU'])}, NVS mIoU {_fmt(summary['nvs']['mIoU'])}"
        write_pictures(out_dir / "pictures.png", rows, title)
    seconds = time.perf_counter() - start
    metrics = {
        "scene": scene_name(scene_dir, scene.meta),
        "variant": label or {},
        "protocol": p.protocol,
        "params": to_dict(p),
        "lift": lift_info,
        "gaussians": int(len(model)),
        "occlusion_test": bool(gt.has_depth),
        **summary,
        "objects": objects,
        "skipped": skipped,
        **extra,
        "seconds": seconds,
    }
    with ph("write"):
        write_json(out_dir / "metrics.json", metrics)
    log.info("evaluate: %d objects (%d skipped), object mIoU %s, PSNR %s, NVS mIoU %s, %.1f s", len(objects),
             len(skipped), _fmt(summary["extraction"]["mIoU"]), _fmt(summary["extraction"]["PSNR"], 1),
             _fmt(summary["nvs"]["mIoU"]), seconds)
    return metrics


def _picture_frame(gt: GroundTruth, oid: int, frames: list[str]) -> str:
    """The picture view among ``frames`` (the scored extraction views, else NVS views): the one with the
    most ground-truth pixels (ties: the later name)."""
    return max(frames, key=lambda f: (int(gt.mask(oid, f).sum()), f))


def _plan_queries(lifted, one, gt: GroundTruth, by_name: dict) -> None:
    """Ask the lifted scene (and its single-point sibling ``one``) for what the object loop will ask,
    then answer it all in one pass over the views (:meth:`~trace3d.lifting.query.FeatureLifted.plan`):
    per object its Gaussians and its masks at the NVS views and at the picture view."""
    for oid in gt.object_ids:
        query = gt.query(oid)
        if query is None:
            continue
        ext_frames, nvs_frames = gt.extraction_views(oid), gt.nvs_views(oid)
        frames = list(nvs_frames)
        if ext_frames or nvs_frames:
            best = _picture_frame(gt, oid, ext_frames or nvs_frames)
            if best not in frames:
                frames.append(best)
        lifted.plan(query, [by_name[f] for f in frames])
        if one is not None:
            one.plan(query, [by_name[f] for f in nvs_frames])
    lifted.run_plan()


def _score_object(lifted, query, oid: int, gt: GroundTruth, model, by_name: dict, image, p: EvaluateParams,
                  lift_dir: Path, ph: Phases | None = None):
    """Both tasks for one object: (keep [N] bool, extraction frames, NVS frames, extraction scores,
    NVS scores, NVS masks)."""
    ph = ph if ph is not None else Phases()
    with ph("object_gaussians"):
        keep = np.asarray(lifted.object_gaussians(query))
    if keep.shape != (len(model),) or keep.dtype != bool:
        raise Trace3DError(f"evaluate: the lifted scene of {lift_dir} returned object Gaussians of shape "
                           f"{keep.shape} ({keep.dtype}); expected [{len(model)}] bool.")
    ext_frames, nvs_frames = gt.extraction_views(oid), gt.nvs_views(oid)
    with ph("extraction"):
        ext_cams = [by_name[f] for f in ext_frames]
        ext_truth = [gt.mask(oid, f) for f in ext_frames]
        extraction = evaluate_extraction(model, keep, ext_cams, ext_truth, [image(f) for f in ext_frames],
                                         p.alpha_eps, p.psnr_margin, p.near)
    with ph("nvs"):
        nvs_cams = [by_name[f] for f in nvs_frames]
        nvs_truth = [gt.mask(oid, f) for f in nvs_frames]
        nvs, nvs_preds = evaluate_nvs(lifted, query, nvs_cams, nvs_truth, p.accuracy)
    return keep, ext_frames, nvs_frames, extraction, nvs, nvs_preds


def _summary(objects: list[dict], p: EvaluateParams) -> dict:
    """Scene means of both tasks over the objects with a scored view, and the pooled means."""
    scored_ext = [o for o in objects if o["extraction"]["iou"] is not None]
    scored_nvs = [o for o in objects if o["nvs"]["iou"] is not None]
    pairs_ext = [v for o in objects for v in o["extraction"]["views"]]
    pairs_nvs = [v for o in objects for v in o["nvs"]["views"]]
    return {
        "extraction": {"mIoU": mean_or_none([o["extraction"]["iou"] for o in scored_ext]),
                       "PSNR": mean_or_none([o["extraction"]["psnr"] for o in scored_ext]),
                       "objects": len(scored_ext), "views": len(pairs_ext),
                       "pooled": _means(pairs_ext, ("iou", "psnr"))},
        "nvs": {"mIoU": mean_or_none([o["nvs"]["iou"] for o in scored_nvs]),
                "mAcc": mean_or_none([o["nvs"]["acc"] for o in scored_nvs]),
                "mAcc_definition": "precision TP/(TP+FP)" if p.accuracy == "precision" else "accuracy (TP+TN)/pixels",
                "objects": len(scored_nvs), "views": len(pairs_nvs),
                "pooled": _means(pairs_nvs, ("iou", "acc"))},
    }


def _single_point(lifted, lift_info: dict, gt: GroundTruth, model, by_name: dict, image, p: EvaluateParams,
                  lift_dir: Path, one=None) -> dict:
    """Both tasks again with the lifted scene queried by one query point (``max_queries: 1``; ``one``:
    that sibling, if made already): the same objects, references, views and means as the multi-point
    protocol."""
    if not hasattr(lifted, "with_query"):
        return {"skipped": f"lifting method {lift_info.get('method', '?')!r} has no query points"}
    start = time.perf_counter()
    one = one if one is not None else lifted.with_query(max_queries=1)
    objects = []
    for oid in gt.object_ids:
        query = gt.query(oid)
        if query is None:
            continue
        keep, _, _, extraction, nvs, _ = _score_object(one, query, oid, gt, model, by_name, image, p, lift_dir)
        objects.append({"id": oid, "query_points": int(one.query_points(query).features.shape[0]),
                        "gaussians": int(keep.sum()),
                        "extraction": {**_means(extraction, ("iou", "psnr")), "views": extraction},
                        "nvs": {**_means(nvs, ("iou", "acc")), "views": nvs}})
    out = {"max_queries": 1, **_summary(objects, p), "objects": objects, "seconds": time.perf_counter() - start}
    log.info("evaluate, one query point: object mIoU %s, NVS mIoU %s, %.1f s", _fmt(out["extraction"]["mIoU"]),
             _fmt(out["nvs"]["mIoU"]), out["seconds"])
    return out


def _panoptic(lifted, lift_info: dict, gt: GroundTruth, cameras: list, by_name: dict, p: EvaluateParams) -> dict:
    """PQ^scene of the lifted features over the protocol's views (test, or all)."""
    if not (hasattr(lifted, "features") and hasattr(lifted, "visibility")):
        return {"skipped": f"lifting method {lift_info.get('method', '?')!r} has no lifted features"}
    frames = [c.name for c in cameras if p.views == "all" or c.split == "test"]
    return evaluate_panoptic(lifted, gt, frames, by_name, p.panoptic_samples, p.panoptic_min_share,
                             p.panoptic_seed, p.min_pixels)


class _ClickScene:
    """The click score's :class:`~trace3d.extract.ClickScene`, made on first use, and its
    :class:`~trace3d.segment.SeenGraph` for the segment score when both are on and their ``neighbours``
    agree (the kNN graph, its edges' feature distances, the data's threshold and the unseen Gaussians'
    nearest seen ones are then made once)."""

    def __init__(self, lifted, p: EvaluateParams):
        self.lifted, self.p, self.scene = lifted, p, None

    def params(self):
        from ..extract import ExtractParams

        return ExtractParams(selection=self.p.click_selection)

    def get(self):
        from .click import click_scene

        if self.scene is None:
            self.scene = click_scene(self.lifted, self.params())
        return self.scene

    def graph_for(self, neighbours: int):
        return self.get().shared if self.p.click and self.params().neighbours == neighbours else None


def _segment(lifted, lift_info: dict, gt: GroundTruth, cameras: list, by_name: dict, p: EvaluateParams,
             clicks: _ClickScene | None = None) -> dict:
    """PQ^scene of the segment step's objects (default parameters) over the protocol's views."""
    from ..segment import SegmentParams
    from .panoptic import evaluate_segments

    if not (hasattr(lifted, "features") and hasattr(lifted, "visibility")):
        return {"skipped": f"lifting method {lift_info.get('method', '?')!r} has no lifted features"}
    frames = [c.name for c in cameras if p.views == "all" or c.split == "test"]
    sp = SegmentParams(near=p.near)
    graph = clicks.graph_for(sp.neighbours) if clicks is not None and hasattr(lifted, "feature_map") else None
    return evaluate_segments(lifted, gt, frames, by_name, sp, p.min_pixels, graph)


def _click(lifted, lift_info: dict, gt: GroundTruth, by_name: dict, p: EvaluateParams,
           clicks: _ClickScene | None = None) -> dict:
    """Click-extract IoU (one click per object, :mod:`.click`)."""
    from ..extract import ExtractParams
    from .click import evaluate_clicks

    if not (hasattr(lifted, "features") and hasattr(lifted, "feature_map")):
        return {"skipped": f"lifting method {lift_info.get('method', '?')!r} has no lifted features"}
    return evaluate_clicks(lifted, gt, by_name, ExtractParams(selection=p.click_selection), p.min_pixels, p.near,
                           clicks.get() if clicks is not None else None)


def _fmt(value: float | None, digits: int = 3) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"
