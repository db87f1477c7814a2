"""The scene's objects without ground truth: ``trace3d segment`` on a contrastively lifted scene.

For a capture with no ground truth (a user's photos or ``transforms.json``, masks from the ``graph``
source), the objects are what the lift separates:

1. **Clustering**: the lifted per-Gaussian features are clustered exactly as the PQ^scene evaluation
   clusters them (:func:`~trace3d.evaluation.panoptic.cluster_features`: ``samples`` Gaussians drawn
   by their summed training-pixel blending weight, HDBSCAN with ``min_cluster_size =
   ceil(samples * min_share)``, every Gaussian to the nearest cluster mean).
2. **Size threshold**: every training view's pixels get the cluster with the largest rendered weight
   (:func:`~trace3d.evaluation.panoptic.instance_map`); a cluster is kept as an object when it has at
   least ``min_gaussians`` Gaussians and wins at least ``min_pixels`` training pixels over all views
   together (defaults 20 Gaussians and 0.1 % of one view's pixels times the number of views, i.e.
   about ``min_share`` of the training pixels: smaller clusters are feature noise or slivers at
   object borders). The kept objects are numbered 1, 2, ... by pixels, largest first (ties by the
   cluster's label), so the room's walls and floor usually come first.
3. **Files**: per object its Gaussians (``objects/<k>.ply``, the 3DGS/2DGS layout of
   :meth:`~trace3d.gaussians.GaussianModel.write_ply`) and the object alone from ``turntable_views``
   directions (``objects/<k>.png``, :func:`~trace3d.evaluation.pictures.turntable_strip`, as the
   evaluate step draws its objects).

Writes into ``out_dir``: ``objects/<k>.ply``, ``objects/<k>.png``, ``contact_sheet.png`` (every
object's turntable strip, one row per object with its number, in order) and ``segment.json`` (per
object: ``gaussians``, ``views`` seen = training views where it wins at least one pixel, ``pixels``
won over all training views, ``cluster``; the clustering's counts, the dropped clusters and the
settings).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from .errors import Trace3DError
from .io import write_json
from .params import from_mapping, to_dict

log = logging.getLogger(__name__)


@dataclasses.dataclass
class SegmentParams:
    """Parameters of ``trace3d segment`` (``--params``).

    Attributes:
        samples: Gaussians clustered (as the PQ^scene evaluation's ``panoptic_samples``).
        min_share: HDBSCAN's minimum cluster size as a share of ``samples`` (as ``panoptic_min_share``).
        seed: the sample draw's seed.
        min_gaussians: a cluster with fewer Gaussians is not an object.
        min_pixels: a cluster winning fewer training pixels (over all views together) is not an
            object; ``None``: ``min_share`` of all the training views' pixels (at least 1).
        turntable_views, turntable_size: each object's ``objects/<k>.png`` strip (views, pixels per side).
        near: the renders' near plane.
    """

    samples: int = 8000
    min_share: float = 0.001
    seed: int = 0
    min_gaussians: int = 20
    min_pixels: int | None = None
    turntable_views: int = 8
    turntable_size: int = 96
    near: float = 0.01

    def __post_init__(self) -> None:
        if self.samples < 2:
            raise ValueError(f"samples must be >= 2, got {self.samples}")
        if not 0.0 < self.min_share < 1.0:
            raise ValueError(f"min_share must be in (0, 1), got {self.min_share}")
        if self.min_gaussians < 1:
            raise ValueError(f"min_gaussians must be >= 1, got {self.min_gaussians}")
        if self.min_pixels is not None and self.min_pixels < 1:
            raise ValueError(f"min_pixels must be >= 1 (or null), got {self.min_pixels}")
        if self.turntable_views < 1 or self.turntable_size < 8:
            raise ValueError("turntable_views must be >= 1 and turntable_size >= 8")


def contact_sheet(strips: list[np.ndarray], labels: list[str]) -> np.ndarray:
    """[H, W, 3] uint8: the strips [h, w, 3] one under another (2-pixel white gaps), each after a
    square tile with its label; an empty list gives one tile saying so."""
    if not strips:
        tile = np.zeros((48, 160, 3), np.uint8)
        cv2.putText(tile, "no objects", (8, 30), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
        return tile
    width = max(s.shape[1] for s in strips)
    rows = []
    for strip, label in zip(strips, labels):
        h = strip.shape[0]
        tile = np.zeros((h, h, 3), np.uint8)
        scale = max(0.35, h / 96)
        cv2.putText(tile, label, (max(2, h // 8), h // 2 + int(8 * scale)), cv2.FONT_HERSHEY_SIMPLEX, scale,
                    (255, 255, 255), max(1, int(round(scale))), cv2.LINE_AA)
        pad = np.zeros((h, width - strip.shape[1], 3), np.uint8)
        rows.append(np.concatenate([tile, np.full((h, 2, 3), 255, np.uint8), strip, pad], axis=1))
        rows.append(np.full((2, rows[-1].shape[1], 3), 255, np.uint8))
    return np.concatenate(rows[:-1], axis=0)


def run_segment(scene, poses_dir: Path | None, gaussians_dir: Path, lift_dir: Path, out_dir: Path,
                params: dict) -> dict:
    """Cluster a contrastive lift's Gaussians into objects and write them into ``out_dir`` (module
    docstring); returns segment.json's content."""
    from .evaluation.panoptic import cluster_features, instance_map
    from .evaluation.pictures import turntable_strip, world_up
    from .lifting import load_lifted
    from .lifting.query import FeatureLifted
    from .scene import write_rgb
    from .tracing.git import load_fitted

    p = from_mapping(SegmentParams, params, "segment params")
    start = time.perf_counter()
    model, cameras = load_fitted(scene, poses_dir, gaussians_dir)
    train = [c for c in cameras if c.split == "train"]
    if not train:
        raise Trace3DError(f"{scene.root}: segment needs training views; cameras.json has none.")
    lifted = load_lifted(lift_dir, model, scene, train)
    if not isinstance(lifted, FeatureLifted):
        method = json.loads((Path(lift_dir) / "lift.json").read_text()).get("method")
        raise Trace3DError(f"{lift_dir}: segment clusters lifted features and needs a contrastive lift "
                           f"(features.npy); this lift's method is {method!r}.")
    clusters = cluster_features(lifted.features, lifted.visibility(), p.samples, p.min_share, p.seed)
    log.info("segment: %d clusters of %d Gaussians from %d samples (%d noise, min cluster size %d)", clusters.count,
             len(model), clusters.samples, clusters.noise, clusters.min_cluster_size)
    # every training pixel to the cluster with the largest rendered weight: pixels won and views seen
    k = clusters.count
    pixels = np.zeros(k + 1, np.int64)
    views = np.zeros(k + 1, np.int64)
    for cam in train:
        won = np.bincount(instance_map(model, cam, clusters.instance, k, p.near).ravel(), minlength=k + 1)
        pixels += won
        views += won > 0
    gaussians = np.bincount(clusters.instance, minlength=k + 1)
    total_pixels = sum(c.width * c.height for c in train)
    min_pixels = p.min_pixels if p.min_pixels is not None else max(1, int(np.ceil(p.min_share * total_pixels)))
    kept, dropped = [], []
    for label in range(1, k + 1):
        entry = {"cluster": label, "gaussians": int(gaussians[label]), "views": int(views[label]),
                 "pixels": int(pixels[label])}
        big = entry["gaussians"] >= p.min_gaussians and entry["pixels"] >= min_pixels
        (kept if big else dropped).append(entry)
    kept.sort(key=lambda e: (-e["pixels"], e["cluster"]))
    out_dir = Path(out_dir)
    objects_dir = out_dir / "objects"
    objects_dir.mkdir(parents=True, exist_ok=True)
    up = world_up(train)
    strips, names = [], []
    for number, entry in enumerate(kept, start=1):
        entry["id"] = number
        obj = model.subset(torch.from_numpy(clusters.instance == entry["cluster"]))
        obj.write_ply(objects_dir / f"{number}.ply")
        strip = turntable_strip(obj, up, p.turntable_views, p.turntable_size, p.near)
        write_rgb(objects_dir / f"{number}.png", strip)
        strips.append(strip)
        names.append(str(number))
    write_rgb(out_dir / "contact_sheet.png", contact_sheet(strips, names))
    info = {
        "objects": [{"id": e["id"], "cluster": e["cluster"], "gaussians": e["gaussians"], "views": e["views"],
                     "pixels": e["pixels"]} for e in kept],
        "dropped": dropped, "clusters": k, "samples": clusters.samples, "noise_samples": clusters.noise,
        "min_cluster_size": clusters.min_cluster_size, "min_pixels": min_pixels,
        "gaussians_total": int(len(model)), "unclustered_gaussians": int(gaussians[0]),
        "training_views": len(train), "training_pixels": int(total_pixels), "background_pixels": int(pixels[0]),
        "params": to_dict(p), "lift": str(Path(lift_dir)), "seconds": time.perf_counter() - start,
    }
    write_json(out_dir / "segment.json", info)
    log.info("segment: %d objects kept (>= %d Gaussians, >= %d training pixels), %d clusters dropped, %.1f s -> %s",
             len(kept), p.min_gaussians, min_pixels, len(dropped), info["seconds"], objects_dir)
    return info

