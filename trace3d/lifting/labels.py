"""Label assignment: per-Gaussian instance labels in closed form (the ``"labels"`` lifting method).

With the geometry frozen, the label map rendered from one-hot per-Gaussian labels is linear in
them: pixel x of view v receives sum_i w_i^v(x) onehot(l_i). The agreement of those renders with
the training views' label maps,

    sum_v sum_x <onehot(L_v(x)), sum_i w_i^v(x) onehot(l_i)> = sum_i A[i, l_i],
    A[i, j] = sum_v W_i^v[j]    (the GIT weights of Gaussian i on label j, summed over views),

is maximised Gaussian by Gaussian: l_i = argmax_j A[i, j] (ties: the smallest label). This is the
FlashSplat-style baseline (closed-form assignment, no training): weights are *summed* over views
before the argmax, not argmax-per-view votes. Each Gaussian also gets a confidence, the share
A[i, l_i] / sum_j A[i, j] of its total weight; Gaussians under ``min_confidence`` (and Gaussians no
training view sees) are left unassigned (label -1) and belong to no object.

Label maps must carry ids that are consistent across views (the merge step's ``instances/``, or
ground-truth ids); 0 means "no instance": it takes part in the argmax (a Gaussian seen mostly on
unlabelled pixels belongs to nothing) but is never an object.

Query (one reference view and a mask): the reference mask is traced through the scene (two labels:
outside, inside). Label l joins the object when the majority of its Gaussians' weight in the
reference view comes from inside the mask (in_l > out_l, the closed-form optimum of the same
linear objective for the object/other indicator); if no label qualifies, the label with the most
weight inside the mask is the object. Masks at any camera: every Gaussian is rendered with the
feature 1 (object) or 0 (other); a pixel is the object when the object's Gaussians hold the
majority of its blending weight (object weight > the others' weight: the rendered label argmax of
object vs. the rest, so other surfaces in front occlude the object as they should).

Files: ``lift.json`` ({"method": "labels", "params": ..., summary}) and ``labels.npz``
(``label`` [N] int32, ``confidence`` [N] float32, ``total`` [N] float32).
"""

from __future__ import annotations

import logging
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from tqdm import tqdm

from ..errors import SceneFormatError, Trace3DError
from ..gaussians import GaussianModel
from ..scene import Camera, Scene
from . import ObjectQuery, register_method

log = logging.getLogger(__name__)

METHOD = "labels"


@dataclass
class LabelsParams:
    """Parameters of the label-assignment lifting.

    min_confidence: Gaussians whose winning label holds less than this share of their total
        weight are left unassigned (FlashSplat's filtering of uncertain Gaussians).
    near: near plane of the tracing and rendering.
    """

    min_confidence: float = 0.5
    near: float = 0.01

    # each field's range: refused on input and in the config schema (trace3d.params.check_ranges)
    RANGES = {"min_confidence": "[0, 1]"}

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_confidence <= 1.0:
            raise ValueError(f"min_confidence must lie in [0, 1], got {self.min_confidence}.")


@torch.no_grad()
def summed_label_weights(model: GaussianModel, cameras: Sequence[Camera], label_maps: Sequence[np.ndarray],
                         near: float = 0.01, progress: bool = False) -> torch.Tensor:
    """A[i, j] = sum over views of the GIT weight of Gaussian i on label j.

    Args:
        model: N Gaussians.
        cameras: L cameras.
        label_maps: L integer maps [H, W], ids >= 0 consistent across views.
    Returns:
        sparse COO [N, T] float64 (coalesced), T = 1 + the largest id of any map.
    """
    from ..render import trace

    if len(cameras) != len(label_maps):
        raise ValueError(f"summed_label_weights: {len(cameras)} cameras but {len(label_maps)} label maps.")
    n = len(model)
    num_labels = 1 + max((int(np.asarray(m).max(initial=0)) for m in label_maps), default=0)
    splats = model.splats()
    rows, cols, vals = [], [], []
    bar = tqdm(list(zip(cameras, label_maps)), desc="label weights", disable=not progress, leave=False,
               mininterval=0.5 if sys.stderr.isatty() else 30.0)
    for cam, labels in bar:
        w = trace(splats, cam, torch.from_numpy(np.asarray(labels).astype(np.int64)), num_labels, near=near)
        r, c = w.indices()
        rows.append(r)
        cols.append(c)
        vals.append(w.values().double())
    if rows:
        index = torch.stack([torch.cat(rows), torch.cat(cols)])
        values = torch.cat(vals)
    else:
        index, values = torch.zeros(2, 0, dtype=torch.int64), torch.zeros(0, dtype=torch.float64)
    return torch.sparse_coo_tensor(index, values, (n, num_labels), check_invariants=True).coalesce()


def _summed_label_weights_dense(model: GaussianModel, cameras: Sequence[Camera], label_maps: Sequence[np.ndarray],
                                near: float = 0.01) -> torch.Tensor:
    """Twin of :func:`summed_label_weights`: dense [N, T] sums of GIT defined as a backward pass
    (``trace_by_backward`` with the reference renderer), view by view."""
    from ..render import trace_by_backward

    num_labels = 1 + max((int(np.asarray(m).max(initial=0)) for m in label_maps), default=0)
    total = torch.zeros(len(model), num_labels, dtype=torch.float64)
    splats = model.splats()
    for cam, labels in zip(cameras, label_maps):
        total += trace_by_backward(splats, cam, torch.from_numpy(np.asarray(labels).astype(np.int64)), num_labels,
                                   near=near, backend="reference").double()
    return total


def assign_labels(weights: torch.Tensor, min_confidence: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closed-form labels from summed weights.

    Args:
        weights: [N, T] sparse or dense summed weights A.
        min_confidence: share under which a Gaussian stays unassigned.
    Returns:
        label [N] int32 (-1: unassigned), confidence [N] float32 (share of the argmax label; 0 when
        unseen), total [N] float32 (sum of the row).
    """
    from ..render import trace_argmax

    label, prob, total = trace_argmax(weights)
    label = label.numpy().astype(np.int32)
    prob = prob.numpy().astype(np.float32)
    label[prob < min_confidence] = -1
    return label, prob, total.numpy().astype(np.float32)


def _label_folder(labels_dir: Path) -> Path:
    """The folder holding ``<frame>.png``: a merge step's ``instances/`` or the folder itself."""
    labels_dir = Path(labels_dir)
    return labels_dir / "instances" if (labels_dir / "instances").is_dir() else labels_dir


def run_labels_lift(scene: Scene, poses_dir: Path | None, gaussians_dir: Path, labels_dir: Path, out_dir: Path,
                    params: dict) -> dict:
    """Lift by label assignment; writes ``lift.json`` and ``labels.npz`` into ``out_dir``.

    ``labels_dir`` is a folder of 16-bit maps ``<frame>.png`` with ids consistent across views (a
    merge step's folder, whose ``instances/`` is used, or any such folder).
    """
    from ..io import write_json
    from ..params import from_mapping, to_dict
    from ..tracing.git import load_fitted, load_label_maps

    p = from_mapping(LabelsParams, params, "labels lifting params")
    model, cameras = load_fitted(scene, poses_dir, gaussians_dir)
    train = [c for c in cameras if c.split == "train"]
    maps = load_label_maps(_label_folder(labels_dir), [c.name for c in train], "label map",
                           [(c.width, c.height) for c in train])
    start = time.perf_counter()
    weights = summed_label_weights(model, train, maps, near=p.near, progress=True)
    label, confidence, total = assign_labels(weights, p.min_confidence)
    seconds = time.perf_counter() - start
    out_dir = Path(out_dir)
    np.savez_compressed(out_dir / "labels.npz", label=label, confidence=confidence, total=total)
    seen = total > 0
    summary = {
        "method": METHOD, "params": to_dict(p), "gaussians": int(len(model)), "views": len(train),
        "labels": int(weights.shape[1]), "seconds": seconds,
        "assigned_fraction": float((label >= 0).mean()) if len(label) else 0.0,
        "background_fraction": float((label == 0).mean()) if len(label) else 0.0,
        "never_seen_fraction": float((~seen).mean()) if len(label) else 0.0,
        "mean_confidence": float(confidence[seen].mean()) if seen.any() else 0.0,
    }
    write_json(out_dir / "lift.json", summary)
    log.info("labels: %d Gaussians, %d labels, %.1f%% assigned, %.1f s", len(model), weights.shape[1],
             100 * summary["assigned_fraction"], seconds)
    return summary


class LabelledScene:
    """A :class:`~trace3d.lifting.LiftedScene` answering queries from per-Gaussian labels."""

    def __init__(self, model: GaussianModel, label: np.ndarray, confidence: np.ndarray, cameras: Sequence[Camera],
                 near: float = 0.01):
        if len(label) != len(model):
            raise Trace3DError(f"labels: {len(label)} labels for {len(model)} Gaussians.")
        self.model = model
        self.label = np.asarray(label, np.int64)
        self.confidence = np.asarray(confidence, np.float32)
        self.cameras = {c.name: c for c in cameras}
        self.near = near
        self._splats = model.splats()

    def object_labels(self, query: ObjectQuery) -> list[int]:
        """The labels that make up the queried object (see the module docstring)."""
        from ..render import trace

        if query.reference not in self.cameras:
            raise Trace3DError(f"labels: the reference view {query.reference!r} is not a camera of the scene.")
        cam = self.cameras[query.reference]
        mask = np.asarray(query.mask, bool)
        if mask.shape != (cam.height, cam.width):
            raise Trace3DError(f"labels: the query mask is {mask.shape}, view {cam.name!r} is "
                               f"{(cam.height, cam.width)}.")
        with torch.no_grad():
            w = trace(self._splats, cam, torch.from_numpy(mask.astype(np.int64)), 2, near=self.near).to_dense().double()
        w = w.numpy()
        assigned = self.label > 0
        if not assigned.any():
            return []
        num = int(self.label.max()) + 1
        inside = np.bincount(self.label[assigned], weights=w[assigned, 1], minlength=num)
        outside = np.bincount(self.label[assigned], weights=w[assigned, 0], minlength=num)
        chosen = np.nonzero((inside > outside) & (inside > 0))[0]
        if chosen.size == 0 and inside.max() > 0:
            chosen = np.array([int(np.argmax(inside))])
        return [int(c) for c in chosen]

    def object_gaussians(self, query: ObjectQuery) -> np.ndarray:
        """[N] bool: Gaussians whose label is one of the object's labels."""
        return np.isin(self.label, self.object_labels(query))

    def object_masks(self, query: ObjectQuery, cameras: Sequence[Camera]) -> list[np.ndarray]:
        """[H, W] bool per camera: the object's Gaussians hold the majority of the pixel's weight."""
        from ..render import render

        member = torch.from_numpy(self.object_gaussians(query).astype(np.float32))[:, None]
        masks = []
        with torch.no_grad():
            for cam in cameras:
                out = render(self._splats, cam, member, near=self.near)
                obj = out.features[..., 0]
                masks.append(((obj > out.alpha - obj) & (obj > 0)).numpy())
        return masks


def load_labels(lift_dir: Path, info: dict, model: GaussianModel, scene: Scene,
                train_cameras: Sequence[Camera]) -> LabelledScene:
    """Loader of ``"method": "labels"`` folders (registered with :func:`register_method`)."""
    path = Path(lift_dir) / "labels.npz"
    if not path.is_file():
        raise SceneFormatError(f"{path}: labels.npz is missing from the labels lifting folder.")
    try:
        with np.load(path) as data:
            label, confidence = data["label"], data["confidence"]
    except (KeyError, ValueError, OSError) as exc:
        raise SceneFormatError(f"{path}: not a labels file ({exc}).") from exc
    if len(label) != len(model):
        raise SceneFormatError(f"{path}: {len(label)} labels but the Gaussians have {len(model)}; "
                               f"the lifting is stale (rerun the lift step).")
    near = float(info.get("params", {}).get("near", 0.01))
    cameras = list(train_cameras)
    return LabelledScene(model, label, confidence, cameras, near=near)


register_method(METHOD, load_labels)
