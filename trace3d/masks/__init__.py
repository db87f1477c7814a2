"""2D masks per view and the primitive patches made from them.

Mask sources (config key ``masks.source``), each yielding per frame a bool stack [M, H, W] and
scores [M]:

* ``simulated``: SAM-like masks from the ground truth, with controlled cross-view inconsistency;
  the default for the synthetic benchmark.  Two models, chosen by ``model`` among its
  parameters: ``one_level`` (:mod:`.simulate`, the default: one granularity per object and view,
  overlaps only sometimes) and ``nested`` (:mod:`.nested`: SAM's automatic generator, nested
  subpart / part / whole / group masks, calibrated in docs/masks_calibration.md).
* ``files`` (:mod:`.files`): masks computed elsewhere, from the scene's ``masks/`` folder.
* ``sam`` (:mod:`.sam`): Segment Anything's automatic mask generator (optional package).
* ``graph`` (:mod:`.graph`): nested multi-scale graph segmentation of each image; reads no ground
  truth, so it runs on a user's photos as on the synthetic rooms.
* ``geometry`` (:mod:`.geometry`): nested masks from the fitted 2DGS scene's rendered depth and
  normals (depth edges, concave creases) with colour; reads no ground truth, needs the fit
  (``gaussians_dir``, ``poses_dir``).

:func:`run_masks` writes ``<frame>.npz`` ("masks" bool [M, H, W], "scores" float32 [M]) for every
frame (train and test) and ``masks.json`` (source, resolved parameters, masks per view, and when the
scene has ground-truth instances, how consistently objects appear across views).
:mod:`.patches` turns them into disjoint patches (paper Sec. 3.2).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Iterator

import numpy as np

from ..errors import ConfigError, SceneFormatError, Trace3DError
from ..io import atomic_file, write_json
from ..params import from_mapping, to_dict
from ..scene import Scene
from .files import FilesParams, iter_file_masks, read_mask_npz
from .geometry import GeometryParams, iter_geometry_masks
from .graph import GraphParams, GraphPromptSegmenter, iter_graph_masks
from .patches import PatchHierarchy, PatchParams, masks_to_patches, read_patches, run_patches
from .nested import NestedParams, iter_nested_masks, nested_view_masks
from .sam import SamParams, iter_sam_masks
from .simulate import (
    SimulatedPromptSegmenter,
    SimulateParams,
    cross_view_disagreement,
    frame_rng,
    iter_simulated_masks,
    object_status,
    simulate_view_masks,
)

log = logging.getLogger(__name__)

SOURCES = ("simulated", "files", "sam", "graph", "geometry")
# the sources that render the fitted scene (the masks step then needs --gaussians and --poses)
FITTED_SOURCES = ("geometry",)
SIMULATED_MODELS = ("one_level", "nested")

__all__ = [
    "SOURCES",
    "FITTED_SOURCES",
    "FilesParams",
    "GeometryParams",
    "NestedParams",
    "SIMULATED_MODELS",
    "GraphParams",
    "GraphPromptSegmenter",
    "PatchHierarchy",
    "PatchParams",
    "SamParams",
    "SimulateParams",
    "SimulatedPromptSegmenter",
    "cross_view_disagreement",
    "frame_rng",
    "iter_masks",
    "masks_to_patches",
    "nested_view_masks",
    "object_status",
    "parse_params",
    "read_mask_npz",
    "read_patches",
    "run_masks",
    "run_patches",
    "simulate_view_masks",
    "write_mask_npz",
]


def parse_params(source: str, params: dict | None):
    """The typed parameter set of ``source`` from a raw config mapping (unknown keys refused)."""
    if source == "simulated":
        model = (params or {}).get("model", "one_level") if isinstance(params, dict) else "one_level"
        if model == "nested":
            return from_mapping(NestedParams, params, "masks params (simulated, model nested)")
        if model != "one_level":
            raise ConfigError(
                f"masks params (simulated).model: {model!r} is not one of {list(SIMULATED_MODELS)}."
            )
        return from_mapping(SimulateParams, params, "masks params (simulated)")
    if source == "files":
        return from_mapping(FilesParams, params, "masks params (files)")
    if source == "sam":
        return from_mapping(SamParams, params, "masks params (sam)")
    if source == "graph":
        return from_mapping(GraphParams, params, "masks params (graph)")
    if source == "geometry":
        return from_mapping(GeometryParams, params, "masks params (geometry)")
    raise Trace3DError(f"unknown mask source {source!r}; expected one of {list(SOURCES)}.")


def iter_masks(scene: Scene, source: str, params, gaussians_dir: Path | None = None,
               poses_dir: Path | None = None) -> Iterator[tuple[str, np.ndarray, np.ndarray]]:
    """Yield (frame name, masks [M, H, W] bool, scores [M] float32) for every frame of ``scene``
    (``gaussians_dir``, ``poses_dir``: the 2DGS fit and its poses, for the sources that render it)."""
    if source == "simulated":
        if isinstance(params, NestedParams):
            return iter_nested_masks(scene, params)
        return iter_simulated_masks(scene, params)
    if source == "files":
        return iter_file_masks(scene, params)
    if source == "sam":
        return iter_sam_masks(scene, params)
    if source == "graph":
        return iter_graph_masks(scene, params)
    if source == "geometry":
        return iter_geometry_masks(scene, params, gaussians_dir, poses_dir)
    raise Trace3DError(f"unknown mask source {source!r}; expected one of {list(SOURCES)}.")


def write_mask_npz(path: str | Path, masks: np.ndarray, scores: np.ndarray) -> None:
    """Write one view's masks [M, H, W] bool and scores [M] float32 as a compressed npz (atomically)."""
    with atomic_file(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, masks=np.asarray(masks, dtype=bool), scores=np.asarray(scores, np.float32))


def run_masks(scene: Scene, out_dir: Path, source: str, params: dict, gaussians_dir: Path | None = None,
              poses_dir: Path | None = None) -> None:
    """Compute the 2D masks of every frame of ``scene`` with ``source`` into ``out_dir`` (``gaussians_dir``,
    ``poses_dir``: the 2DGS fit and its poses, which the ``geometry`` source renders)."""
    typed = parse_params(source, params)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    counts: dict[str, int] = {}
    statuses = []
    for name, masks, scores in iter_masks(scene, source, typed, gaussians_dir, poses_dir):
        cam = scene.camera(name)
        if masks.shape[1:] != (cam.height, cam.width) or masks.dtype != bool or scores.shape != (len(masks),):
            raise SceneFormatError(
                f"{scene.image_path(name)}: the {source} source produced masks of shape {masks.shape} "
                f"and scores of shape {scores.shape} for a {cam.width}x{cam.height} image."
            )
        write_mask_npz(out_dir / f"{name}.npz", masks, scores)
        counts[name] = int(len(masks))
        if scene.has_instances:
            statuses.append(object_status(masks, scene.instances(name), scene.objects))
    summary = {
        "source": source,
        "params": to_dict(typed),
        "total_masks": int(sum(counts.values())),
        "mean_masks_per_view": float(np.mean(list(counts.values()))) if counts else 0.0,
        "masks_per_view": counts,
    }
    if counts and not any(counts.values()):
        raise SceneFormatError(
            f"{scene.root}: the {source} mask source gave no mask in any of the {len(counts)} views; later steps "
            f"need masks to trace and merge (check the masks folder, or the source's parameters)."
        )
    if statuses:
        summary["ground_truth_check"] = cross_view_disagreement(statuses)
    write_json(out_dir / "masks.json", summary)
    log.info("masks (%s): %d views, %.1f masks per view", source, len(counts), summary["mean_masks_per_view"])
