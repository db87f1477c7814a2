"""Parameters of the ``evaluate`` step and its two protocols."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

PROTOCOLS = ("standard", "official")

# what each protocol fills in for the settings left at None
PROTOCOL_VALUES = {
    "standard": {"views": "test", "min_pixels": 50, "skip_occluded_nvs": False, "reference": "largest_unoccluded",
                 "accuracy": "accuracy", "single_point": True, "panoptic": True, "segment": True, "click": True},
    "official": {"views": "all", "min_pixels": 200, "skip_occluded_nvs": True, "reference": "largest",
                 "accuracy": "precision", "single_point": False, "panoptic": False, "segment": False,
                 "click": False},
}


@dataclass
class EvaluateParams:
    """Parameters of the ``evaluate`` step (``None`` takes the protocol's value).

    protocol: ``standard`` (test views only, mAcc = pixel accuracy (TP+TN)/pixels as SA3D and
        GaussianCut define it) or ``official`` (as the released Trace3D code evaluates: every view
        containing the object, at least 200 px, occluded views skipped for both tasks, reference =
        largest ground-truth area, its "mAcc" is precision TP/(TP+FP)).
    views: which views are scored: ``test`` or ``all`` (train and test).
    min_pixels: a view counts for an object when at least this many of its pixels are visible.
    skip_occluded_nvs: also skip occluded views in the novel-view segmentation (extraction always
        skips them: the object rendered alone shows what an occluder hides).
    occlusion_depth_ratio: a boundary pixel of the object is occluded when a 4-neighbour outside the
        object is closer to the camera by more than this fraction of the object's depth there.
    max_occluded_fraction: a view is "not occluded" when at most this share of the object's
        boundary pixels is occluded (needs the scene's depth maps; without them no view is occluded).
    reference: ``largest`` (the training view with the most visible pixels of the object) or
        ``largest_unoccluded`` (the same among views where the object is neither occluded nor cut by
        the image border; the largest view when there is none).
    accuracy: ``accuracy`` ((TP+TN)/pixels) or ``precision`` (TP/(TP+FP)) for the mAcc column.
    alpha_eps: the extracted object's predicted mask is where its render on black has alpha above
        this (0.5/255: where a white object would be non-zero in an 8-bit render).
    psnr_margin: pixels by which the ground-truth box grows for the PSNR.
    objects: object ids to evaluate instead of ``objects.json``'s evaluated ones.
    picture_objects: objects shown in ``pictures.png``.
    object_files: write ``objects/<id>.ply`` and ``objects/<id>.png``.
    turntable_views, turntable_size: views (and their side in pixels) of ``objects/<id>.png``.
    near: near plane of every render.
    single_point: also score both tasks with the lifted scene queried by ONE query point
        (``max_queries: 1`` of the query; methods without query points skip it), written to
        ``metrics.json["single_point"]`` (standard: on; official: off).
    panoptic: scene-level instance segmentation from the lifted features alone, scored as PQ^scene
        over the scored views (:mod:`trace3d.evaluation.panoptic`; methods without lifted features skip
        it), written to ``metrics.json["panoptic"]`` (standard: on; official: off).
    panoptic_samples: rendered training-view pixels drawn for the clustering.
    panoptic_min_share: the smallest cluster's share of those samples (HDBSCAN's min_cluster_size =
        min_samples = ceil(samples * share) = 8; 0.001 = 19 px of a 160x120 view on average; chosen on
        exact object labels only, docs/evaluation.md).
    panoptic_seed: seed of the pixel draw.
    segment: PQ^scene of the ``trace3d segment`` objects (the lifted features over the Gaussians' 3D
        kNN graph, default :class:`~trace3d.segment.SegmentParams`; no ground truth until the score),
        written to ``metrics.json["segment"]`` (standard: on; official: off).
    click: click-extract IoU: one click per object at the deepest pixel of its reference mask, the
        object selected by ``trace3d extract``'s ``click_selection``, scored at its NVS views
        (:mod:`trace3d.evaluation.click`), written to ``metrics.json["click"]`` (standard: on; official: off).
    click_selection: ``features`` (similar features linked in 3D to the click), ``segment`` (the
        segment the click falls in) or ``region`` (the 2D region grown from the click, queried as a
        reference mask: the extract step before issue 48); the other settings are
        :class:`~trace3d.extract.ExtractParams`'.
    """

    protocol: Literal["standard", "official"] = "standard"
    views: Literal["test", "all"] | None = None
    min_pixels: int | None = None
    skip_occluded_nvs: bool | None = None
    occlusion_depth_ratio: float = 0.05
    max_occluded_fraction: float = 0.05
    reference: Literal["largest", "largest_unoccluded"] | None = None
    accuracy: Literal["accuracy", "precision"] | None = None
    alpha_eps: float = 0.5 / 255.0
    psnr_margin: int = 10
    objects: list[int] | None = None
    picture_objects: int = 4
    object_files: bool = True
    turntable_views: int = 8
    turntable_size: int = 96
    near: float = 0.01
    single_point: bool | None = None
    panoptic: bool | None = None
    panoptic_samples: int = 8000
    panoptic_min_share: float = 0.001
    panoptic_seed: int = 0
    segment: bool | None = None
    click: bool | None = None
    click_selection: Literal["features", "segment", "region"] = "features"

    # each field's range: refused on input and in the config schema (trace3d.params.check_ranges)
    RANGES = {"panoptic_samples": ">= 2", "panoptic_min_share": "(0, 1)", "min_pixels": ">= 1",
              "max_occluded_fraction": "[0, 1]", "occlusion_depth_ratio": ">= 0", "alpha_eps": ">= 0",
              "psnr_margin": ">= 0", "turntable_views": ">= 1", "turntable_size": ">= 8", "picture_objects": ">= 0",
              "panoptic_seed": ">= 0"}

    def __post_init__(self) -> None:
        for key, value in PROTOCOL_VALUES[self.protocol].items():
            if getattr(self, key) is None:
                setattr(self, key, value)
        if self.panoptic_samples < 2 or not 0.0 < self.panoptic_min_share < 1.0:
            raise ValueError(f"panoptic_samples must be at least 2 and panoptic_min_share in (0, 1), got "
                             f"{self.panoptic_samples}, {self.panoptic_min_share}.")
        if self.min_pixels < 1:
            raise ValueError(f"min_pixels must be at least 1, got {self.min_pixels}.")
        if not 0.0 <= self.max_occluded_fraction <= 1.0:
            raise ValueError(f"max_occluded_fraction must lie in [0, 1], got {self.max_occluded_fraction}.")
        if self.occlusion_depth_ratio < 0 or self.alpha_eps < 0 or self.psnr_margin < 0:
            raise ValueError("occlusion_depth_ratio, alpha_eps and psnr_margin must be non-negative.")
        if self.turntable_views < 1 or self.turntable_size < 8 or self.picture_objects < 0:
            raise ValueError("turntable_views >= 1, turntable_size >= 8 and picture_objects >= 0 are required.")
