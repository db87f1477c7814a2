"""Self-prompting (paper Sec. 3.5, the online setting of SA3D / FlashSplat, with GIT).

From point prompts on the reference view (``points`` pixels sampled inside the query mask: the one
deepest inside it and random others), a promptable mask source (:mod:`trace3d.masks.prompts`,
``prompt_source``: ``sam``; ``graph``, the images' graph segmentation, which reads no ground truth;
or ``simulated``, an *oracle* that answers from the ground-truth instance maps) gives the reference
view's mask (the granularity closest to the query mask, as a user picks one of
SAM's answers). Then, view by view along the training views ordered by pose
proximity to the reference:

1. the masks so far are traced with GIT: per Gaussian, its blending weight summed over all visited
   views on the object's pixels and on the rest; the object's Gaussians are those whose object share
   exceeds ``gaussian_share`` (0.5: the majority vote of the weight matrix W);
2. those Gaussians are rendered into the next view as an indicator (every Gaussian of the scene
   blends 1 if it is the object's, 0 otherwise, so occluders count): pixels above ``mask_threshold``
   are where the object is seen, and ``points`` prompts are sampled there as on the reference;
3. the mask source answers those prompts with the view's mask (the granularity closest to the
   rendered region), which is traced in turn.

A view where the object's Gaussians cover fewer than ``min_prompt_pixels`` pixels is skipped.
At any camera the object's mask is the same indicator render, thresholded at ``mask_threshold``.
"""

from __future__ import annotations

import logging
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Sequence

import numpy as np
import torch
from tqdm import tqdm

from ..errors import Trace3DError
from ..gaussians import GaussianModel
from ..scene import Camera, Scene
from . import ObjectQuery

log = logging.getLogger(__name__)


@dataclass
class SelfPromptParams:
    """Parameters of self-prompting (the lift step records them; the work happens per query)."""

    method: Literal["self_prompt"] = "self_prompt"
    preset: Literal["paper", "official"] = "paper"  # recorded; self-prompting has one form
    prompt_source: Literal["simulated", "sam", "graph"] = "simulated"  # simulated: an oracle (reads ground truth)
    simulate: dict = field(default_factory=dict)  # SimulateParams overrides (simulated source)
    graph: dict = field(default_factory=dict)  # GraphPromptParams overrides (graph source)
    sam_checkpoint: str | None = None
    sam_model_type: str = "vit_h"
    sam_device: str = "cpu"
    points: int = 3
    max_views: int | None = None  # visit at most this many training views (None: all)
    gaussian_share: float = 0.5
    mask_threshold: float = 0.5
    min_prompt_pixels: int = 4
    seed: int = 0
    near: float = 0.01

    # each field's range: refused on input and in the config schema (trace3d.params.check_ranges)
    RANGES = {"points": ">= 1", "min_prompt_pixels": ">= 1", "gaussian_share": "[0, 1)", "mask_threshold": "(0, 1)",
              "seed": ">= 0"}

    def __post_init__(self) -> None:
        if self.points < 1 or self.min_prompt_pixels < 1:
            raise ValueError(f"points and min_prompt_pixels must be >= 1, got {self.points}, {self.min_prompt_pixels}")
        if not (0.0 <= self.gaussian_share < 1.0 and 0.0 < self.mask_threshold < 1.0):
            raise ValueError("gaussian_share must be in [0, 1) and mask_threshold in (0, 1)")
        if self.prompt_source == "graph":  # refuse a misspelled graph key before anything runs
            from ..masks.graph import GraphParams, GraphPromptParams
            from ..params import from_mapping

            graph = from_mapping(GraphPromptParams, self.graph, "lift params graph")
            from_mapping(GraphParams, graph.graph, "lift params graph.graph")


def order_by_proximity(reference: Camera, cameras: Sequence[Camera]) -> list[Camera]:
    """``cameras`` sorted by pose distance to ``reference``: centre distance over the median centre
    distance plus the angle (radians) between viewing directions; the reference first."""
    def direction(c: Camera) -> np.ndarray:
        return c.world_to_camera[2, :3]  # camera z axis in world coordinates

    centres = np.array([c.center for c in cameras])
    dist = np.linalg.norm(centres - reference.center, axis=1)
    scale = np.median(dist[dist > 0]) if (dist > 0).any() else 1.0
    angle = np.array([np.arccos(np.clip(direction(c) @ direction(reference), -1.0, 1.0)) for c in cameras])
    score = dist / scale + angle
    score = np.where([c.name == reference.name for c in cameras], -1.0, score)
    return [cameras[i] for i in np.argsort(score, kind="stable")]


def sample_prompts(region: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """[K, 2] (x, y) pixel centres in ``region``: its deepest pixel, then random pixels of its inner part."""
    import cv2

    from .query import deepest_pixel

    x, y = deepest_pixel(region)
    points = [(x + 0.5, y + 0.5)]
    inner = cv2.erode(region.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    pool = np.argwhere(inner if inner.sum() >= count else region)
    if count > 1 and pool.size:
        pick = rng.choice(pool.shape[0], size=min(count - 1, pool.shape[0]), replace=False)
        points += [(float(c) + 0.5, float(r) + 0.5) for r, c in pool[np.sort(pick)]]
    return np.asarray(points, np.float64)


def indicator_render(model: GaussianModel, camera: Camera, members: np.ndarray, near: float = 0.01) -> np.ndarray:
    """[H, W]: sum_k w_k [k is a member] rendered with the whole scene (occluders included)."""
    from ..render import render

    with torch.no_grad():
        f = torch.from_numpy(np.asarray(members, np.float32))[:, None]
        return render(model.splats(), camera, f, near=near).features[..., 0].numpy()


# what a SelfPromptLifted keeps of the views' projections and tile lists (1 GiB: every view of the
# default 160x120 rooms, a few hundred MB; past it a view is projected and binned on each use)
VIEW_CACHE_BYTES = 1 << 30


class FrozenViews:
    """Each camera's :class:`~trace3d.render.core.FrozenView` of one frozen scene, kept while their
    bytes stay under ``max_bytes``: every query self-prompts across the same training views, so the
    projection and the binning are done once per view, not twice per view and query. The renders and
    traces are the bits of :func:`indicator_render` and :func:`~trace3d.render.trace` (tested)."""

    def __init__(self, model: GaussianModel, near: float, max_bytes: int = VIEW_CACHE_BYTES):
        self.splats, self.near, self.max_bytes = model.splats(), float(near), int(max_bytes)
        self.views: dict[str, object] = {}
        self.bytes = 0

    def view(self, camera: Camera):
        from ..render.core import FrozenView

        v = self.views.get(camera.name)
        if v is None:
            v = FrozenView(self.splats, camera, self.near)
            if self.bytes + v.nbytes <= self.max_bytes:
                self.views[camera.name] = v
                self.bytes += v.nbytes
        return v

    @staticmethod
    def indicator(view, members: np.ndarray) -> np.ndarray:
        f = torch.from_numpy(np.asarray(members, np.float32))[:, None]
        return view.render_features(f)[..., 0].numpy()


@dataclass
class SelfPromptResult:
    gaussians: np.ndarray  # [N] bool
    visited: list[str]  # frames whose mask was traced, in order
    skipped: list[str]


def self_prompt(model: GaussianModel, cameras: Sequence[Camera], reference: Camera, mask: np.ndarray, segmenter,
                params: SelfPromptParams, progress: bool = False, views: FrozenViews | None = None) -> SelfPromptResult:
    """Run self-prompting from ``mask`` ([H, W] bool) on ``reference`` across ``cameras`` (the training views).

    ``views``: the scene's projected views, shared by the queries of one scene (default: a fresh set)."""
    mask = np.asarray(mask, bool)
    if not mask.any():
        raise Trace3DError(f"self-prompting: the reference mask on {reference.name!r} is empty.")
    views = FrozenViews(model, params.near) if views is None else views
    fg = torch.zeros(len(model), dtype=torch.float64)
    total = torch.zeros(len(model), dtype=torch.float64)

    def add(view, view_mask: np.ndarray) -> None:
        w = view.trace(torch.from_numpy(view_mask.astype(np.int64)), 2)
        rows, cols = w.indices()
        vals = w.values().double()
        total.index_add_(0, rows, vals)
        fg.index_add_(0, rows[cols == 1], vals[cols == 1])

    def members() -> np.ndarray:
        return ((total > 0) & (fg / total.clamp_min(1e-12) > params.gaussian_share)).numpy()

    rng = np.random.default_rng(params.seed)
    ordered = order_by_proximity(reference, list(cameras))
    if params.max_views is not None:
        ordered = ordered[: params.max_views]
    first = segmenter.segment(reference.name, sample_prompts(mask, params.points, rng), rng, like=mask)
    add(views.view(reference), first)
    visited, skipped = [reference.name], []
    bar = tqdm(ordered[1:], desc="self-prompting", disable=not progress, leave=False,
               mininterval=0.5 if sys.stderr.isatty() else 30.0)
    for cam in bar:
        current = members()
        if not current.any():
            break
        view = views.view(cam)
        region = views.indicator(view, current) > params.mask_threshold
        if region.sum() < params.min_prompt_pixels:
            skipped.append(cam.name)
            continue
        view_mask = segmenter.segment(cam.name, sample_prompts(region, params.points, rng), rng, like=region)
        add(view, view_mask)
        visited.append(cam.name)
    return SelfPromptResult(members(), visited, skipped)


class SelfPromptLifted:
    """A :class:`~trace3d.lifting.LiftedScene` that self-prompts per query (method ``"self_prompt"``)."""

    def __init__(self, model: GaussianModel, train_cameras: Sequence[Camera], segmenter, params: SelfPromptParams):
        self.model = model
        self.train_cameras = list(train_cameras)
        self.segmenter = segmenter
        self.params = params
        self._results: dict[str, SelfPromptResult] = {}
        self.views = FrozenViews(model, params.near)

    def result(self, query: ObjectQuery) -> SelfPromptResult:
        from .query import query_key

        key = query_key(query)
        if key not in self._results:
            ref = next((c for c in self.train_cameras if c.name == query.reference), None)
            if ref is None:
                raise Trace3DError(f"query: reference view {query.reference!r} is not a training view.")
            self._results[key] = self_prompt(self.model, self.train_cameras, ref, query.mask, self.segmenter, self.params,
                                             views=self.views)
        return self._results[key]

    def object_gaussians(self, query: ObjectQuery) -> np.ndarray:
        return self.result(query).gaussians

    def object_masks(self, query: ObjectQuery, cameras: Sequence[Camera]) -> list[np.ndarray]:
        members = self.object_gaussians(query)
        return [self.views.indicator(self.views.view(c), members) > self.params.mask_threshold for c in cameras]


def make_prompt_segmenter(scene: Scene, params: SelfPromptParams):
    from ..masks.prompts import make_segmenter

    return make_segmenter(params.prompt_source, scene, params.simulate, params.sam_checkpoint, params.sam_model_type,
                          params.sam_device, params.graph)


def load_self_prompt(lift_dir: Path, info: dict, model: GaussianModel, scene: Scene,
                     train_cameras: Sequence[Camera]) -> SelfPromptLifted:
    """Loader of method ``"self_prompt"``: the parameters in lift.json name the mask source."""
    from ..params import from_mapping

    params = from_mapping(SelfPromptParams, info.get("params", {}), f"{Path(lift_dir) / 'lift.json'} params")
    return SelfPromptLifted(model, train_cameras, make_prompt_segmenter(scene, params), params)
