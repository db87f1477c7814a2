"""Gaussian Instance Tracing over all training views (paper Sec. 3.2; the ``trace`` step).

For every training view the view's label map (patch map, or a consistent instance map) is traced
through the fitted scene with :func:`trace3d.render.trace`: W_i^v[j] = the summed blending weight
of Gaussian i over the pixels of label j in view v (or, under the ``official`` preset, the number
of such pixels, as the released code counts). As the supplementary ("Scalability of GIT") does, the
[N, T] matrix of one view is reduced at once and only [N, L] arrays are kept:

    label       [N, L] int32    argmax label of Gaussian i in view v (-1: no weight in the view)
    prob        [N, L] float32  max_j W_i^v[j] / sum_j W_i^v[j] (0 where not seen)
    visibility  [N, L] float32  sum_j W_i^v[j]: total weight (or pixel count) in the view

``git.npz`` holds these plus ``frames`` [L] and ``num_labels`` [L]. N x T x L is never held.
"""

from __future__ import annotations

import logging
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Sequence

import numpy as np
import torch
from tqdm import tqdm

from ..tooling.compiling import track as track_compile_time
from ..errors import SceneFormatError
from ..gaussians import GaussianModel
from ..scene import Camera

log = logging.getLogger(__name__)

PRESETS = ("paper", "official")


class _LabelTable:
    """The shape of a GIT table with a ``label`` array [N, L] (N Gaussians, L views)."""

    label: np.ndarray

    @property
    def num_gaussians(self) -> int:
        return int(self.label.shape[0])

    @property
    def num_views(self) -> int:
        return int(self.label.shape[1])


@dataclass
class GITStats(_LabelTable):
    """Per-view argmax reduction of the GIT weights (see the module docstring for the shapes)."""

    label: np.ndarray  # [N, L] int32
    prob: np.ndarray  # [N, L] float32
    visibility: np.ndarray  # [N, L] float32
    frames: list[str]
    num_labels: np.ndarray  # [L] int64

    def visible(self, min_visibility: float) -> np.ndarray:
        """[N, L] bool: Gaussian i sees view v (its visibility exceeds ``min_visibility``)."""
        return (self.visibility > min_visibility) & (self.label >= 0)

    def save(self, path: str | Path) -> None:
        np.savez_compressed(path, label=self.label, prob=self.prob, visibility=self.visibility,
                            frames=np.asarray(self.frames), num_labels=self.num_labels)

    @classmethod
    def load(cls, path: str | Path) -> "GITStats":
        path = Path(path)
        if not path.is_file():
            raise SceneFormatError(f"{path}: GIT statistics file is missing.")
        try:
            with np.load(path) as data:
                out = cls(label=data["label"], prob=data["prob"], visibility=data["visibility"],
                          frames=[str(f) for f in data["frames"]], num_labels=data["num_labels"])
        except (KeyError, ValueError, OSError) as exc:
            raise SceneFormatError(f"{path}: not a GIT statistics file ({exc}).") from exc
        n, views = out.label.shape
        if out.prob.shape != (n, views) or out.visibility.shape != (n, views) or len(out.frames) != views:
            raise SceneFormatError(f"{path}: GIT arrays disagree in shape ({out.label.shape}, {out.prob.shape}, "
                                   f"{out.visibility.shape}, {len(out.frames)} frames).")
        return out

    @staticmethod
    def load_frames(path: str | Path) -> list[str]:
        """The traced views' names of a ``git.npz``, without reading its [N, L] arrays."""
        path = Path(path)
        if not path.is_file():
            raise SceneFormatError(f"{path}: GIT statistics file is missing.")
        try:
            with np.load(path) as data:
                return [str(f) for f in data["frames"]]
        except (KeyError, ValueError, OSError) as exc:
            raise SceneFormatError(f"{path}: not a GIT statistics file ({exc}).") from exc


# Rows of the [N, L] table handled at once where a whole-table temporary is avoided.
ROW_BLOCK_ENTRIES = 1 << 21


@dataclass
class GITVisible(_LabelTable):
    """The GIT table as the ``merge`` step reads it: the labels and the visible mask at one visibility
    threshold, without ``prob`` (the merge never reads it) and ``visibility`` (read only through the
    mask): 5 instead of 12 bytes per (Gaussian, view). It answers ``label``, ``frames``,
    ``num_labels`` and :meth:`visible` as :class:`GITStats` does, for its own threshold only."""

    label: np.ndarray  # [N, L] int32
    mask: np.ndarray  # [N, L] bool: visibility > min_visibility and label >= 0
    min_visibility: float
    frames: list[str]
    num_labels: np.ndarray  # [L] int64

    def visible(self, min_visibility: float) -> np.ndarray:
        """The mask (:meth:`GITStats.visible` at this table's threshold, the same array every call)."""
        if min_visibility != self.min_visibility:
            raise ValueError(f"GITVisible holds the mask at visibility > {self.min_visibility}, "
                             f"not > {min_visibility}.")
        return self.mask

    @classmethod
    def load(cls, path: str | Path, min_visibility: float) -> "GITVisible":
        """Read ``git.npz``'s labels and its visible mask, :meth:`GITStats.visible` bit for bit; the
        float arrays are read one at a time (visibility, dropped once compared, then the labels), so
        at most 5 bytes per (Gaussian, view) are held while reading."""
        path = Path(path)
        if not path.is_file():
            raise SceneFormatError(f"{path}: GIT statistics file is missing.")
        try:
            with np.load(path) as data:
                frames = [str(f) for f in data["frames"]]
                num_labels = data["num_labels"]
                visibility = data["visibility"]
                shape = visibility.shape
                mask = visibility > min_visibility
                del visibility
                label = data["label"]
        except (KeyError, ValueError, OSError) as exc:
            raise SceneFormatError(f"{path}: not a GIT statistics file ({exc}).") from exc
        if label.ndim != 2 or shape != label.shape or len(frames) != label.shape[1]:
            raise SceneFormatError(f"{path}: GIT arrays disagree in shape ({label.shape}, {shape}, "
                                   f"{len(frames)} frames).")
        step = max(1, ROW_BLOCK_ENTRIES // max(1, label.shape[1]))
        for lo in range(0, len(label), step):
            mask[lo:lo + step] &= label[lo:lo + step] >= 0
        return cls(label=label, mask=mask, min_visibility=min_visibility, frames=frames, num_labels=num_labels)


@torch.no_grad()
def trace_views(model: GaussianModel, cameras: Sequence[Camera], label_maps: Sequence[np.ndarray],
                count_pixels: bool = False, near: float = 0.01, progress: bool = False) -> GITStats:
    """Trace every view's label map through ``model`` and reduce per view.

    Args:
        model: N Gaussians.
        cameras: L cameras.
        label_maps: L integer maps [H, W] (0 is a label like any other: e.g. uncovered pixels;
            negative values are ignored).
        count_pixels: count pixels instead of summing weights (the official code).
    Returns:
        :class:`GITStats`.
    """
    from ..render import trace_reduced

    if len(cameras) != len(label_maps):
        raise ValueError(f"trace_views: {len(cameras)} cameras but {len(label_maps)} label maps.")
    splats = model.splats()
    n, views = len(model), len(cameras)
    label = np.full((n, views), -1, np.int32)
    prob = np.zeros((n, views), np.float32)
    visibility = np.zeros((n, views), np.float32)
    num_labels = np.zeros(views, np.int64)
    bar = tqdm(list(zip(cameras, label_maps)), desc="GIT trace", disable=not progress, leave=False,
               mininterval=0.5 if sys.stderr.isatty() else 30.0)  # log files get a line every 30 s
    track_compile_time(bar)  # the ETA leaves out a first run's kernel compilation
    for v, (cam, labels) in enumerate(bar):
        labels_t = torch.from_numpy(np.asarray(labels).astype(np.int64))
        t = int(labels_t.max()) + 1 if labels_t.numel() else 1
        trace_reduced(splats, cam, labels_t, max(t, 1), near=near, count_pixels=count_pixels,
                      out=(label[:, v], prob[:, v], visibility[:, v]))
        num_labels[v] = t
    return GITStats(label=label, prob=prob, visibility=visibility, frames=[c.name for c in cameras],
                    num_labels=num_labels)


# ----------------------------------------------------------------------------------------------
# The `trace` step
# ----------------------------------------------------------------------------------------------


@dataclass
class TraceParams:
    """Parameters of the ``trace`` step.

    ``preset`` picks the statistic: ``paper`` sums blending weights (the paper's reverse
    rasterisation), ``official`` counts pixels per Gaussian as the released code does. ``statistic``
    overrides the preset's choice.
    """

    preset: Literal["paper", "official"] = "paper"
    statistic: Literal["weights", "pixels"] | None = None
    near: float = 0.01

    def __post_init__(self) -> None:
        if self.statistic is None:
            self.statistic = "weights" if self.preset == "paper" else "pixels"


def load_label_maps(folder: Path, frames: Sequence[str], what: str,
                    sizes: Sequence[tuple[int, int]] | None = None) -> list[np.ndarray]:
    """The 16-bit label maps ``folder/<frame>.png`` of ``frames``; each must be its view's
    (width, height) from ``sizes`` when given (a map of another size would be read at the wrong pixels)."""
    from ..scene import read_u16

    sizes = list(sizes) if sizes is not None else [None] * len(frames)
    return [read_u16(Path(folder) / f"{f}.png", what, size).astype(np.int64) for f, size in zip(frames, sizes)]


def load_fitted(scene, poses_dir: Path | None, gaussians_dir: Path) -> tuple[GaussianModel, list[Camera]]:
    """The fitted model (``point_cloud.ply``) and the cameras it lives with (the poses folder's,
    else the scene's)."""
    from ..training import read_pose_cameras

    from ..scene import require_known_poses

    if poses_dir is None:
        require_known_poses(scene, "trace3d trace/refine")
    model = GaussianModel.read_ply(Path(gaussians_dir) / "point_cloud.ply")
    cameras = read_pose_cameras(Path(poses_dir), scene) if poses_dir is not None else list(scene.cameras)
    return model, cameras


def run_trace(scene, poses_dir: Path | None, gaussians_dir: Path, labels_dir: Path, out_dir: Path,
              params: dict) -> dict:
    """The ``trace`` step: GIT statistics of every training view's label map; writes ``git.npz`` and
    ``trace.json`` into ``out_dir``."""
    from ..io import write_json
    from ..params import from_mapping, to_dict

    p = from_mapping(TraceParams, params, "trace params")
    model, cameras = load_fitted(scene, poses_dir, gaussians_dir)
    train = [c for c in cameras if c.split == "train"]
    maps = load_label_maps(labels_dir, [c.name for c in train], "label map", [(c.width, c.height) for c in train])
    start = time.perf_counter()
    stats = trace_views(model, train, maps, count_pixels=p.statistic == "pixels", near=p.near, progress=True)
    seconds = time.perf_counter() - start
    stats.save(Path(out_dir) / "git.npz")
    seen = stats.visible(0.0)
    summary = {
        "params": to_dict(p), "gaussians": stats.num_gaussians, "views": stats.num_views,
        "seconds": seconds, "mean_views_per_gaussian": float(seen.sum(1).mean()),
        "never_seen_fraction": float((~seen.any(1)).mean()),
        "mean_top_probability": float(stats.prob[seen].mean()) if seen.any() else 0.0,
    }
    write_json(Path(out_dir) / "trace.json", summary)
    log.info("GIT: %d Gaussians x %d views in %.1f s", stats.num_gaussians, stats.num_views, seconds)
    return summary

