"""SAM-like 2D masks simulated from ground-truth instance maps.

The point of this source is to reproduce, under control, the two faults of SAM's automatic masks
that the paper is about (Sec. 1, Fig. 1): *inconsistent granularity across views* and *ragged,
misaligned boundaries*.  Per view, independently:

* every visible object is given at one granularity: its **parts** (objects with >= 2 visible parts),
  the **whole** object, or a **group**: its ground-truth group (``objects.json`` parent at level
  ``group``, e.g. a table with the items on it) or, for a stand-alone object (Replica: every id),
  the object merged with one randomly chosen touching neighbour (objects adjacent in the view);
  large flat "stuff" (walls, floors ...) only merges with other stuff;
* sometimes the masks of the other granularity are emitted too (whole + parts, group + members),
  overlapping as SAM's automatic generator does, so that patches become overlap regions;
* boundaries are jittered: one smooth random warp of the label map per view plus a random
  dilation / erosion of each mask by up to ``jitter_pixels`` (an erosion that would remove more
  than half of a mask is skipped);
* small or thin objects are sometimes missed (left uncovered);
* large flat regions are sometimes cut in two along a random straight line.

One knob, ``inconsistency`` in [0, 1], multiplies every one of these probabilities and amplitudes:
at 0 every view gives exactly the ground-truth object-level masks (no jitter, no misses, score 1).
Everything is drawn from ``numpy.random.default_rng([seed, frame_index])``.

``SimulatedPromptSegmenter`` is the point-prompt counterpart (what SAM does with one click): it
returns the mask, at a randomly chosen granularity, that contains the clicked point.
"""

from __future__ import annotations

import dataclasses
import logging
from collections import Counter
from typing import Iterator, Mapping, Literal

import cv2
import numpy as np
from tqdm import tqdm

from ..errors import Trace3DError
from ..params import check_ranges, from_mapping
from ..scene import ObjectTable, Scene

log = logging.getLogger(__name__)

DEFAULT_FLAT_CATEGORIES = ("wall", "floor", "ceiling", "rug", "carpet")


@dataclasses.dataclass
class SimulateParams:
    """Parameters of the simulated mask source.  Rates are per object per view at inconsistency 1.

    Attributes:
        model: always ``"one_level"`` (this model; ``"nested"`` selects :mod:`.nested` instead).
        seed: random seed (combined with the frame index).
        inconsistency: in [0, 1]; scales every rate and amplitude below (0: exact object masks).
        part_rate: probability that an object with >= 2 visible parts is given as its parts.
        group_rate: probability that an object is merged with its group / a touching neighbour.
        multi_rate: probability that the other granularity is emitted as well (overlapping masks).
        miss_rate: probability that a small or thin object gets no mask.
        split_rate: probability that a large flat region is cut in two along a random line.
        jitter_pixels: largest per-mask dilation / erosion radius, in pixels.
        warp_pixels: standard deviation of the per-view smooth boundary warp, in pixels.
        warp_cells: control-grid cells of the warp across the image (more: wigglier).
        small_fraction: objects covering less than this fraction of the image count as small.
        thin_pixels: objects whose largest inscribed radius is at most this count as thin.
        flat_categories: categories treated as flat stuff (lower-case match of SceneObject.category).
        flat_fraction: uncategorised objects covering at least this fraction count as flat stuff.
        touch_pixels: two objects touch when they share at least this many boundary pixel pairs.
        min_mask_pixels: masks with fewer pixels are dropped.
    """

    model: Literal["one_level", "nested"] = "one_level"
    seed: int = 0
    inconsistency: float = 0.5
    part_rate: float = 0.6
    group_rate: float = 0.4
    multi_rate: float = 0.3
    miss_rate: float = 0.5
    split_rate: float = 0.35
    jitter_pixels: int = 1
    warp_pixels: float = 1.0
    warp_cells: int = 6
    small_fraction: float = 0.002
    thin_pixels: float = 1.5
    flat_categories: list[str] = dataclasses.field(default_factory=lambda: list(DEFAULT_FLAT_CATEGORIES))
    flat_fraction: float = 0.12
    touch_pixels: int = 4
    min_mask_pixels: int = 16

    # each field's range: refused on input and in the config schema (trace3d.params.check_ranges)
    RANGES = {"inconsistency": "[0, 1]", "part_rate": "[0, 1]", "group_rate": "[0, 1]", "multi_rate": "[0, 1]",
              "miss_rate": "[0, 1]", "split_rate": "[0, 1]", "small_fraction": "[0, 1]", "flat_fraction": "[0, 1]",
              "jitter_pixels": ">= 0", "warp_pixels": ">= 0", "thin_pixels": ">= 0", "touch_pixels": ">= 0",
              "min_mask_pixels": ">= 0", "seed": ">= 0", "warp_cells": ">= 1"}

    def __post_init__(self) -> None:
        if self.model != "one_level":
            raise ValueError(f"model must be 'one_level' for these parameters, got {self.model!r}")
        check_ranges(self)
        self.flat_categories = [c.lower() for c in self.flat_categories]

    def rate(self, name: str) -> float:
        """``<name>_rate`` scaled by ``inconsistency``."""
        return self.inconsistency * getattr(self, f"{name}_rate")


# ----------------------------------------------------------------------------------------------
# Hierarchy lookups and per-view analysis
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass
class _LevelTables:
    """Leaf id -> object id / group id lookups [65536] and the categories of the objects."""

    to_object: np.ndarray
    to_group: np.ndarray
    category: dict[int, str]

    @classmethod
    def build(cls, objects: ObjectTable | None) -> "_LevelTables":
        size = 65536
        to_object = np.arange(size, dtype=np.int64)
        to_group = np.arange(size, dtype=np.int64)
        category: dict[int, str] = {}
        if objects is not None and len(objects):
            obj_lut, grp_lut = objects.lookup("object"), objects.lookup("group")
            for o in objects:
                to_object[o.id] = obj_lut[o.id]
                to_group[o.id] = grp_lut[o.id]
                category[o.id] = (o.category or "").lower()
        return cls(to_object, to_group, category)


@dataclasses.dataclass
class _ViewLayout:
    """What one view shows, derived from its leaf-id map.

    Attributes:
        leaf: [H, W] int64 leaf ids (0 = unlabelled).
        obj: [H, W] int64 object-level ids.
        object_ids: [K] visible object ids, ascending.
        area: object id -> pixel count.
        parts: object id -> its visible leaf ids, for objects with >= 2 visible parts.
        group: object id -> its ground-truth group id (only objects that have one).
        neighbours: object id -> touching object ids.
        flat: objects that are flat stuff.
        small_or_thin: objects that may be missed.
    """

    leaf: np.ndarray
    obj: np.ndarray
    object_ids: np.ndarray
    area: dict[int, int]
    parts: dict[int, list[int]]
    group: dict[int, int]
    neighbours: dict[int, set[int]]
    flat: set[int]
    small_or_thin: set[int]

    def object_mask(self, object_id: int) -> np.ndarray:
        return self.obj == object_id

    def union_mask(self, object_ids) -> np.ndarray:
        return np.isin(self.obj, np.asarray(list(object_ids), dtype=np.int64))

    def group_members(self, object_id: int) -> list[int]:
        """Visible objects of ``object_id``'s ground-truth group (itself included), or []."""
        g = self.group.get(object_id)
        if g is None:
            return []
        return [o for o, og in self.group.items() if og == g]

    def merge_partners(self, object_id: int) -> list[int]:
        """Touching objects that may be merged with ``object_id`` (stuff only merges with stuff)."""
        is_flat = object_id in self.flat
        return sorted(n for n in self.neighbours.get(object_id, ()) if (n in self.flat) == is_flat)


def _touching_pairs(labels: np.ndarray, min_shared: int) -> list[tuple[int, int]]:
    """Pairs (a < b) of nonzero labels [H, W] sharing at least ``min_shared`` 4-neighbour pixel pairs."""
    keys = []
    for a, b in ((labels[:, :-1], labels[:, 1:]), (labels[:-1, :], labels[1:, :])):
        keep = (a != b) & (a > 0) & (b > 0)
        lo, hi = np.minimum(a[keep], b[keep]), np.maximum(a[keep], b[keep])
        keys.append(lo * 65536 + hi)
    keys = np.concatenate(keys)
    if not len(keys):
        return []
    unique, counts = np.unique(keys, return_counts=True)
    unique = unique[counts >= max(min_shared, 1)]
    return [(int(k // 65536), int(k % 65536)) for k in unique]


def _analyse_view(leaf: np.ndarray, tables: _LevelTables, params: SimulateParams) -> _ViewLayout:
    leaf = leaf.astype(np.int64)
    H, W = leaf.shape
    obj = tables.to_object[leaf]
    obj[leaf == 0] = 0
    counts = np.bincount(obj.ravel(), minlength=1)
    object_ids = np.nonzero(counts)[0]
    object_ids = object_ids[object_ids > 0]
    area = {int(o): int(counts[o]) for o in object_ids}

    pairs = np.unique(obj[leaf > 0] * 65536 + leaf[leaf > 0])
    pieces: dict[int, list[int]] = {}
    for key in pairs:
        pieces.setdefault(int(key // 65536), []).append(int(key % 65536))
    parts = {o: leaves for o, leaves in pieces.items() if len(leaves) >= 2}

    group = {}
    for o in area:
        g = int(tables.to_group[o])
        if g != o:
            group[o] = g

    neighbours: dict[int, set[int]] = {o: set() for o in area}
    for a, b in _touching_pairs(obj, params.touch_pixels):
        neighbours[a].add(b)
        neighbours[b].add(a)

    flat = set()
    for o in area:
        cat = tables.category.get(o, "")
        if cat in params.flat_categories or (not cat and area[o] >= params.flat_fraction * H * W):
            flat.add(o)

    # largest inscribed radius per object: distance to the nearest pixel of another label
    edge = np.zeros((H, W), dtype=bool)
    edge[:, :-1] |= obj[:, :-1] != obj[:, 1:]
    edge[:, 1:] |= obj[:, :-1] != obj[:, 1:]
    edge[:-1, :] |= obj[:-1, :] != obj[1:, :]
    edge[1:, :] |= obj[:-1, :] != obj[1:, :]
    if edge.any():
        dist = cv2.distanceTransform((~edge).astype(np.uint8), cv2.DIST_L2, 3)
    else:
        dist = np.full((H, W), float(max(H, W)), dtype=np.float32)
    radius = np.zeros(counts.shape[0], dtype=np.float32)
    np.maximum.at(radius, obj.ravel(), dist.ravel())
    small_or_thin = {
        o for o in area if area[o] < params.small_fraction * H * W or radius[o] <= params.thin_pixels
    }
    return _ViewLayout(leaf, obj, object_ids, area, parts, group, neighbours, flat, small_or_thin)


# ----------------------------------------------------------------------------------------------
# Boundary perturbations
# ----------------------------------------------------------------------------------------------


def smooth_warp(labels: np.ndarray, amplitude: float, cells: int, rng: np.random.Generator) -> np.ndarray:
    """Resample a label map [H, W] (uint16) through a smooth random displacement field.

    The field is Gaussian noise of standard deviation ``amplitude`` pixels on a
    ``(cells + 1) x (cells + 1)`` grid, upsampled bicubically; nearest-neighbour lookup keeps labels.
    """
    H, W = labels.shape
    if amplitude <= 0:
        return labels.copy()
    grid = (rng.normal(size=(2, cells + 1, cells + 1)) * amplitude).astype(np.float32)
    dx = cv2.resize(grid[0], (W, H), interpolation=cv2.INTER_CUBIC)
    dy = cv2.resize(grid[1], (W, H), interpolation=cv2.INTER_CUBIC)
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float32)
    return cv2.remap(labels, xs + dx, ys + dy, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)


def morph_jitter(mask: np.ndarray, radius: int) -> np.ndarray:
    """Dilate (radius > 0) or erode (radius < 0) a bool mask [H, W] with a disc of |radius| pixels."""
    if radius == 0:
        return mask
    size = 2 * abs(radius) + 1
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    op = cv2.dilate if radius > 0 else cv2.erode
    return op(mask.astype(np.uint8), kernel, borderType=cv2.BORDER_REPLICATE).astype(bool)


def random_line_split(mask: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Cut a bool mask [H, W] in two along a random line through a random pixel of the mask."""
    ys, xs = np.nonzero(mask)
    k = rng.integers(len(ys))
    angle = rng.uniform(0, np.pi)
    H, W = mask.shape
    yy, xx = np.mgrid[0:H, 0:W]
    side = (xx - xs[k]) * np.cos(angle) + (yy - ys[k]) * np.sin(angle) > 0
    return mask & side, mask & ~side


# ----------------------------------------------------------------------------------------------
# Automatic (SAM-AMG-like) masks of one view
# ----------------------------------------------------------------------------------------------


def simulate_view_masks(
    instance_map: np.ndarray,
    objects: ObjectTable | None,
    rng: np.random.Generator,
    params: SimulateParams,
) -> tuple[np.ndarray, np.ndarray]:
    """SAM-automatic-generator-like masks of one view from its ground truth.

    Args:
        instance_map: [H, W] leaf instance ids (0 = unlabelled).
        objects: the hierarchy (None: every id is a stand-alone object, as in Replica).
        rng: the view's random generator.
        params: see :class:`SimulateParams`.
    Returns:
        masks [M, H, W] bool (largest first) and scores [M] float32.
    """
    return _simulate(instance_map, _LevelTables.build(objects), rng, params)


def _simulate(
    instance_map: np.ndarray, tables: _LevelTables, rng: np.random.Generator, params: SimulateParams
) -> tuple[np.ndarray, np.ndarray]:
    instance_map = np.asarray(instance_map)
    if instance_map.ndim != 2:
        raise ValueError(f"instance_map must be [H, W], got {instance_map.shape}")
    H, W = instance_map.shape
    inc = params.inconsistency
    leaf = smooth_warp(instance_map.astype(np.uint16), inc * params.warp_pixels, params.warp_cells, rng)
    view = _analyse_view(leaf, tables, params)

    emitted: list[tuple[np.ndarray, bool]] = []  # (mask, is a whole flat object)

    def emit(mask: np.ndarray, whole_flat: bool = False) -> None:
        emitted.append((mask, whole_flat))

    missed = {o for o in sorted(view.small_or_thin) if rng.random() < params.rate("miss")}
    assigned = set(missed)
    for o in (int(v) for v in rng.permutation(view.object_ids)):
        if o in assigned:
            continue
        r_group, r_part, r_multi = rng.random(3)
        partners: list[int] = []
        if r_group < params.rate("group"):
            members = view.group_members(o)
            if members:
                partners = [m for m in members if m != o and m not in assigned]
            else:
                free = [n for n in view.merge_partners(o) if n not in assigned]
                if free:
                    partners = [free[int(rng.integers(len(free)))]]
        if partners:
            members = [o] + partners
            assigned.update(members)
            emit(view.union_mask(members))
            if r_multi < params.rate("multi"):
                for m in members:
                    emit(view.object_mask(m), m in view.flat)
            continue
        assigned.add(o)
        parts = view.parts.get(o, [])
        if parts and r_part < params.rate("part"):
            for p in parts:
                emit(view.leaf == p)
            if r_multi < params.rate("multi"):
                emit(view.object_mask(o), o in view.flat)
        else:
            emit(view.object_mask(o), o in view.flat)
            if parts and r_multi < params.rate("multi"):
                for p in parts:
                    emit(view.leaf == p)

    # spurious splits of flat regions, then per-mask boundary jitter
    radius = int(round(inc * params.jitter_pixels))
    final: list[np.ndarray] = []
    for mask, whole_flat in emitted:
        pieces = [mask]
        if whole_flat and rng.random() < params.rate("split"):
            a, b = random_line_split(mask, rng)
            if a.sum() >= params.min_mask_pixels and b.sum() >= params.min_mask_pixels:
                pieces = [a, b]
        for piece in pieces:
            if radius > 0:
                jittered = morph_jitter(piece, int(rng.integers(-radius, radius + 1)))
                # erosion must not wipe out a small object: misses are miss_rate's job
                if jittered.sum() >= 0.5 * piece.sum():
                    piece = jittered
            if piece.sum() >= max(params.min_mask_pixels, 1):
                final.append(piece)

    if not final:
        return np.zeros((0, H, W), dtype=bool), np.zeros(0, dtype=np.float32)
    masks = np.stack(final)
    if inc > 0:
        scores = (1.0 - inc * rng.uniform(0.0, 0.15, size=len(masks))).astype(np.float32)
    else:
        scores = np.ones(len(masks), dtype=np.float32)
    order = np.argsort(-masks.sum(axis=(1, 2)), kind="stable")
    return masks[order], scores[order]


def frame_rng(seed: int, frame_index: int) -> np.random.Generator:
    """The random generator of view ``frame_index`` (index into ``scene.cameras``)."""
    return np.random.default_rng([seed, frame_index])


def _need_instances(scene: Scene) -> None:
    if not scene.has_instances:
        raise Trace3DError(
            f"{scene.root / 'instances'}: the `simulated` mask source needs ground-truth instance maps, "
            f"which this scene does not have; use the `files` or `sam` mask source instead."
        )


def iter_simulated_masks(scene: Scene, params: SimulateParams) -> Iterator[tuple[str, np.ndarray, np.ndarray]]:
    """Yield (frame name, masks [M, H, W] bool, scores [M] float32) for every frame of ``scene``."""
    _need_instances(scene)
    tables = _LevelTables.build(scene.objects)
    for index, cam in enumerate(tqdm(scene.cameras, desc="simulated masks", unit="view")):
        masks, scores = _simulate(scene.instances(cam.name), tables, frame_rng(params.seed, index), params)
        yield cam.name, masks, scores


# ----------------------------------------------------------------------------------------------
# Point prompts (SAM with one click)
# ----------------------------------------------------------------------------------------------


class SimulatedPromptSegmenter:
    """Point-prompt segmentation from ground truth: the simulated counterpart of SAM's predictor.

    ``segment(frame, (x, y), rng)`` returns the mask containing the point at a random granularity:
    the group (ground-truth group, or the object with its touching neighbours) with probability
    ``inconsistency * group_rate``, else the part with probability ``inconsistency * part_rate``,
    else the whole object; boundaries are jittered by up to ``inconsistency * jitter_pixels``.
    A point on unlabelled pixels returns the connected unlabelled region around it.
    """

    def __init__(self, scene: Scene, params: SimulateParams | Mapping | None = None):
        _need_instances(scene)
        self.scene = scene
        self.params = params if isinstance(params, SimulateParams) else from_mapping(
            SimulateParams, params, "simulated prompt params"
        )
        self._tables = _LevelTables.build(scene.objects)
        self._layouts: dict[str, _ViewLayout] = {}

    def _layout(self, frame_name: str) -> _ViewLayout:
        if frame_name not in self._layouts:
            try:
                self.scene.camera(frame_name)
            except KeyError:
                raise Trace3DError(f"{self.scene.root / 'cameras.json'}: no frame named {frame_name!r}.") from None
            if len(self._layouts) >= 16:  # bounded cache
                self._layouts.pop(next(iter(self._layouts)))
            self._layouts[frame_name] = _analyse_view(self.scene.instances(frame_name), self._tables, self.params)
        return self._layouts[frame_name]

    def candidates(self, frame_name: str, point_xy: tuple[float, float]) -> dict[str, np.ndarray]:
        """The un-jittered masks containing the point, by granularity.

        Args:
            frame_name: the view.
            point_xy: (x, y) pixel coordinates (pixel centres at +0.5).
        Returns:
            {"object": [H, W] bool, optionally "part" and "group"}.
        """
        view = self._layout(frame_name)
        H, W = view.leaf.shape
        x, y = int(np.floor(point_xy[0])), int(np.floor(point_xy[1]))
        if not (0 <= x < W and 0 <= y < H):
            raise Trace3DError(f"frame {frame_name!r}: prompt point {tuple(point_xy)} lies outside the {W}x{H} image.")
        leaf_id = int(view.leaf[y, x])
        if leaf_id == 0:
            _, comps = cv2.connectedComponents((view.leaf == 0).astype(np.uint8), connectivity=4)
            return {"object": comps == comps[y, x]}
        o = int(view.obj[y, x])
        out = {"object": view.object_mask(o)}
        if o in view.parts:
            out["part"] = view.leaf == leaf_id
        members = view.group_members(o) or [o] + view.merge_partners(o)
        if len(members) > 1:
            out["group"] = view.union_mask(members)
        return out

    def segment(self, frame_name: str, point_xy: tuple[float, float], rng: np.random.Generator) -> np.ndarray:
        """[H, W] bool mask containing ``point_xy`` at a randomly chosen granularity."""
        cands = self.candidates(frame_name, point_xy)
        r_group, r_part = rng.random(2)
        if "group" in cands and r_group < self.params.rate("group"):
            mask = cands["group"]
        elif "part" in cands and r_part < self.params.rate("part"):
            mask = cands["part"]
        else:
            mask = cands["object"]
        radius = int(round(self.params.inconsistency * self.params.jitter_pixels))
        if radius > 0:
            jittered = morph_jitter(mask, int(rng.integers(-radius, radius + 1)))
            x, y = int(np.floor(point_xy[0])), int(np.floor(point_xy[1]))
            if jittered[y, x]:
                mask = jittered
        return mask.copy()


# ----------------------------------------------------------------------------------------------
# Diagnostics against ground truth (any mask source)
# ----------------------------------------------------------------------------------------------


def object_status(
    masks: np.ndarray, instance_map: np.ndarray, objects: ObjectTable | None, min_pixels: int = 32
) -> dict[int, str]:
    """How each visible ground-truth object appears among a view's masks.

    Args:
        masks: [M, H, W] bool.
        instance_map: [H, W] leaf ids.
        objects: hierarchy (None: ids are objects).
        min_pixels: objects with fewer visible pixels are skipped.
    Returns:
        object id -> "whole" (a mask with IoU >= 0.5), "merged" (a mask holds >= half of the
        object but is mostly elsewhere), "split" (masks lying mostly inside the object cover >= half
        of it) or "missed".
    """
    tables = _LevelTables.build(objects)
    leaf = np.asarray(instance_map).astype(np.int64)
    obj = tables.to_object[leaf]
    obj[leaf == 0] = 0
    ids, inverse = np.unique(obj.ravel(), return_inverse=True)
    K = len(ids)
    obj_area = np.bincount(inverse, minlength=K)
    M = len(masks)
    flat_masks = masks.reshape(M, leaf.size)  # (M, -1) is ambiguous for a view without masks
    inter = np.zeros((M, K), dtype=np.int64)  # [M, K] pixels of mask m on object k
    for m in range(M):
        inter[m] = np.bincount(inverse[flat_masks[m]], minlength=K)
    mask_area = flat_masks.sum(axis=1)
    status = {}
    for k, o in enumerate(ids):
        if o == 0 or obj_area[k] < min_pixels:
            continue
        i = inter[:, k]
        iou = i / np.maximum(obj_area[k] + mask_area - i, 1)
        if M and iou.max() >= 0.5:
            status[int(o)] = "whole"
        elif M and np.any((i >= 0.5 * obj_area[k]) & (i < 0.5 * mask_area)):
            status[int(o)] = "merged"
        elif M and i[(i >= 0.5 * mask_area) & (i > 0)].sum() >= 0.5 * obj_area[k]:
            status[int(o)] = "split"
        else:
            status[int(o)] = "missed"
    return status


def cross_view_disagreement(statuses: list[dict[int, str]]) -> dict:
    """Summarise :func:`object_status` over views.

    Returns:
        {"objects": number seen in >= 2 views, "inconsistent_fraction": fraction of those whose
        status differs between views, "status_counts": counts over all (view, object) entries}.
    """
    per_object: dict[int, set[str]] = {}
    seen: Counter = Counter()
    counts: Counter = Counter()
    for status in statuses:
        for o, s in status.items():
            per_object.setdefault(o, set()).add(s)
            seen[o] += 1
            counts[s] += 1
    multi = [o for o in per_object if seen[o] >= 2]
    inconsistent = sum(len(per_object[o]) > 1 for o in multi)
    return {
        "objects": len(multi),
        "inconsistent_fraction": inconsistent / len(multi) if multi else 0.0,
        "status_counts": dict(sorted(counts.items())),
    }
