"""Ground truth of the evaluation: the evaluated objects, their masks per view, which views count,
and the query (reference view + mask) that stands for each object.

An object's mask in a view is the set of pixels whose leaf id (``instances/<frame>.png``) has the
object as itself or an ancestor in ``objects.json`` (a table's mask is its top and legs).

Occlusion (the supplementary filters "test views where the objects are occluded"): a boundary pixel
of the object's mask (a mask pixel with a 4-neighbour outside it) is occluded when such an outside
neighbour is closer to the camera by more than ``occlusion_depth_ratio`` of the object's depth at
that pixel (ground-truth depth maps); the view is occluded when more than
``max_occluded_fraction`` of the boundary is. Contact (a lamp standing on a table, the floor at a
chair's feet) changes depth by a few centimetres and does not count; a book in front of the lamp
does. Scenes without depth maps have no occlusion test (every view is "not occluded").
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..errors import SceneFormatError
from ..lifting import ObjectQuery
from ..scene import Camera, ObjectTable, Scene
from .params import EvaluateParams

log = logging.getLogger(__name__)


def membership(table: ObjectTable, object_id: int) -> np.ndarray:
    """[max_id + 1] bool: leaf ids that are ``object_id`` or lie below it in the hierarchy."""
    max_id = max((o.id for o in table), default=0)
    member = np.zeros(max_id + 1, bool)
    for o in table:
        current = o
        while True:
            if current.id == object_id:
                member[o.id] = True
                break
            if current.parent is None:
                break
            current = table.by_id[current.parent]
    return member


def object_mask(instances: np.ndarray, member: np.ndarray) -> np.ndarray:
    """[H, W] bool mask of an object from a leaf-id map [H, W] and its :func:`membership` table."""
    ids = instances.astype(np.int64)
    inside = ids < len(member)
    out = np.zeros(ids.shape, bool)
    out[inside] = member[ids[inside]]
    return out


def _leaf_ids(instances: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """(ids [H, W], ids < size) of a leaf-id map: what :func:`object_mask` computes per object,
    computed once per view. An unsigned map of up to 32 bits (the PNGs' uint16) is kept as it is (the
    same comparisons, indices and counts as its int64 copy, which took 8 bytes per pixel of every view
    for the evaluation's length); any other map becomes int64."""
    ids = instances if instances.dtype.kind == "u" and instances.dtype.itemsize <= 4 else instances.astype(np.int64)
    return ids, ids < size


def _mask_from_ids(ids: np.ndarray, inside: np.ndarray, member: np.ndarray) -> np.ndarray:
    """:func:`object_mask` from :func:`_leaf_ids` (the same mask)."""
    out = np.zeros(ids.shape, bool)
    out[inside] = member[ids[inside]]
    return out


def occluded_fraction(mask: np.ndarray, depth: np.ndarray, ratio: float) -> float:
    """Share of ``mask``'s boundary pixels that have a closer outside 4-neighbour.

    Args:
        mask: [H, W] bool, non-empty.
        depth: [H, W] ground-truth depth (0 = invalid: never occludes, never occluded).
        ratio: relative depth step that counts as "in front".
    """
    h, w = mask.shape
    occluded = np.zeros_like(mask)
    boundary = np.zeros_like(mask)
    for dy, dx in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        ys = slice(max(0, -dy), h - max(0, dy))
        yn = slice(max(0, dy), h - max(0, -dy))
        xs = slice(max(0, -dx), w - max(0, dx))
        xn = slice(max(0, dx), w - max(0, -dx))
        here, there = mask[ys, xs], mask[yn, xn]
        edge = here & ~there
        boundary[ys, xs] |= edge
        d_here, d_there = depth[ys, xs], depth[yn, xn]
        closer = edge & (d_here > 0) & (d_there > 0) & (d_there < d_here * (1.0 - ratio))
        occluded[ys, xs] |= closer
    count = int(boundary.sum())
    return float(occluded.sum()) / count if count else 0.0


def touches_border(mask: np.ndarray) -> bool:
    return bool(mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any())


@dataclass
class ViewInfo:
    """One object in one view."""

    frame: str
    split: str
    pixels: int
    occluded: float | None  # share of the boundary that is occluded (None: no depth maps)
    border: bool  # the mask touches the image border

    def is_occluded(self, p: EvaluateParams) -> bool:
        return self.occluded is not None and self.occluded > p.max_occluded_fraction

    def to_json(self) -> dict:
        return {"frame": self.frame, "split": self.split, "pixels": self.pixels,
                "occluded_fraction": None if self.occluded is None else round(self.occluded, 4),
                "border": self.border}


class GroundTruth:
    """Masks and per-view facts of the evaluated objects of one scene.

    ``cameras`` are the cameras the fitted scene lives with (the poses step's, same frame names).
    """

    def __init__(self, scene: Scene, cameras: Sequence[Camera], params: EvaluateParams):
        if scene.objects is None or not scene.has_instances:
            raise SceneFormatError(f"{scene.root}: evaluation needs ground truth (objects.json and instances/), "
                                   f"which this scene lacks.")
        self.scene = scene
        self.params = params
        self.cameras = list(cameras)
        ids = list(params.objects) if params.objects is not None else scene.objects.evaluated_ids()
        unknown = [i for i in ids if i not in scene.objects.by_id]
        if unknown:
            where = "evaluate params.objects" if params.objects is not None else f"{scene.root / 'objects.json'}"
            raise SceneFormatError(f"{where}: object ids {unknown[:5]} are not objects of the scene {scene.root} "
                                   f"(its objects.json lists {len(scene.objects.by_id)}); use ids from that file.")
        self.object_ids = sorted(ids)
        self.members = {oid: membership(scene.objects, oid) for oid in self.object_ids}
        self.has_depth = scene.has_depth
        self.info: dict[int, list[ViewInfo]] = {oid: [] for oid in self.object_ids}
        self._instances: dict[str, np.ndarray] = {}
        self._ids: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        size = len(next(iter(self.members.values()))) if self.members else 0
        for cam in self.cameras:
            instances = self._instances[cam.name] = scene.instances(cam.name)
            ids, inside = self._ids[cam.name] = _leaf_ids(instances, size)
            # pixels per leaf id: an object's pixel count without its mask (most objects miss most views)
            leaves = ids[inside]
            counts = np.bincount(leaves, minlength=size) if not leaves.size or leaves.min() >= 0 else None
            depth = scene.depth(cam.name) if self.has_depth else None
            for oid in self.object_ids:
                mask = None
                if counts is not None:
                    pixels = int(counts[self.members[oid]].sum())
                else:  # negative ids (a signed map): count the mask itself, as object_mask indexes them
                    mask = _mask_from_ids(ids, inside, self.members[oid])
                    pixels = int(mask.sum())
                occ = None
                border = False
                if pixels:
                    if mask is None:
                        mask = _mask_from_ids(ids, inside, self.members[oid])
                    border = touches_border(mask)
                    if depth is not None:
                        occ = occluded_fraction(mask, depth, params.occlusion_depth_ratio)
                self.info[oid].append(ViewInfo(cam.name, cam.split, pixels, occ, border))

    def instances(self, frame: str) -> np.ndarray:
        """[H, W] leaf ids of ``frame`` (``instances/<frame>.png``)."""
        return self._instances[frame]

    def mask(self, object_id: int, frame: str) -> np.ndarray:
        """[H, W] bool ground-truth mask of ``object_id`` in ``frame``."""
        ids, inside = self._ids[frame]
        return _mask_from_ids(ids, inside, self.members[object_id])

    def name(self, object_id: int) -> str:
        return self.scene.objects.by_id[object_id].name

    # --- which views count ---------------------------------------------------------------------
    def _scored(self, v: ViewInfo) -> bool:
        return (self.params.views == "all" or v.split == "test") and v.pixels >= self.params.min_pixels

    def extraction_views(self, object_id: int) -> list[str]:
        """Views scored for 3D extraction: scored split, >= min_pixels visible, not occluded."""
        return [v.frame for v in self.info[object_id] if self._scored(v) and not v.is_occluded(self.params)]

    def nvs_views(self, object_id: int) -> list[str]:
        """Views scored for novel-view segmentation (occluded ones too unless ``skip_occluded_nvs``)."""
        return [v.frame for v in self.info[object_id]
                if self._scored(v) and not (self.params.skip_occluded_nvs and v.is_occluded(self.params))]

    # --- the query -----------------------------------------------------------------------------
    def reference(self, object_id: int) -> str | None:
        """The training view the object is queried from (None: no training view shows it with
        ``min_pixels``). Most visible pixels wins (ties: the earlier frame); under
        ``largest_unoccluded`` views where it is occluded or cut by the border come last."""
        candidates = [v for v in self.info[object_id] if v.split == "train" and v.pixels >= self.params.min_pixels]
        if not candidates:
            return None
        if self.params.reference == "largest_unoccluded":
            clean = [v for v in candidates if not v.is_occluded(self.params) and not v.border]
            candidates = clean or candidates
        best = max(candidates, key=lambda v: (v.pixels, -self.cameras.index(self.camera(v.frame))))
        return best.frame

    def camera(self, frame: str) -> Camera:
        for cam in self.cameras:
            if cam.name == frame:
                return cam
        raise KeyError(frame)

    def query(self, object_id: int) -> ObjectQuery | None:
        frame = self.reference(object_id)
        if frame is None:
            return None
        return ObjectQuery(reference=frame, mask=self.mask(object_id, frame), object_id=object_id)
