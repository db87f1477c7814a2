"""The ``graph`` mask source: nested multi-scale graph segmentation that never reads the ground truth.

Each image is segmented by Felzenszwalb & Huttenlocher's graph method (scikit-image's
``felzenszwalb``) at ``len(scales)`` (>= 3) scales, finest first. The partitions are then made
**nested**, fine to coarse, so that the mask set is a strict hierarchy like SAM's subpart / part /
whole answers:

* the finest partition is kept as it is;
* every region of level ``k`` is assigned to the region of the raw level-``k + 1`` partition that
  holds most of its pixels (ties: the lower label), and level ``k + 1`` is redefined as the unions of
  the level-``k`` regions so assigned. A coarse region therefore takes its borders from the finest
  partition (the most accurate edges), and a coarse region that no finer region chose disappears.

Before nesting, thin regions of each raw partition (chiefly the strips of blurred colour that the
method leaves along strong edges) are dissolved into the nearest regions (``thin_pixels``).

Every region of every level is emitted as one mask unless it covers fewer than ``min_area`` or more
than ``max_area`` of the image (the whole-image region says nothing), and a region identical to the
region it was built from at the finer level is emitted once. Any two masks of one view are hence
disjoint or nested (an exact hierarchy, tested); the finest level covers the image except regions
under ``min_area``. Graph segmentation gives no confidence: every score is 1.

Size scaling: the parameters are given for an image of ``reference_pixels`` pixels (160 x 120, the
synthetic rooms' size). For an image of ``H * W`` pixels with ``f = H * W / reference_pixels``,
Felzenszwalb's ``scale`` is multiplied by ``f`` (its merge threshold ``scale / |region|`` then treats
a region covering the same share of the image alike) and ``sigma`` (a length, in pixels) by
``sqrt(f)``; ``min_size`` and ``min_area`` are fractions of the image's pixels.

:class:`GraphPromptSegmenter` is the point-prompt counterpart for self-prompting
(:mod:`trace3d.lifting.self_prompt`, ``prompt_source: graph``), reading no ground truth either: the
candidates are, per level, the union of the regions under the positive points that hold no negative
point; like SAM's three answers, the one closest to the caller's ``like`` mask is taken (without
one: the finest level at which one region holds every positive point and no negative); optionally
refined by OpenCV's GrabCut seeded with that candidate (see :class:`GraphPromptParams`).

Everything is deterministic: no random choice is made.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Iterator, Mapping

import numpy as np
from tqdm import tqdm

from ..errors import Trace3DError
from ..params import from_mapping
from ..scene import Scene

log = logging.getLogger(__name__)

REFERENCE_PIXELS = 160 * 120


@dataclasses.dataclass
class GraphParams:
    """Parameters of the ``graph`` mask source (module docstring: how they scale with the image).

    Attributes:
        scales: Felzenszwalb ``scale`` of each level at ``reference_pixels`` (>= 3 values, strictly
            increasing: finest first). Larger: larger regions.
        sigma: Gaussian pre-smoothing width in pixels at ``reference_pixels``.
        min_size: Felzenszwalb's post-merge minimum region size, as a fraction of the image pixels.
        min_area: regions covering less than this fraction of the image give no mask.
        max_area: regions covering more than this fraction of the image give no mask.
        thin_pixels: half-width (pixels at ``reference_pixels``, scaled by ``sqrt(f)`` and rounded
            up) under which a raw region counts as thin: one of at least ``2 (2 r + 1)^2`` pixels
            with no pixel whose whole ``(2 r + 1)``-square neighbourhood lies in it. Thin regions (chiefly the strips of
            blurred colour that Felzenszwalb leaves along strong edges) are dissolved, pixel by
            pixel, into the nearest region that is not thin. 0: keep them.
        reference_pixels: the image size (pixels) at which ``scales`` and ``sigma`` apply as given.
    """

    scales: list[float] = dataclasses.field(default_factory=lambda: [150.0, 400.0, 1000.0, 2500.0])
    sigma: float = 0.8
    min_size: float = 0.003
    min_area: float = 0.003
    max_area: float = 0.9
    thin_pixels: float = 1.0
    reference_pixels: int = REFERENCE_PIXELS

    # each field's range: refused on input and in the config schema (trace3d.params.check_ranges)
    RANGES = {"sigma": ">= 0", "min_size": "[0, 1)", "min_area": "[0, 1)", "max_area": "(0, 1]",
              "thin_pixels": ">= 0", "reference_pixels": ">= 1", "scales": "> 0"}

    def __post_init__(self) -> None:
        self.scales = [float(s) for s in self.scales]
        if len(self.scales) < 3:
            raise ValueError(f"scales needs at least 3 values (finest first), got {self.scales}")
        if any(s <= 0 for s in self.scales) or any(b <= a for a, b in zip(self.scales, self.scales[1:])):
            raise ValueError(f"scales must be positive and strictly increasing (finest first), got {self.scales}")
        if self.sigma < 0:
            raise ValueError(f"sigma must be >= 0, got {self.sigma}")
        for name in ("min_size", "min_area"):
            if not 0.0 <= getattr(self, name) < 1.0:
                raise ValueError(f"{name} must be a fraction of the image in [0, 1), got {getattr(self, name)}")
        if not self.min_area < self.max_area <= 1.0:
            raise ValueError(f"max_area must be in (min_area, 1], got {self.max_area}")
        if self.thin_pixels < 0:
            raise ValueError(f"thin_pixels must be >= 0, got {self.thin_pixels}")
        if self.reference_pixels < 1:
            raise ValueError(f"reference_pixels must be >= 1, got {self.reference_pixels}")

    def resolved(self, height: int, width: int) -> dict:
        """The pixel-unit settings for an ``height`` x ``width`` image (module docstring)."""
        pixels = height * width
        factor = pixels / self.reference_pixels
        return {
            "scales": [s * factor for s in self.scales],
            "sigma": self.sigma * float(np.sqrt(factor)),
            "min_size": max(1, int(np.ceil(self.min_size * pixels))),
            "min_area": max(1, int(np.ceil(self.min_area * pixels))),
            "max_area": int(np.floor(self.max_area * pixels)),
            "thin_radius": int(np.ceil(self.thin_pixels * np.sqrt(factor))),
        }


def _consecutive(labels: np.ndarray) -> tuple[np.ndarray, int]:
    """Relabel an int map to 0..n-1 (in order of the old labels); returns the map and n."""
    uniq, inverse = np.unique(labels, return_inverse=True)
    return inverse.reshape(labels.shape).astype(np.int32), len(uniq)


def nest_partitions(levels: np.ndarray) -> np.ndarray:
    """Make label maps nested, fine to coarse, by majority assignment (module docstring).

    Args:
        levels: [K, H, W] int partitions, finest first.
    Returns:
        [K, H, W] int32: level 0 relabelled 0..n0-1; level k's labels are a function of level k-1's
        (every level-(k-1) region lies inside exactly one level-k region).
    """
    levels = np.asarray(levels)
    out = np.empty(levels.shape, np.int32)
    out[0], n_fine = _consecutive(levels[0])
    for k in range(1, len(levels)):
        coarse, n_coarse = _consecutive(levels[k])
        overlap = np.bincount((out[k - 1].ravel().astype(np.int64) * n_coarse + coarse.ravel()),
                              minlength=n_fine * n_coarse).reshape(n_fine, n_coarse)
        parent = np.argmax(overlap, axis=1)  # first maximum: the lower label on ties
        out[k], n_fine = _consecutive(parent[out[k - 1]])
    return out


def _nest_partitions_reference(levels: np.ndarray) -> np.ndarray:
    """Loop twin of :func:`nest_partitions` (used by the tests)."""
    levels = np.asarray(levels)
    out = np.empty(levels.shape, np.int32)
    out[0], _ = _consecutive(levels[0])
    for k in range(1, len(levels)):
        coarse, _ = _consecutive(levels[k])
        assigned = np.empty_like(out[k - 1])
        for r in np.unique(out[k - 1]):
            inside = out[k - 1] == r
            values, counts = np.unique(coarse[inside], return_counts=True)
            assigned[inside] = values[np.argmax(counts)]
        out[k], _ = _consecutive(assigned)
    return out


def dissolve_thin(labels: np.ndarray, radius: int) -> np.ndarray:
    """Dissolve thin regions into their neighbours (:class:`GraphParams` ``thin_pixels``).

    Args:
        labels: [H, W] int partition; radius: the half-width of the square test window (0: no-op).
    Returns:
        [H, W] int partition: each pixel of a thin region — one of at least ``2 (2 radius + 1)^2``
        pixels (smaller ones are small, not thin: Felzenszwalb's ``min_size`` governs them) with no
        interior pixel (one whose ``(2 radius + 1)``-square neighbourhood, clipped to the image,
        lies inside the region) — takes the label of the nearest pixel not in a thin region
        (Euclidean distance; unchanged when every pixel is in one).
    """
    from scipy import ndimage

    if radius <= 0:
        return labels
    size = 2 * radius + 1
    interior = ndimage.maximum_filter(labels, size=size, mode="nearest") == ndimage.minimum_filter(
        labels, size=size, mode="nearest")
    n = int(labels.max()) + 1
    has_interior = np.bincount(labels[interior].ravel(), minlength=n) > 0
    large = np.bincount(labels.ravel(), minlength=n) >= 2 * size * size
    thin = (~has_interior & large)[labels]
    if not thin.any() or thin.all():
        return labels
    _, (rows, cols) = ndimage.distance_transform_edt(thin, return_indices=True)
    return labels[rows, cols]


def graph_hierarchy(image: np.ndarray, params: GraphParams) -> np.ndarray:
    """Nested multi-scale Felzenszwalb partitions of one image.

    Args:
        image: [H, W, 3] uint8 RGB.
    Returns:
        [K, H, W] int32 label maps, finest first, nested (:func:`nest_partitions`).
    """
    from skimage.segmentation import felzenszwalb

    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3:
        raise Trace3DError(f"graph masks: expected an [H, W, 3] RGB image, got shape {image.shape}.")
    H, W = image.shape[:2]
    r = params.resolved(H, W)
    levels = np.stack([
        dissolve_thin(felzenszwalb(image, scale=s, sigma=r["sigma"], min_size=r["min_size"], channel_axis=-1),
                      r["thin_radius"])
        for s in r["scales"]
    ])
    return nest_partitions(levels)


def hierarchy_masks(hierarchy: np.ndarray, params: GraphParams) -> tuple[np.ndarray, np.ndarray]:
    """The masks of a nested hierarchy: every region of every level, finest level first.

    A region is skipped when its area is outside [min_area, max_area] (resolved for the image) or
    when it equals the single finer region it was built from (:func:`nested_masks`).

    Args:
        hierarchy: [K, H, W] int32 nested label maps (:func:`graph_hierarchy`).
    Returns:
        masks [M, H, W] bool and level [M] int32 (the level each mask comes from).
    """
    K, H, W = hierarchy.shape
    r = params.resolved(H, W)
    return nested_masks(hierarchy, r["min_area"], r["max_area"])


def nested_masks(hierarchy: np.ndarray, min_area: int, max_area: int,
                 exclude: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Every region of every level of a nested hierarchy as a mask, finest level first.

    A region is skipped when its area (pixels) is outside [min_area, max_area], when it equals the
    single finer region it was built from, or when more than half of it lies in ``exclude``.

    Args:
        hierarchy: [K, H, W] int nested label maps; exclude: [H, W] bool, optional.
    Returns:
        masks [M, H, W] bool and level [M] int32 (the level each mask comes from).
    """
    K, H, W = hierarchy.shape
    masks, level_of = [], []
    for k in range(K):
        labels = hierarchy[k]
        n = int(labels.max()) + 1
        areas = np.bincount(labels.ravel(), minlength=n)
        excluded = (np.bincount(labels[exclude].ravel(), minlength=n) if exclude is not None
                    else np.zeros(n, np.int64))
        if k > 0:  # children per region: a region with one child repeats that child's mask
            pairs = np.unique(hierarchy[k - 1].ravel().astype(np.int64) * n + labels.ravel())
            children = np.bincount(pairs % n, minlength=n)
        for label in range(n):
            if not min_area <= areas[label] <= max_area or 2 * excluded[label] > areas[label]:
                continue
            if k > 0 and children[label] == 1:
                continue
            masks.append(labels == label)
            level_of.append(k)
    if not masks:
        return np.zeros((0, H, W), bool), np.zeros(0, np.int32)
    return np.stack(masks), np.asarray(level_of, np.int32)


def graph_view_masks(image: np.ndarray, params: GraphParams) -> tuple[np.ndarray, np.ndarray]:
    """One view's masks [M, H, W] bool and scores [M] float32 (all 1) from its RGB image [H, W, 3]."""
    masks, _ = hierarchy_masks(graph_hierarchy(image, params), params)
    return masks, np.ones(len(masks), np.float32)


def iter_graph_masks(scene: Scene, params: GraphParams) -> Iterator[tuple[str, np.ndarray, np.ndarray]]:
    """Yield (frame name, masks [M, H, W] bool, scores [M] float32) for every frame, from the images only."""
    log.info("graph masks: Felzenszwalb at scales %s (at %d pixels), sigma %.2f, nested fine to coarse",
             params.scales, params.reference_pixels, params.sigma)
    for cam in tqdm(scene.cameras, desc="graph masks", unit="view", mininterval=5.0):
        masks, scores = graph_view_masks(scene.image(cam.name), params)
        yield cam.name, masks, scores


# ----------------------------------------------------------------------------------------------
# Point prompts
# ----------------------------------------------------------------------------------------------


# the prompt source's default hierarchy: finer than the mask source's (measured best, docs/masks.md)
PROMPT_HIERARCHY = {"scales": [30.0, 100.0, 300.0, 1000.0, 2500.0], "min_size": 0.001, "min_area": 0.001}


@dataclasses.dataclass
class GraphPromptParams:
    """Parameters of the ``graph`` prompt source (lift params ``graph``).

    Attributes:
        graph: :class:`GraphParams` overrides (the hierarchy the candidates come from); default
            ``PROMPT_HIERARCHY``, five levels finer than the mask source's (``{}``: the mask
            source's defaults).
        select: how a level's candidate is built when the caller passes ``like``: ``points`` (the
            regions under the positive points, as SAM answers clicks) or ``fit`` (those regions and
            every region with at least ``fit_share`` of its pixels inside ``like``: the level's best
            fit to the rendered region). Regions holding a negative point are left out either way.
        fit_share: see ``select``.
        refine: ``none`` (the chosen graph candidate) or ``grabcut`` (OpenCV's GrabCut initialised
            with the candidate as probable foreground, the positive points as sure foreground, the
            negative points and everything farther than ``grabcut_margin`` from the candidate as sure
            background, the rest probable background).
        grabcut_iterations: GrabCut iterations.
        grabcut_margin: fraction of the image diagonal around the candidate left to GrabCut.
    """

    graph: dict = dataclasses.field(default_factory=lambda: dict(PROMPT_HIERARCHY))
    select: str = "fit"
    fit_share: float = 0.5
    refine: str = "none"
    grabcut_iterations: int = 3
    grabcut_margin: float = 0.05

    def __post_init__(self) -> None:
        if self.select not in ("points", "fit"):
            raise ValueError(f"select must be 'points' or 'fit', got {self.select!r}")
        if not 0.0 < self.fit_share <= 1.0:
            raise ValueError(f"fit_share must be in (0, 1], got {self.fit_share}")
        if self.refine not in ("none", "grabcut"):
            raise ValueError(f"refine must be 'none' or 'grabcut', got {self.refine!r}")
        if self.grabcut_iterations < 1:
            raise ValueError(f"grabcut_iterations must be >= 1, got {self.grabcut_iterations}")
        if not 0.0 <= self.grabcut_margin <= 1.0:
            raise ValueError(f"grabcut_margin must be in [0, 1], got {self.grabcut_margin}")


def _pixels(points: np.ndarray | None, H: int, W: int, what: str, frame: str) -> np.ndarray:
    """[K, 2] (x, y) float points -> [K, 2] int (row, col), refusing points outside the image."""
    if points is None:
        return np.zeros((0, 2), np.int64)
    points = np.asarray(points, np.float64).reshape(-1, 2)
    cols, rows = np.floor(points[:, 0]).astype(np.int64), np.floor(points[:, 1]).astype(np.int64)
    bad = (cols < 0) | (cols >= W) | (rows < 0) | (rows >= H)
    if bad.any():
        raise Trace3DError(f"frame {frame!r}: {what} prompt point {tuple(points[bad][0])} lies outside the "
                           f"{W}x{H} image.")
    return np.stack([rows, cols], axis=1)


def prompt_candidates(hierarchy: np.ndarray, positive: np.ndarray, negative: np.ndarray,
                      fit: np.ndarray | None = None, fit_share: float = 0.5) -> list[np.ndarray]:
    """Per level, the union of the regions under the positive points that hold no negative point.

    Args:
        hierarchy: [K, H, W] nested label maps.
        positive: [P, 2] int (row, col), P >= 1; negative: [Q, 2] int (row, col).
        fit: [H, W] bool, optional: also take every region with at least ``fit_share`` of its
            pixels inside ``fit``.
    Returns:
        K masks [H, W] bool (finest first); a level where every positive region holds a negative
        (and no region fits) gives the positive pixels alone.
    """
    out = []
    for labels in hierarchy:
        pos = set(labels[positive[:, 0], positive[:, 1]].tolist())
        if fit is not None:
            n = int(labels.max()) + 1
            inside = np.bincount(labels[fit], minlength=n)
            area = np.bincount(labels.ravel(), minlength=n)
            pos |= set(np.nonzero(inside >= fit_share * area)[0].tolist())
        neg = set(labels[negative[:, 0], negative[:, 1]].tolist()) if len(negative) else set()
        keep = sorted(pos - neg)
        mask = np.isin(labels, keep) if keep else np.zeros(labels.shape, bool)
        if not keep:
            mask[positive[:, 0], positive[:, 1]] = True
        out.append(mask)
    return out


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 0.0


def grabcut_refine(image: np.ndarray, candidate: np.ndarray, positive: np.ndarray, negative: np.ndarray,
                   iterations: int = 3, margin: float = 0.05) -> np.ndarray:
    """GrabCut seeded by a candidate mask and the prompts (:class:`GraphPromptParams`).

    Args:
        image: [H, W, 3] uint8 RGB; candidate: [H, W] bool; positive, negative: [*, 2] int (row, col).
    Returns:
        [H, W] bool; the candidate itself when GrabCut drops a positive point or returns nothing.
    """
    import cv2

    H, W = candidate.shape
    radius = max(1, int(round(margin * np.hypot(H, W))))
    near = cv2.dilate(candidate.astype(np.uint8), cv2.getStructuringElement(
        cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))).astype(bool)
    init = np.full((H, W), cv2.GC_BGD, np.uint8)
    init[near] = cv2.GC_PR_BGD
    init[candidate] = cv2.GC_PR_FGD
    init[positive[:, 0], positive[:, 1]] = cv2.GC_FGD
    if len(negative):
        init[negative[:, 0], negative[:, 1]] = cv2.GC_BGD
    if not ((init == cv2.GC_BGD) | (init == cv2.GC_PR_BGD)).any():
        return candidate.copy()  # nothing to learn a background from
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    bgr = np.ascontiguousarray(np.asarray(image, np.uint8)[..., ::-1])
    cv2.setRNGSeed(0)
    cv2.grabCut(bgr, init, None, bgd, fgd, int(iterations), cv2.GC_INIT_WITH_MASK)
    out = (init == cv2.GC_FGD) | (init == cv2.GC_PR_FGD)
    if not out[positive[:, 0], positive[:, 1]].all():
        return candidate.copy()
    return out


class GraphPromptSegmenter:
    """Point prompts answered from the image's nested graph segmentation; reads no ground truth.

    ``segment(frame, points, rng, like=None, negatives=None)`` -> [H, W] bool (module docstring).
    The hierarchies of the last 16 frames are cached.
    """

    def __init__(self, scene: Scene, params: GraphPromptParams | Mapping | None = None):
        self.scene = scene
        self.params = params if isinstance(params, GraphPromptParams) else from_mapping(
            GraphPromptParams, params, "graph prompt params")
        self.graph = from_mapping(GraphParams, self.params.graph, "graph prompt params.graph")
        self._cache: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def view(self, frame: str) -> tuple[np.ndarray, np.ndarray]:
        """The frame's RGB image [H, W, 3] uint8 and nested hierarchy [K, H, W] int32."""
        if frame not in self._cache:
            try:
                self.scene.camera(frame)
            except KeyError:
                raise Trace3DError(f"{self.scene.root / 'cameras.json'}: no frame named {frame!r}.") from None
            if len(self._cache) >= 16:
                self._cache.pop(next(iter(self._cache)))
            image = self.scene.image(frame)
            self._cache[frame] = (image, graph_hierarchy(image, self.graph))
        return self._cache[frame]

    def segment(self, frame: str, points: np.ndarray, rng: np.random.Generator | None = None,
                like: np.ndarray | None = None, negatives: np.ndarray | None = None) -> np.ndarray:
        """[H, W] bool mask of the object under the positive points ``points`` [P, 2] (x, y).

        Args:
            points: [P, 2] positive (x, y) pixel coordinates (pixel centres at +0.5), P >= 1.
            rng: unused (the answer is deterministic); kept for the prompt-source interface.
            like: [H, W] bool, optional: take the candidate closest (IoU) to it.
            negatives: [Q, 2] negative (x, y) points, optional.
        """
        image, hierarchy = self.view(frame)
        H, W = hierarchy.shape[1:]
        positive = _pixels(points, H, W, "positive", frame)
        if len(positive) == 0:
            raise Trace3DError(f"graph prompt segmenter: no positive point prompts for frame {frame!r}.")
        negative = _pixels(negatives, H, W, "negative", frame)
        if like is not None:
            like = np.asarray(like, bool)
            if like.shape != (H, W):
                raise Trace3DError(f"frame {frame!r}: the `like` mask has shape {like.shape}, not {(H, W)}.")
        fit = like if (like is not None and self.params.select == "fit") else None
        cands = prompt_candidates(hierarchy, positive, negative, fit, self.params.fit_share)
        if like is not None:
            scores = [_iou(c, like) for c in cands]
            mask = cands[int(np.argmax(scores))]  # first maximum: the finer level on ties
        else:
            mask = cands[-1]
            for k, labels in enumerate(hierarchy):
                pos = np.unique(labels[positive[:, 0], positive[:, 1]])
                neg = labels[negative[:, 0], negative[:, 1]] if len(negative) else np.zeros(0, labels.dtype)
                if len(pos) == 1 and not np.isin(pos, neg).any():
                    mask = cands[k]
                    break
        if self.params.refine == "grabcut":
            mask = grabcut_refine(image, mask, positive, negative, self.params.grabcut_iterations,
                                  self.params.grabcut_margin)
        return mask.copy()

    def settings(self) -> dict:
        from ..params import to_dict

        return {"source": "graph", **to_dict(self.params)}
