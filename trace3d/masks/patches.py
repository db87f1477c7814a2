"""Primitive patches: overlap all masks of a view into disjoint patches and keep their hierarchy.

Paper, Sec. 3.2: the masks ``{M_j}`` of a view are overlapped and every distinct overlap region
becomes one disjoint *instance patch* ``P_j``; every later stage (GIT, merging, refinement,
lifting) works on these patches.  Supplementary "Scalability of patch merging": only patches that
lie in the same coarser mask are candidates for merging, so the hierarchy (which masks contain each
patch, coarse to fine) is kept beside the patch map.

Definition used here (one choice made where the paper is silent):

* A pixel's *signature* is the set of masks covering it.  Pixels covered by no mask get label 0.
* Connected regions (4-neighbourhood) of equal signature are the raw pieces.  A piece smaller than
  ``min_patch_pixels`` or thinner than ``min_patch_width`` everywhere (the slivers and rings left
  where slightly misaligned masks overlap) is absorbed into the largest
  (by area, ties to the lower piece number) 4-adjacent piece that shares at least one covering mask
  with it, i.e. lies inside a common coarser mask, provided that neighbour is bigger than the
  tiny piece itself (same order); otherwise the tiny piece stays (and may receive smaller ones).
  Pieces are numbered in raster order of their first pixel.
  Uncovered pixels are never absorbed and never absorb.
* ``split_disconnected=False`` (default): all pieces that end with the same signature form ONE
  patch, even when disconnected (SAM put them in exactly the same masks, e.g. an object cut in
  two by an occluder; the paper treats overlap regions, not components).  ``True``: every
  connected piece is its own patch.
* Patch ids are 1..P in raster order of their first pixel; the hierarchy lists, for every patch,
  its covering masks ordered coarse to fine (mask area descending, ties by mask index).

On-disk output of :func:`run_patches` (one folder per scene)::

    <frame>.png     uint16 [H, W] patch ids, 0 = covered by no mask
    <frame>.json    PatchHierarchy.to_json(): masks (index, area, score), patches (id, area, masks)
    patches.json    parameters and patches per view
    preview.png     contact sheet: image | masks | patches for a few views
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from skimage.measure import label as _label_regions
from tqdm import tqdm

from ..errors import SceneFormatError, Trace3DError
from ..io import write_json
from ..params import from_mapping, to_dict
from ..scene import Scene, read_u16, write_u16

log = logging.getLogger(__name__)

MAX_PATCHES = 65535  # the patch map is a 16-bit PNG


@dataclasses.dataclass
class PatchParams:
    """Parameters of the patch step.

    Attributes:
        min_patch_pixels: pieces with fewer pixels are absorbed into their largest neighbour inside
            a common coarser mask (0 disables).
        min_patch_width: pieces whose thickness (largest city-block distance from a pixel to the
            outside of the piece) is below half of this are absorbed likewise; 3 absorbs slivers
            at most 2 pixels wide (<= 2 disables).
        split_disconnected: make every connected piece its own patch instead of one patch per
            distinct mask combination.
        preview_views: number of views shown in ``preview.png`` (0: no preview).
        max_depth: only the masks nested at most this deep are overlapped (:func:`nesting_depth`: 0 = the
            masks no other mask of the view contains, 1 = those directly inside one of them, ...); ``None``
            (default): every mask. 1 gives coarser patches from a deep hierarchy (the ``geometry``
            source's: docs/masks.md).
    """

    min_patch_pixels: int = 20
    min_patch_width: int = 3
    split_disconnected: bool = False
    preview_views: int = 4
    max_depth: int | None = None

    # each field's range: refused on input and in the config schema (trace3d.params.check_ranges)
    RANGES = {"min_patch_pixels": ">= 0", "min_patch_width": ">= 0", "preview_views": ">= 0", "max_depth": ">= 0"}

    def __post_init__(self) -> None:
        if self.min_patch_pixels < 0:
            raise ValueError(f"min_patch_pixels must be >= 0, got {self.min_patch_pixels}")
        if self.min_patch_width < 0:
            raise ValueError(f"min_patch_width must be >= 0, got {self.min_patch_width}")
        if self.preview_views < 0:
            raise ValueError(f"preview_views must be >= 0, got {self.preview_views}")
        if self.max_depth is not None and self.max_depth < 0:
            raise ValueError(f"max_depth must be >= 0 or null, got {self.max_depth}")


def nesting_depth(masks: np.ndarray) -> np.ndarray:
    """[M] int: how many other masks of the view contain each mask (a mask contains another when it covers
    all its pixels and is larger, or equal with a lower index: of two equal masks the later is inside the
    earlier). In a nested mask set (any two disjoint or nested) this is the mask's depth in the nesting
    tree; overlapping masks that do not contain each other do not count."""
    from .nested import pairwise_intersections

    inter = pairwise_intersections(np.asarray(masks, dtype=bool))  # [M, M] shared pixels, areas on the diagonal
    return _containers(inter, np.diag(inter), np.diag(inter))


def _containers(inter: np.ndarray, size: np.ndarray, area: np.ndarray) -> np.ndarray:
    """[M] int64: how many masks contain each mask. Mask i contains mask j when they share all of j's ``size``
    (``inter`` [M, M]: shared pixels, or shared patches) and i's ``area`` is larger, or equal with i < j."""
    index = np.arange(len(area))
    contains = (inter >= size[None, :]) & ((area[:, None] > area[None, :]) |
                                           ((area[:, None] == area[None, :]) & (index[:, None] < index[None, :])))
    return contains.sum(axis=0).astype(np.int64)


def _nesting_depth_reference(masks: np.ndarray) -> np.ndarray:
    """Loop twin of :func:`nesting_depth` (pixel sets compared pair by pair; used by the tests)."""
    sets = [frozenset(zip(*np.nonzero(m))) for m in masks]
    depth = []
    for j, inner in enumerate(sets):
        count = 0
        for i, outer in enumerate(sets):
            if i != j and inner <= outer and (len(outer) > len(inner) or i < j):
                count += 1
        depth.append(count)
    return np.array(depth, dtype=np.int64)


def select_masks(masks: np.ndarray, scores: np.ndarray, params: PatchParams) -> tuple[np.ndarray, np.ndarray]:
    """The masks (and scores) the patches are made of: those at most ``params.max_depth`` deep."""
    if params.max_depth is None or len(masks) == 0:
        return masks, scores
    keep = nesting_depth(masks) <= params.max_depth
    return masks[keep], scores[keep]


def coarser_patches(patch_map: np.ndarray, hierarchy: "PatchHierarchy", max_depth: int) -> np.ndarray:
    """[H, W] int64: the patches regrouped by their masks at most ``max_depth`` deep (:func:`nesting_depth`,
    read from the hierarchy: mask A contains mask B when every patch of B lies in A and A is larger, or
    equal with a lower index). Two patches share a label when the same such masks cover them; labels are
    1.. in raster order of their first pixel; a patch covered by none of them, and uncovered pixels, get 0.
    The contrastive lift's coarse block (``coarse_depth``) trains on these."""
    member = hierarchy.membership()  # [P + 1, M]
    inter = member.T.astype(np.int64) @ member.astype(np.int64)  # [M, M] shared patches, counts on the diagonal
    keep = _containers(inter, np.diag(inter), np.asarray(hierarchy.mask_areas, np.int64)) <= max_depth
    signature = member[:, keep]
    _, group = np.unique(signature, axis=0, return_inverse=True)
    group = group.reshape(-1) + 1
    group[~signature.any(axis=1)] = 0
    coarse = group[np.asarray(patch_map, np.int64)]
    values, first = np.unique(coarse, return_index=True)
    first, values = first[values > 0], values[values > 0]
    relabel = np.zeros(int(group.max(initial=0)) + 1, np.int64)
    relabel[values[np.argsort(first, kind="stable")]] = np.arange(1, len(values) + 1)
    return relabel[coarse]


# ----------------------------------------------------------------------------------------------
# Hierarchy
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass
class PatchHierarchy:
    """Which masks contain each patch of one view.

    Attributes:
        patch_masks: P lists; entry ``p - 1`` holds the indices of the masks containing patch ``p``,
            coarse to fine (mask area descending, ties by index).
        patch_areas: [P] int64 pixel count of each patch.
        mask_areas: [M] int64 pixel count of each input mask.
        mask_scores: [M] float32 score of each input mask.
        frame: the view's name ('' when unknown).
    """

    patch_masks: list[list[int]]
    patch_areas: np.ndarray
    mask_areas: np.ndarray
    mask_scores: np.ndarray
    frame: str = ""

    @property
    def num_patches(self) -> int:
        return len(self.patch_masks)

    @property
    def num_masks(self) -> int:
        return int(len(self.mask_areas))

    def containers(self, patch_id: int) -> list[int]:
        """Mask indices containing patch ``patch_id`` (1-based), coarse to fine."""
        if not 1 <= patch_id <= self.num_patches:
            raise IndexError(f"patch id {patch_id} is outside 1..{self.num_patches}")
        return list(self.patch_masks[patch_id - 1])

    def membership(self) -> np.ndarray:
        """[P + 1, M] bool: row p says which masks contain patch p (row 0, background, is empty)."""
        out = np.zeros((self.num_patches + 1, self.num_masks), dtype=bool)
        for p, masks in enumerate(self.patch_masks, start=1):
            out[p, masks] = True
        return out

    def patches_in_mask(self, mask_index: int) -> list[int]:
        """Patch ids (ascending) that lie inside mask ``mask_index``."""
        return [p for p, masks in enumerate(self.patch_masks, start=1) if mask_index in masks]

    def candidate_pairs(self) -> np.ndarray:
        """[K, 2] int64 patch-id pairs (a < b) that share at least one containing mask.

        These are the only pairs the merging stage needs to consider (paper supplementary,
        "Scalability of patch merging").
        """
        keys = []
        by_mask: dict[int, list[int]] = {}
        for p, masks in enumerate(self.patch_masks, start=1):
            for m in masks:
                by_mask.setdefault(m, []).append(p)
        for members in by_mask.values():
            if len(members) > 1:
                ids = np.asarray(members, dtype=np.int64)
                a, b = np.triu_indices(len(ids), k=1)
                keys.append(ids[a] * (self.num_patches + 1) + ids[b])
        if not keys:
            return np.zeros((0, 2), dtype=np.int64)
        unique = np.unique(np.concatenate(keys))
        return np.stack([unique // (self.num_patches + 1), unique % (self.num_patches + 1)], axis=1)

    def to_json(self) -> dict:
        return {
            "frame": self.frame,
            "num_masks": self.num_masks,
            "num_patches": self.num_patches,
            "masks": [
                {"index": i, "area": int(a), "score": float(s)}
                for i, (a, s) in enumerate(zip(self.mask_areas, self.mask_scores))
            ],
            "patches": [
                {"id": p, "area": int(a), "masks": [int(m) for m in masks]}
                for p, (a, masks) in enumerate(zip(self.patch_areas, self.patch_masks), start=1)
            ],
        }

    @classmethod
    def from_json(cls, data: Any, where: str) -> "PatchHierarchy":
        """Parse :meth:`to_json` output; raises SceneFormatError naming ``where`` if malformed."""
        try:
            masks = data["masks"]
            patches = data["patches"]
            mask_areas = np.array([int(m["area"]) for m in masks], dtype=np.int64)
            mask_scores = np.array([float(m["score"]) for m in masks], dtype=np.float32)
            ids = [int(p["id"]) for p in patches]
            patch_masks = [[int(m) for m in p["masks"]] for p in patches]
            patch_areas = np.array([int(p["area"]) for p in patches], dtype=np.int64)
            frame = str(data.get("frame", ""))
        except (KeyError, TypeError, ValueError) as exc:
            raise SceneFormatError(f"{where}: patch hierarchy is malformed ({exc!r}).") from exc
        if ids != list(range(1, len(ids) + 1)):
            raise SceneFormatError(f"{where}: patch ids must be 1..P in order.")
        if any(m < 0 or m >= len(mask_areas) for ms in patch_masks for m in ms):
            raise SceneFormatError(f"{where}: a patch names a mask index outside 0..{len(mask_areas) - 1}.")
        return cls(patch_masks, patch_areas, mask_areas, mask_scores, frame)


def read_patches(patches_dir: str | Path, frame: str) -> tuple[np.ndarray, PatchHierarchy]:
    """Read one view's patch map [H, W] uint16 and hierarchy from a patches folder."""
    patches_dir = Path(patches_dir)
    patch_map = read_u16(patches_dir / f"{frame}.png", "patch map")
    path = patches_dir / f"{frame}.json"
    if not path.is_file():
        raise SceneFormatError(f"{path}: patch hierarchy file is missing.")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise SceneFormatError(f"{path}: not valid JSON ({exc}).") from exc
    hierarchy = PatchHierarchy.from_json(data, str(path))
    if int(patch_map.max(initial=0)) > hierarchy.num_patches:
        raise SceneFormatError(
            f"{path}: the patch map uses id {int(patch_map.max())} but the hierarchy lists only "
            f"{hierarchy.num_patches} patches."
        )
    return patch_map, hierarchy


# ----------------------------------------------------------------------------------------------
# Fast (vectorised) implementation
# ----------------------------------------------------------------------------------------------


def _pixel_signatures(masks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Label every pixel by the set of masks covering it.

    Args:
        masks: [M, H, W] bool.
    Returns:
        signature_map [H, W] int64 (0 = covered by no mask) and signature_words [S, B] uint64
        (row s = membership bit-vector of signature s, bit k of word k // 64 for mask k; row 0 all
        zero; B = ceil(M / 64)).
    """
    M, H, W = masks.shape
    num_words = max((M + 63) // 64, 1)
    # byte b of a pixel holds masks 8b..8b+7; 8 little-endian bytes make one uint64 word
    planes = np.zeros((8 * num_words, H * W), dtype=np.uint8)
    flat = masks.reshape(M, H * W).view(np.uint8)
    for k in range(M):
        planes[k // 8] |= flat[k] << np.uint8(k % 8)
    words = np.ascontiguousarray(planes.T).view("<u8").astype(np.uint64)  # [H*W, num_words]
    if num_words == 1:
        unique, inverse = np.unique(words[:, 0], return_inverse=True)
        unique = unique[:, None]
    else:
        keys = words.view(np.dtype((np.void, 8 * num_words))).ravel()
        unique, inverse = np.unique(keys, return_inverse=True)
        unique = unique.view(np.uint64).reshape(-1, num_words)
    inverse = inverse.reshape(H, W).astype(np.int64)
    if unique[0].any():  # no uncovered pixel: the all-zero signature is absent, make room for it
        unique = np.concatenate([np.zeros((1, num_words), dtype=np.uint64), unique], axis=0)
        inverse += 1
    return inverse, unique


def _unpack_words(words: np.ndarray, count: int) -> np.ndarray:
    """[S, B] uint64 bit-vectors -> [S, count] bool."""
    k = np.arange(count)
    return ((words[:, k // 64] >> (k % 64).astype(np.uint64)) & np.uint64(1)).astype(bool)


def _piece_thickness(pieces: np.ndarray, num_pieces: int) -> np.ndarray:
    """[num_pieces + 1] int64: per piece, the largest city-block distance from one of its pixels to
    the nearest in-image pixel outside the piece (1 for a 1- or 2-pixel-wide sliver).

    Args:
        pieces: [H, W] piece labels (0 = uncovered, also a "piece" for this purpose).
    """
    H, W = pieces.shape
    edge = np.zeros((H, W), dtype=bool)
    horizontal = pieces[:, :-1] != pieces[:, 1:]
    vertical = pieces[:-1, :] != pieces[1:, :]
    edge[:, :-1] |= horizontal
    edge[:, 1:] |= horizontal
    edge[:-1, :] |= vertical
    edge[1:, :] |= vertical
    thickness = np.zeros(num_pieces + 1, dtype=np.int64)
    if not edge.any():
        thickness[:] = H + W  # a single piece: nothing outside it
        return thickness
    # distance to the nearest edge pixel; the nearest outside pixel is one step further
    dist = cv2.distanceTransform((~edge).astype(np.uint8), cv2.DIST_L1, 3).astype(np.int64) + 1
    np.maximum.at(thickness, pieces.ravel(), dist.ravel())
    return thickness


def _adjacent_pairs(pieces: np.ndarray) -> np.ndarray:
    """[E, 2] int64 unordered-once pairs (a < b) of distinct nonzero labels that are 4-adjacent."""
    num = int(pieces.max(initial=0)) + 1
    pairs = []
    for a, b in ((pieces[:, :-1], pieces[:, 1:]), (pieces[:-1, :], pieces[1:, :])):
        keep = (a != b) & (a > 0) & (b > 0)
        lo = np.minimum(a[keep], b[keep]).astype(np.int64)
        hi = np.maximum(a[keep], b[keep]).astype(np.int64)
        pairs.append(lo * num + hi)
    keys = np.unique(np.concatenate(pairs)) if pairs else np.zeros(0, dtype=np.int64)
    return np.stack([keys // num, keys % num], axis=1)


def masks_to_patches(
    masks: np.ndarray,
    min_patch_pixels: int = PatchParams.min_patch_pixels,
    *,
    min_patch_width: int = 0,
    scores: np.ndarray | None = None,
    split_disconnected: bool = False,
    frame: str = "",
) -> tuple[np.ndarray, PatchHierarchy]:
    """Overlap a view's masks into disjoint primitive patches (see the module docstring).

    Args:
        masks: [M, H, W] bool mask stack.
        min_patch_pixels: pieces smaller than this are absorbed (0: no absorption).
        min_patch_width: pieces with thickness * 2 < this are absorbed too (<= 2: never).
        scores: [M] mask scores (default all 1).
        split_disconnected: one patch per connected piece instead of per mask combination.
        frame: view name stored in the hierarchy.
    Returns:
        patch_map [H, W] uint16 (0 = no mask) and its :class:`PatchHierarchy`.
    """
    masks = np.asarray(masks)
    if masks.ndim != 3 or masks.dtype != bool:
        raise ValueError(f"masks must be a bool [M, H, W] stack, got {masks.dtype} {masks.shape}")
    M, H, W = masks.shape
    scores = np.ones(M, dtype=np.float32) if scores is None else np.asarray(scores, dtype=np.float32)
    if scores.shape != (M,):
        raise ValueError(f"scores must have shape [{M}], got {scores.shape}")

    signature_map, bits = _pixel_signatures(masks)
    # raw pieces: connected regions of equal signature (uncovered pixels stay 0)
    pieces = _label_regions(signature_map, background=0, connectivity=1).astype(np.int64)
    num_pieces = int(pieces.max(initial=0))
    # number the pieces in raster order of their first pixel (makes tie-breaking well defined)
    labels_seen, first_seen = np.unique(pieces.ravel(), return_index=True)
    keep = labels_seen > 0
    renumber = np.zeros(num_pieces + 1, dtype=np.int64)
    renumber[labels_seen[keep][np.argsort(first_seen[keep], kind="stable")]] = np.arange(1, num_pieces + 1)
    pieces = renumber[pieces]
    piece_signature = np.zeros(num_pieces + 1, dtype=np.int64)
    piece_signature[pieces.ravel()] = signature_map.ravel()
    piece_area = np.bincount(pieces.ravel(), minlength=num_pieces + 1)

    # tiny-piece absorption: each tiny piece points at its largest qualifying neighbour
    parent = np.arange(num_pieces + 1)
    if (min_patch_pixels > 0 or min_patch_width > 2) and num_pieces > 1:
        tiny = piece_area < min_patch_pixels
        if min_patch_width > 2:
            tiny |= 2 * _piece_thickness(pieces, num_pieces) < min_patch_width
        tiny[0] = False
        pairs = _adjacent_pairs(pieces)
        if tiny.any() and len(pairs):
            both = np.concatenate([pairs, pairs[:, ::-1]], axis=0)  # directed (small, neighbour)
            both = both[tiny[both[:, 0]]]
            shared = np.any(bits[piece_signature[both[:, 0]]] & bits[piece_signature[both[:, 1]]], axis=1)
            both = both[shared]
            if len(both):
                small, neighbour = both[:, 0], both[:, 1]
                # per small piece: maximum neighbour area, ties to the lowest neighbour number
                order = np.lexsort((-neighbour, piece_area[neighbour], small))
                small, neighbour = small[order], neighbour[order]
                last = np.r_[small[1:] != small[:-1], True]
                small, neighbour = small[last], neighbour[last]
                # only into a bigger piece: (area, -number) strictly increases along every chain,
                # so there are no cycles and pointer jumping terminates
                bigger = (piece_area[neighbour] > piece_area[small]) | (
                    (piece_area[neighbour] == piece_area[small]) & (neighbour < small)
                )
                parent[small[bigger]] = neighbour[bigger]
                while True:
                    jumped = parent[parent]
                    if np.array_equal(jumped, parent):
                        break
                    parent = jumped
    root = parent[pieces]  # [H, W]

    if split_disconnected:
        key = root
        key_signature = piece_signature  # indexed by root piece
    else:
        key = piece_signature[root]
        key_signature = np.arange(len(bits))
    flat = key.ravel()
    values, first = np.unique(flat, return_index=True)
    first_nonzero = values > 0
    values, first = values[first_nonzero], first[first_nonzero]
    order = np.argsort(first, kind="stable")  # raster order of first pixel
    values = values[order]
    if len(values) > MAX_PATCHES:
        raise Trace3DError(
            f"view {frame!r}: {len(values)} patches do not fit the 16-bit patch map (limit {MAX_PATCHES})."
        )
    relabel = np.zeros(int(flat.max(initial=0)) + 1, dtype=np.int64)
    relabel[values] = np.arange(1, len(values) + 1)
    patch_map = relabel[key].astype(np.uint16)

    mask_areas = masks.reshape(M, H * W).sum(axis=1).astype(np.int64)
    num_patches = len(values)
    patch_areas = np.bincount(patch_map.ravel(), minlength=num_patches + 1)[1:].astype(np.int64)
    patch_bits = bits[key_signature[values]]  # [P, B]
    member = _unpack_words(patch_bits, M)  # [P, M]
    coarse_to_fine = np.lexsort((np.arange(M), -mask_areas))  # mask indices, largest first
    patch_masks = [[int(m) for m in coarse_to_fine if row[m]] for row in member]
    hierarchy = PatchHierarchy(patch_masks, patch_areas, mask_areas, scores.copy(), frame)
    return patch_map, hierarchy


# ----------------------------------------------------------------------------------------------
# Slow reference twin (plain loops over pixels), used by the tests
# ----------------------------------------------------------------------------------------------


def _masks_to_patches_reference(
    masks: np.ndarray, min_patch_pixels: int, split_disconnected: bool = False, min_patch_width: int = 0
) -> tuple[np.ndarray, list[list[int]]]:
    """Obviously-correct loop version of :func:`masks_to_patches` (small inputs only).

    Returns:
        patch_map [H, W] uint16 and the per-patch container lists (coarse to fine).
    """
    M, H, W = masks.shape
    sig = [[tuple(int(m) for m in range(M) if masks[m, y, x]) for x in range(W)] for y in range(H)]
    # connected pieces of equal, non-empty signature (4-neighbourhood, BFS in raster order)
    piece = [[0] * W for _ in range(H)]
    piece_sig: list[tuple] = [()]
    piece_area = [0]
    for y in range(H):
        for x in range(W):
            if piece[y][x] or not sig[y][x]:
                continue
            pid = len(piece_sig)
            piece_sig.append(sig[y][x])
            piece_area.append(0)
            stack = [(y, x)]
            piece[y][x] = pid
            while stack:
                cy, cx = stack.pop()
                piece_area[pid] += 1
                for ny, nx in ((cy - 1, cx), (cy + 1, cx), (cy, cx - 1), (cy, cx + 1)):
                    if 0 <= ny < H and 0 <= nx < W and not piece[ny][nx] and sig[ny][nx] == sig[y][x]:
                        piece[ny][nx] = pid
                        stack.append((ny, nx))
    # neighbours
    neighbours: dict[int, set[int]] = {p: set() for p in range(1, len(piece_sig))}
    for y in range(H):
        for x in range(W):
            for ny, nx in ((y + 1, x), (y, x + 1)):
                if ny < H and nx < W:
                    a, b = piece[y][x], piece[ny][nx]
                    if a and b and a != b:
                        neighbours[a].add(b)
                        neighbours[b].add(a)
    # thickness: largest city-block distance from a pixel of the piece to a pixel outside it
    labels = np.array(piece)
    ys, xs = np.mgrid[0:H, 0:W]
    thickness = [0] * len(piece_sig)
    for y in range(H):
        for x in range(W):
            outside = labels != labels[y, x]
            d = int((np.abs(ys - y) + np.abs(xs - x))[outside].min()) if outside.any() else H + W
            thickness[labels[y, x]] = max(thickness[labels[y, x]], d)
    target = list(range(len(piece_sig)))
    for p in range(1, len(piece_sig)):
        thin = min_patch_width > 2 and 2 * thickness[p] < min_patch_width
        if piece_area[p] >= min_patch_pixels and not thin:
            continue
        best = None
        for n in sorted(neighbours[p]):
            if set(piece_sig[p]) & set(piece_sig[n]):
                if best is None or piece_area[n] > piece_area[best]:
                    best = n
        if best is not None and (piece_area[best], -best) > (piece_area[p], -p):
            target[p] = best

    def root_of(p: int) -> int:
        while target[p] != p:
            p = target[p]
        return p

    key_of_piece = {}
    for p in range(1, len(piece_sig)):
        r = root_of(p)
        key_of_piece[p] = r if split_disconnected else piece_sig[r]
    patch_ids: dict[Any, int] = {}
    patch_map = np.zeros((H, W), dtype=np.uint16)
    for y in range(H):
        for x in range(W):
            if piece[y][x]:
                k = key_of_piece[piece[y][x]]
                if k not in patch_ids:
                    patch_ids[k] = len(patch_ids) + 1
                patch_map[y, x] = patch_ids[k]
    areas = [int(masks[m].sum()) for m in range(M)]
    containers: list[list[int]] = [[] for _ in patch_ids]
    for k, pid in patch_ids.items():
        s = piece_sig[k] if split_disconnected else k
        containers[pid - 1] = sorted(s, key=lambda m: (-areas[m], m))
    return patch_map, containers


# ----------------------------------------------------------------------------------------------
# Pipeline step
# ----------------------------------------------------------------------------------------------


def run_patches(scene: Scene, masks_dir: Path, out_dir: Path, params: dict) -> None:
    """Compute patch maps and hierarchies for every frame of ``scene`` from ``masks_dir``.

    Writes ``out_dir/<frame>.png``, ``<frame>.json``, ``patches.json`` and ``preview.png``.
    """
    from .files import read_mask_npz

    p = from_mapping(PatchParams, params, "patches params")
    masks_dir, out_dir = Path(masks_dir), Path(out_dir)
    if not masks_dir.is_dir():
        raise SceneFormatError(f"{masks_dir}: masks folder does not exist (run the masks step first).")
    out_dir.mkdir(parents=True, exist_ok=True)
    per_view: dict[str, dict] = {}
    for cam in tqdm(scene.cameras, desc="patches", unit="view"):
        masks, scores = read_mask_npz(masks_dir / f"{cam.name}.npz", cam.height, cam.width)
        masks, scores = select_masks(masks, scores, p)
        patch_map, hierarchy = masks_to_patches(
            masks,
            p.min_patch_pixels,
            min_patch_width=p.min_patch_width,
            scores=scores,
            split_disconnected=p.split_disconnected,
            frame=cam.name,
        )
        write_u16(out_dir / f"{cam.name}.png", patch_map)
        write_json(out_dir / f"{cam.name}.json", hierarchy.to_json())
        per_view[cam.name] = {
            "masks": hierarchy.num_masks,
            "patches": hierarchy.num_patches,
            "covered_fraction": float((patch_map > 0).mean()),
        }
        log.debug("%s: %d masks -> %d patches", cam.name, hierarchy.num_masks, hierarchy.num_patches)
    counts = [v["patches"] for v in per_view.values()]
    summary = {
        "params": to_dict(p),
        "max_patches": int(max(counts, default=0)),
        "mean_patches": float(np.mean(counts)) if counts else 0.0,
        "views": per_view,
    }
    write_json(out_dir / "patches.json", summary)
    log.info("patches: %d views, %.1f patches per view (max %d)", len(counts), summary["mean_patches"],
             summary["max_patches"])
    if p.preview_views > 0:
        write_preview(scene, masks_dir, out_dir, out_dir / "preview.png", p.preview_views)


# ----------------------------------------------------------------------------------------------
# Contact sheet
# ----------------------------------------------------------------------------------------------


def write_preview(scene: Scene, masks_dir: Path, patches_dir: Path, path: Path, views: int) -> None:
    """Contact sheet (image | masks | patches) for ``views`` evenly spaced frames."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..io import atomic_file
    from ..preview import label_overlay, mask_overlay
    from .files import read_mask_npz

    cams = scene.cameras
    picks = sorted(set(np.linspace(0, len(cams) - 1, min(views, len(cams))).round().astype(int).tolist()))
    fig, axes = plt.subplots(len(picks), 3, figsize=(9, 2.6 * len(picks)), squeeze=False)
    for row, idx in enumerate(picks):
        cam = cams[idx]
        image = scene.image(cam.name)
        masks, _ = read_mask_npz(masks_dir / f"{cam.name}.npz", cam.height, cam.width)
        patch_map = read_u16(patches_dir / f"{cam.name}.png", "patch map")
        panels = (
            (image, f"{cam.name} ({cam.split})"),
            (mask_overlay(image, masks), f"{len(masks)} masks"),
            (label_overlay(image, patch_map), f"{int(patch_map.max(initial=0))} patches"),
        )
        for col, (panel, title) in enumerate(panels):
            axes[row, col].imshow(panel)
            axes[row, col].set_title(title, fontsize=8)
            axes[row, col].axis("off")
    fig.tight_layout()
    with atomic_file(path) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    plt.close(fig)
