"""The ``poses`` step's parameters (:mod:`trace3d.poses`)."""

from __future__ import annotations

import dataclasses
from typing import Literal

from ..params import from_mapping


@dataclasses.dataclass
class PosesParams:
    """Parameters of the ``poses`` step (COLMAP's defaults where COLMAP has one, except
    ``sift_peak_threshold``).

    Attributes:
        mode: "colmap" (run SfM) or "dataset" (use the scene's cameras; see ``dataset_points``).
        matcher: "exhaustive" (every pair; small scenes) or "sequential" (video-like captures, frames
            matched to their ``sequential_overlap`` successors in name order).
        sequential_overlap: number of following frames each frame is matched with (sequential).
        sequential_quadratic_overlap: also match frames 2^k apart (COLMAP's quadratic overlap).
        single_camera: one shared camera for all frames; None = decide from the scene (shared when
            every frame has the same size and, with known intrinsics, the same K).
        known_intrinsics: start from the scene's K (its cameras.json) instead of COLMAP's guess.
        refine_intrinsics: let bundle adjustment refine focal lengths and principal point (with
            known intrinsics; estimated intrinsics always refine the focal lengths).
        max_num_features: SIFT features per image.
        max_image_size: images larger than this are downscaled for extraction.
        sift_peak_threshold: SIFT detection threshold.  COLMAP's default is 0.02 / 3 = 0.0067, made
            for megapixel photos; 0.003 finds ~15 % more features in the small (160 x 120) benchmark
            images and removed the pose outliers measured on the default rooms (room 3: worst
            camera-centre error 17.8 % -> 2.1 % of the camera diameter, worst rotation 4.5 -> 0.6
            degrees).  On large images the ``max_num_features`` strongest are kept either way.
        domain_size_pooling: DSP-SIFT descriptors (more robust matching, slower extraction).
        guided_matching: re-match guided by the verified two-view geometry (more inliers, slower).
        init_min_num_inliers: verified matches needed by the initial image pair.
        min_num_matches: verified matches for a pair to enter the view graph.
        min_registered_fraction: fraction of the scene's frames that must register (1 = all).
        min_num_points: fewer triangulated points than this is a degenerate reconstruction.
        align_to_scene: map the reconstruction into the frame of the scene's poses; None = whenever
            the scene has reference poses.
        align_method: "poses" (rotation from the camera orientations, scale and translation from
            the centres) or "centers" (Umeyama on the centres alone); see
            :func:`trace3d.pointcloud.align_cameras`.
        dataset_points: (dataset mode) where points3D.ply comes from: "depth" (back-project the
            scene's depth maps), "triangulate" (SIFT matches triangulated with the scene's poses and
            intrinsics, poses kept fixed), "none"; "auto" = depth when the scene has depth/, else
            triangulate.
        depth_points: (dataset mode) total number of depth pixels back-projected into points.
        num_threads: CPU threads for pycolmap (-1 = all cores of ``trace3d --threads``). 1 by default:
            with more threads COLMAP's poses are not reproducible (two runs of the same room with 2
            threads gave cameras differing at about 1e-5 relative; with one, identical files), and
            every later step inherits the difference. More threads are faster on large captures at
            that price.
        seed: seed of pycolmap's random number generator (RANSAC, mapping) and of point sampling.
        colmap_log_level: verbosity of pycolmap's own log (written to stderr, the step log).
    """

    mode: Literal["colmap", "dataset"] = "colmap"
    matcher: Literal["exhaustive", "sequential"] = "exhaustive"
    sequential_overlap: int = 10
    sequential_quadratic_overlap: bool = True
    single_camera: bool | None = None
    known_intrinsics: bool = True
    refine_intrinsics: bool = False
    max_num_features: int = 8192
    max_image_size: int = 3200
    sift_peak_threshold: float = 0.003
    domain_size_pooling: bool = False
    guided_matching: bool = False
    init_min_num_inliers: int = 100
    min_num_matches: int = 15
    min_registered_fraction: float = 1.0
    min_num_points: int = 100
    align_to_scene: bool | None = None
    align_method: Literal["poses", "centers"] = "poses"
    dataset_points: Literal["auto", "depth", "triangulate", "none"] = "auto"
    depth_points: int = 100_000
    num_threads: int = 1
    seed: int = 0
    colmap_log_level: Literal["info", "warning", "error"] = "info"

    # each field's range: refused on input and in the config schema (trace3d.params.check_ranges)
    RANGES = {"min_registered_fraction": "(0, 1]", "sequential_overlap": ">= 1", "max_num_features": ">= 1",
              "max_image_size": ">= 1", "init_min_num_inliers": ">= 1", "min_num_matches": ">= 1",
              "sift_peak_threshold": "> 0", "min_num_points": ">= 0", "depth_points": ">= 0",
              "num_threads": "-1 | >= 1", "seed": ">= 0"}

    def __post_init__(self) -> None:
        if not 0.0 < self.min_registered_fraction <= 1.0:
            raise ValueError(f"min_registered_fraction must be in (0, 1], got {self.min_registered_fraction}")
        for name in ("sequential_overlap", "max_num_features", "max_image_size", "init_min_num_inliers",
                     "min_num_matches"):  # fmt: skip
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.sift_peak_threshold <= 0:
            raise ValueError(f"sift_peak_threshold must be > 0, got {self.sift_peak_threshold}")
        if self.min_num_points < 0 or self.depth_points < 0:
            raise ValueError("min_num_points and depth_points must be >= 0")
        if self.num_threads == 0 or self.num_threads < -1:
            raise ValueError(f"num_threads must be -1 (all cores) or >= 1, got {self.num_threads}")


def params_from(values: dict | None) -> PosesParams:
    """Parse a raw parameter mapping (config / ``--params``) into :class:`PosesParams`."""
    return from_mapping(PosesParams, values, "poses params")
