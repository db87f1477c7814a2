"""Nested SAM-like masks: the simulated model of SAM's *automatic* mask generator.

Selected with ``masks: {source: simulated, simulated: {model: nested}}``; the older model
(:mod:`.simulate`, ``model: one_level``) stays for comparison.

SAM's automatic generator prompts a 32 x 32 grid of points and keeps, per point, up to three
nested masks (multimask output: subpart, part, whole); the masks that pass the predicted-IoU and
stability thresholds and box NMS are returned together, so the mask set of one view is *nested
and over-segmented*, and which levels survive for an object changes from view to view.  This
model draws that per view from the ground truth (objects.json hierarchy) and the image:

* per visible object, independently: its **parts** (objects with >= 2 visible parts, rate
  ``part_rate``), **subparts** (each finest region, part or single-part object, cut along the
  image's texture / shading edges: an Otsu split of its luminance into connected pieces, or a
  random smooth cut where the region has no edge; rate ``subpart_rate``), its **group** (the
  ``objects.json`` parent at level ``group``, or for a stand-alone object one touching neighbour;
  rate ``group_rate``), and the **whole** object, which is dropped with ``whole_drop_rate`` when
  finer masks cover >= ``drop_cover`` of it (otherwise always emitted);
* walls, floor, ceiling ("stuff") are cut into 2..``stuff_max_pieces`` pieces (shading edges or
  random smooth cuts; rate ``stuff_split_rate``), the enclosing whole kept or dropped
  (``stuff_whole_drop_rate``);
* small or thin objects are missed (``miss_rate``): no mask at any level of their own;
* borders are ragged: one smooth random warp of the label map per view (``warp_pixels``) and a
  random dilation / erosion of every mask by up to ``jitter_pixels``;
* post-processing as SAM's generator and the released preprocessing do: masks below
  ``min_mask_pixels`` dropped, duplicates (mask IoU > ``nms_iou``) suppressed keeping the higher
  score, then masks covered at
  least ``nest_coverage`` by a larger one merged into it (:func:`.sam.nest_covered_masks`).

The knob ``inconsistency`` in [0, 1] (default 0.5 = the calibrated SAM-like level) sets every rate
``r`` to ``1 - (1 - r) ** (inconsistency / 0.5)``: 0 gives exact object masks (no warp, jitter,
misses, splits; score 1), 0.5 the rates as written (docs/masks_calibration.md), 1 the rates
compounded twice.  Amplitudes (``warp_pixels``, ``jitter_pixels``) scale by ``inconsistency / 0.5``.
Everything is drawn from ``numpy.random.default_rng([seed, frame_index])``.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Iterator, Literal

import cv2
import numpy as np
from tqdm import tqdm

from ..params import check_ranges
from ..scene import ObjectTable, Scene
from .sam import nest_covered_masks
from .simulate import (
    DEFAULT_FLAT_CATEGORIES,
    _analyse_view,
    _LevelTables,
    _need_instances,
    _ViewLayout,
    frame_rng,
    morph_jitter,
    smooth_warp,
)

log = logging.getLogger(__name__)

REFERENCE_INCONSISTENCY = 0.5  # the level at which the rates apply as written (the calibrated level)


@dataclasses.dataclass
class NestedParams:
    """Parameters of the nested (SAM-automatic-generator-like) simulated masks.

    Rates are probabilities per object (or stuff region) per view at ``inconsistency`` = 0.5; the
    defaults are the calibration of docs/masks_calibration.md (fixed on mask statistics only).

    Attributes:
        model: always ``"nested"`` (selects this model under ``masks.simulated``).
        seed: random seed (combined with the frame index).
        inconsistency: in [0, 1]; 0 exact object masks, 0.5 the calibrated level (module docstring).
        part_rate: an object with >= 2 visible parts also gets its part masks.
        subpart_rate: each finest region (part, or single-part object) of an object is also cut
            into subpart masks (applies per object: all its finest regions or none).
        group_rate: the object's group (or object + one touching neighbour) gets a mask.
        whole_drop_rate: the whole-object mask is left out when a finer level is present.
        miss_rate: a small or thin object gets no mask of its own.
        stuff_split_rate: a wall / floor / ceiling region is cut into pieces.
        stuff_whole_drop_rate: a cut stuff region's enclosing whole mask is left out.
        drop_cover: the whole is only dropped when the finer masks cover at least this share of it
            (otherwise SAM's grid points on the uncovered rest would return the whole).
        max_subparts: most subpart masks per region (the largest pieces are kept).
        stuff_max_pieces: most pieces a stuff region is cut into (>= 2).
        edge_contrast: a region whose luminance standard deviation (0..1 scale) is below this has no
            texture / shading edge and is cut along a random smooth line instead.
        cut_cells: control-grid cells of the random smooth cut field across the image.
        jitter_pixels: largest per-mask dilation / erosion radius at inconsistency 0.5.
        warp_pixels: standard deviation of the per-view smooth label warp at inconsistency 0.5.
        warp_cells: control-grid cells of the warp.
        small_fraction: objects covering less than this fraction of the image count as small.
        thin_pixels: objects whose largest inscribed radius is at most this count as thin.
        flat_categories: categories treated as stuff (lower-case match of SceneObject.category).
        flat_fraction: uncategorised objects covering at least this fraction count as stuff.
        touch_pixels: two objects touch when they share at least this many boundary pixel pairs.
        min_mask_pixels: masks with fewer pixels are dropped (the released preprocessing drops
            masks of <= 96 px at 640 x 480: 6 px at 160 x 120).
        nms_iou: mask-IoU threshold of the duplicate suppression (SAM's ``box_nms_thresh`` value;
            :func:`duplicate_nms` says why mask IoU).
        nest_coverage: a mask covered at least this much by a larger one is merged into it.
    """

    model: Literal["one_level", "nested"] = "nested"
    seed: int = 0
    inconsistency: float = 0.5
    part_rate: float = 0.55
    subpart_rate: float = 0.3
    group_rate: float = 0.25
    whole_drop_rate: float = 0.3
    miss_rate: float = 0.5
    stuff_split_rate: float = 0.8
    stuff_whole_drop_rate: float = 0.4
    drop_cover: float = 0.7
    max_subparts: int = 3
    stuff_max_pieces: int = 3
    edge_contrast: float = 0.04
    cut_cells: int = 3
    jitter_pixels: int = 1
    warp_pixels: float = 1.0
    warp_cells: int = 6
    small_fraction: float = 0.002
    thin_pixels: float = 1.5
    flat_categories: list[str] = dataclasses.field(default_factory=lambda: list(DEFAULT_FLAT_CATEGORIES))
    flat_fraction: float = 0.12
    touch_pixels: int = 4
    min_mask_pixels: int = 6
    nms_iou: float = 0.7
    nest_coverage: float = 0.9

    # each field's range: refused on input and in the config schema (trace3d.params.check_ranges)
    RANGES = {"inconsistency": "[0, 1]", "part_rate": "[0, 1]", "subpart_rate": "[0, 1]", "group_rate": "[0, 1]",
              "whole_drop_rate": "[0, 1]", "miss_rate": "[0, 1]", "stuff_split_rate": "[0, 1]",
              "stuff_whole_drop_rate": "[0, 1]", "drop_cover": "[0, 1]", "edge_contrast": "[0, 1]",
              "small_fraction": "[0, 1]", "flat_fraction": "[0, 1]", "jitter_pixels": ">= 0", "warp_pixels": ">= 0",
              "thin_pixels": ">= 0", "touch_pixels": ">= 0", "min_mask_pixels": ">= 0", "seed": ">= 0",
              "max_subparts": ">= 2", "stuff_max_pieces": ">= 2", "warp_cells": ">= 1", "cut_cells": ">= 1",
              "nms_iou": "(0, 1]", "nest_coverage": "(0, 1]"}

    def __post_init__(self) -> None:
        if self.model != "nested":
            raise ValueError(f"model must be 'nested' for these parameters, got {self.model!r}")
        check_ranges(self)
        self.flat_categories = [c.lower() for c in self.flat_categories]

    def rate(self, name: str) -> float:
        """``<name>_rate`` at this inconsistency: ``1 - (1 - r) ** (inconsistency / 0.5)``."""
        r = getattr(self, f"{name}_rate")
        if self.inconsistency == 0.0:
            return 0.0
        return float(1.0 - (1.0 - r) ** (self.inconsistency / REFERENCE_INCONSISTENCY))

    def amplitude(self, value: float) -> float:
        """A border amplitude scaled by ``inconsistency / 0.5``."""
        return value * self.inconsistency / REFERENCE_INCONSISTENCY


# ----------------------------------------------------------------------------------------------
# Cuts of one region
# ----------------------------------------------------------------------------------------------


def luminance(image: np.ndarray) -> np.ndarray:
    """[H, W] float32 luminance in [0, 1] of an RGB uint8 image [H, W, 3], lightly smoothed."""
    gray = cv2.cvtColor(np.ascontiguousarray(image[..., :3]), cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
    return cv2.GaussianBlur(gray, (3, 3), 0.7)


def _otsu_threshold(values: np.ndarray) -> float:
    """Otsu's threshold of 1-D values in [0, 1] (64 bins)."""
    hist, edges = np.histogram(values, bins=64, range=(0.0, 1.0))
    hist = hist.astype(np.float64)
    centres = 0.5 * (edges[:-1] + edges[1:])
    w0 = np.cumsum(hist)
    w1 = w0[-1] - w0
    m0 = np.cumsum(hist * centres)
    mean0 = m0 / np.maximum(w0, 1e-12)
    mean1 = (m0[-1] - m0) / np.maximum(w1, 1e-12)
    between = w0 * w1 * (mean0 - mean1) ** 2
    between[(w0 == 0) | (w1 == 0)] = -1.0
    return float(edges[int(np.argmax(between)) + 1])


def edge_pieces(region: np.ndarray, lum: np.ndarray, min_pixels: int, max_pieces: int) -> list[np.ndarray]:
    """Cut a region along its luminance edge: connected pieces of its two Otsu classes.

    Args:
        region: [H, W] bool.
        lum: [H, W] float32 luminance in [0, 1].
        min_pixels: smaller pieces are dropped (left to the coarser masks, as SAM leaves them).
        max_pieces: the largest pieces kept.
    Returns:
        up to ``max_pieces`` disjoint [H, W] bool pieces inside ``region`` (largest first); fewer
        than 2 when the region has no usable edge.
    """
    values = lum[region]
    if len(values) < 2:
        return []
    threshold = _otsu_threshold(values)
    pieces = []
    bright = lum >= threshold
    for cls in (region & bright, region & ~bright):
        count, comps = cv2.connectedComponents(cls.astype(np.uint8), connectivity=4)
        if count <= 1:
            continue
        areas = np.bincount(comps.ravel(), minlength=count)
        for c in range(1, count):
            if areas[c] >= max(min_pixels, 1):
                pieces.append((int(areas[c]), len(pieces), comps, c))
    pieces.sort(key=lambda t: (-t[0], t[1]))
    return [comps == c for _, _, comps, c in pieces[:max_pieces]]


def smooth_cut(region: np.ndarray, cells: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Cut a bool region [H, W] in two along a random smooth curve (the median level of a smooth field)."""
    H, W = region.shape
    grid = rng.normal(size=(cells + 1, cells + 1)).astype(np.float32)
    field = cv2.resize(grid, (W, H), interpolation=cv2.INTER_CUBIC)
    level = float(np.median(field[region]))
    side = field > level
    return region & side, region & ~side


def cut_region(
    region: np.ndarray, lum: np.ndarray, pieces: int, params: NestedParams, rng: np.random.Generator
) -> list[np.ndarray]:
    """Cut ``region`` [H, W] bool into up to ``pieces`` subparts: along edges when it has one, else smooth cuts."""
    values = lum[region]
    if len(values) >= 2 and float(values.std()) >= params.edge_contrast:
        found = edge_pieces(region, lum, params.min_mask_pixels, pieces)
        if len(found) >= 2:
            return found
    out = [region]
    while len(out) < pieces:
        largest = int(np.argmax([p.sum() for p in out]))
        a, b = smooth_cut(out[largest], params.cut_cells, rng)
        if a.sum() < params.min_mask_pixels or b.sum() < params.min_mask_pixels:
            break
        out[largest:largest + 1] = [a, b]
    return out if len(out) >= 2 else []


# ----------------------------------------------------------------------------------------------
# Post-processing as SAM's generator does
# ----------------------------------------------------------------------------------------------


def pairwise_intersections(masks: np.ndarray) -> np.ndarray:
    """[M, M] int64 pixel counts of ``masks[a] & masks[b]`` (diagonal: areas), masks [M, H, W] bool.

    Counted over the distinct covering patterns of the pixels (no large float product).
    """
    M = len(masks)
    flat = masks.reshape(M, -1)
    covered = flat.any(axis=0)
    if not covered.any():
        return np.zeros((M, M), dtype=np.int64)
    packed = np.packbits(flat[:, covered], axis=0).T  # [pixels, ceil(M / 8)] uint8
    # one integer pattern id per pixel, built one byte column at a time (1-D uniques only)
    ids = np.zeros(len(packed), dtype=np.int64)
    for column in packed.T:
        _, ids = np.unique(ids * 256 + column, return_inverse=True)
        ids = ids.reshape(-1)
    first = np.unique(ids, return_index=True)[1]
    counts = np.bincount(ids)
    bits = np.unpackbits(packed[first], axis=1, count=M).astype(np.int64)  # [S, M]
    return bits.T @ (bits * counts[:, None])


def duplicate_nms(masks: np.ndarray, scores: np.ndarray, iou_threshold: float) -> np.ndarray:
    """[M] bool keep-flags of greedy non-maximum suppression on mask IoU (higher score first).

    SAM's generator suppresses by box IoU; on the nested pieces of one region (a wall cut in two
    keeps nearly the wall's box) box IoU would remove the piece *or* the whole and leave the rest of
    the region uncovered, where SAM's other grid points would have found it again.  Mask IoU removes
    only real duplicates (e.g. a whole object and a part that is nearly all of it).

    Args:
        masks: [M, H, W] bool.
        scores: [M] float.
    """
    M = len(masks)
    if M == 0:
        return np.zeros(0, dtype=bool)
    inter = pairwise_intersections(masks)
    area = np.diag(inter)
    iou = inter / np.maximum(area[:, None] + area[None, :] - inter, 1e-12)
    order = np.argsort(-np.asarray(scores), kind="stable")
    keep = np.zeros(M, dtype=bool)
    for i in order:
        if not np.any(iou[i, keep] > iou_threshold):
            keep[i] = True
    return keep


# ----------------------------------------------------------------------------------------------
# One view
# ----------------------------------------------------------------------------------------------


def nested_view_masks(
    instance_map: np.ndarray,
    image: np.ndarray,
    objects: ObjectTable | None,
    rng: np.random.Generator,
    params: NestedParams,
) -> tuple[np.ndarray, np.ndarray]:
    """Nested SAM-automatic-generator-like masks of one view from its ground truth and image.

    Args:
        instance_map: [H, W] leaf instance ids (0 = unlabelled).
        image: [H, W, 3] uint8 RGB of the view (subparts follow its edges).
        objects: the hierarchy (None: every id is a stand-alone object, as in Replica).
        rng: the view's random generator.
        params: see :class:`NestedParams`.
    Returns:
        masks [M, H, W] bool (largest first) and scores [M] float32.
    """
    return _nested(instance_map, image, _LevelTables.build(objects), rng, params)


def _nested(
    instance_map: np.ndarray, image: np.ndarray, tables: _LevelTables, rng: np.random.Generator, params: NestedParams
) -> tuple[np.ndarray, np.ndarray]:
    instance_map = np.asarray(instance_map)
    if instance_map.ndim != 2:
        raise ValueError(f"instance_map must be [H, W], got {instance_map.shape}")
    H, W = instance_map.shape
    if image.shape[:2] != (H, W):
        raise ValueError(f"image must be [{H}, {W}, 3], got {image.shape}")
    inc = params.inconsistency
    leaf = smooth_warp(instance_map.astype(np.uint16), params.amplitude(params.warp_pixels), params.warp_cells, rng)
    view: _ViewLayout = _analyse_view(leaf, tables, params)
    lum = luminance(image)

    emitted: list[np.ndarray] = []
    groups_done: set[tuple[int, ...]] = set()
    p_part, p_sub, p_group = params.rate("part"), params.rate("subpart"), params.rate("group")
    p_drop, p_miss = params.rate("whole_drop"), params.rate("miss")
    p_split, p_stuff_drop = params.rate("stuff_split"), params.rate("stuff_whole_drop")

    for o in (int(v) for v in view.object_ids):
        # one fixed number of draws per object keeps the stream aligned whatever is drawn
        r_miss, r_part, r_sub, r_group, r_drop, r_split, r_pieces = rng.random(7)
        whole = view.object_mask(o)
        if o in view.flat:
            finer = []
            if r_split < p_split:
                pieces = 2 + int(r_pieces * (params.stuff_max_pieces - 1))
                finer = cut_region(whole, lum, pieces, params, rng)
            emitted.extend(finer)
            if r_drop >= p_stuff_drop or not _covers(finer, whole, params.drop_cover):
                emitted.append(whole)
        else:
            if o in view.small_or_thin and r_miss < p_miss:
                continue
            parts = [view.leaf == p for p in view.parts.get(o, [])]
            finer = []
            if parts and r_part < p_part:
                finer.extend(parts)
            if r_sub < p_sub:
                for region in parts or [whole]:
                    finer.extend(cut_region(region, lum, params.max_subparts, params, rng))
            emitted.extend(finer)
            if r_drop >= p_drop or not _covers(finer, whole, params.drop_cover):
                emitted.append(whole)
        if r_group < p_group:
            members = view.group_members(o)
            if not members:
                partners = view.merge_partners(o)
                if partners:
                    members = [o, partners[int(r_pieces * len(partners)) % len(partners)]]
            key = tuple(sorted(members))
            if len(key) >= 2 and key not in groups_done:
                groups_done.add(key)
                emitted.append(view.union_mask(key))

    radius = int(round(params.amplitude(params.jitter_pixels)))
    final: list[np.ndarray] = []
    for mask in emitted:
        if radius > 0:
            jittered = morph_jitter(mask, int(rng.integers(-radius, radius + 1)))
            if jittered.sum() >= 0.5 * mask.sum():  # erosion must not wipe out a small object
                mask = jittered
        if mask.sum() >= max(params.min_mask_pixels, 1):
            final.append(mask)
    if not final:
        return np.zeros((0, H, W), dtype=bool), np.zeros(0, dtype=np.float32)
    masks = np.stack(final)
    if inc > 0:
        # SAM's predicted IoU of the masks it keeps: above its 0.88 threshold
        scores = rng.uniform(0.88, 1.0, size=len(masks)).astype(np.float32)
        keep = duplicate_nms(masks, scores, params.nms_iou)
        masks, scores = masks[keep], scores[keep]
    else:
        # exact object masks are disjoint: nothing to suppress
        scores = np.ones(len(masks), dtype=np.float32)
    masks, order = nest_covered_masks(masks, params.nest_coverage)
    scores = scores[order]
    order = np.argsort(-masks.sum(axis=(1, 2)), kind="stable")
    return masks[order], scores[order]


def _covers(pieces: list[np.ndarray], region: np.ndarray, share: float = 0.9) -> bool:
    """Whether ``pieces`` cover at least ``share`` of ``region`` (else the whole is kept: SAM's grid
    points on the uncovered rest would return it)."""
    if not pieces:
        return False
    union = np.logical_or.reduce(pieces)
    return bool((union & region).sum() >= share * region.sum())


def iter_nested_masks(scene: Scene, params: NestedParams) -> Iterator[tuple[str, np.ndarray, np.ndarray]]:
    """Yield (frame name, masks [M, H, W] bool, scores [M] float32) for every frame of ``scene``."""
    _need_instances(scene)
    tables = _LevelTables.build(scene.objects)
    for index, cam in enumerate(tqdm(scene.cameras, desc="nested simulated masks", unit="view")):
        masks, scores = _nested(scene.instances(cam.name), scene.image(cam.name), tables,
                                frame_rng(params.seed, index), params)
        yield cam.name, masks, scores
