"""GIT-guided density control (paper Sec. 3.4; the ``refine`` step).

With the consistent instance maps, GIT gives every Gaussian i its top instance probability in each
view it sees (V_i). Its ambiguity score is

    As_i = 1/|V_i| sum_{v in V_i} [max_j W_i^v[j] < gamma]        (gamma = 0.8)

and it is *ambiguous* when As_i > theta_As (0.5). While the whole scene is retrained with the
photometric loss, detection runs on a schedule: an ambiguous Gaussian is split into two children
whose scales are the parent's divided by ``scale_divisor`` (2.0) and whose centres are sampled from
the parent used as a PDF in its tangent plane; children that are still ambiguous at a later
detection are removed. A last detection after the final iteration removes children that are still
ambiguous then (otherwise the last round's children would never be checked).

:class:`GITStrategy` is this density control as a :class:`~trace3d.training.strategy.Strategy`
plugged into the ordinary training loop; the split generation of each Gaussian is an optimiser
statistic, so it follows every edit.

Presets (every value a key of :class:`RefineParams`):

- ``paper``: weight sums, gamma 0.8, theta_As 0.5, scales / 2.0, detection at iterations
  1, 1000, 2000, 3000 of a 5000-iteration retraining (the paper says "every 1000 iterations" and
  gives neither the first detection nor the length; these are ours), loss L1 + 0.2 D-SSIM + 0.05
  normal consistency, no gradient densification (the paper *replaces* the 3DGS strategy).
- ``official`` (the released code, ``remove_ab_gaus.py`` with ``script/replica.sh``'s flags): pixel
  counts, a view counts as seen above 25 pixels, theta_As 0.4, scales / 1.6, detection at 10, 1210,
  2410, 3610 of a 9000-iteration fine-tune without gradient densification, loss L1 + 0.2 D-SSIM +
  0.05 normal; and its pruning: at a detection every ambiguous Gaussian is split (children too) and
  every Gaussian still ambiguous right after the split is removed (``prune: after_split``), there is
  no detection after the last iteration (``final_prune: false``), and Gaussians that no training
  view sees are removed at the first and the last iteration (``prune_unseen: true``).

``prune: next_detection`` (the paper's reading, ``paper``): ambiguous original Gaussians are split,
children still ambiguous at the next detection are removed, and ``final_prune`` checks the last
round's children after the final iteration.

All iteration numbers are on the 30k scale and multiplied by ``schedule_scale`` like the fit's.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Sequence

import numpy as np
import torch

from ..gaussians import GaussianModel
from ..scene import Camera
from ..training.optimizer import GaussianOptimizer
from ..training.strategy import Strategy, split_gaussians
from .git import GITStats, trace_views

log = logging.getLogger(__name__)

PRESET_VALUES = {
    "paper": {"statistic": "weights", "min_visibility": 0.0, "gamma": 0.8, "ambiguity_threshold": 0.5,
              "scale_divisor": 2.0, "iterations": 5000, "detect_at": [1, 1000, 2000, 3000],
              "prune": "next_detection", "final_prune": True, "prune_unseen": False},
    "official": {"statistic": "pixels", "min_visibility": 25.0, "gamma": 0.8, "ambiguity_threshold": 0.4,
                 "scale_divisor": 1.6, "iterations": 9000, "detect_at": [10, 1210, 2410, 3610],
                 "prune": "after_split", "final_prune": False, "prune_unseen": True},
}


@dataclass
class RefineParams:
    """Parameters of the ``refine`` step (``None`` takes the preset's value; see the module docstring)."""

    preset: Literal["paper", "official"] = "paper"
    statistic: Literal["weights", "pixels"] | None = None
    min_visibility: float | None = None
    gamma: float | None = None
    ambiguity_threshold: float | None = None
    scale_divisor: float | None = None
    position_std: float = 1.0  # children's centres ~ N(0, position_std * (s_u, s_v)) in the tangent plane
    iterations: int | None = None  # retraining length, 30k scale
    detect_at: list[int] | None = None  # detection iterations, 30k scale
    prune: Literal["next_detection", "after_split"] | None = None  # which ambiguous Gaussians go, and when
    final_prune: bool | None = None  # a last detection after the final iteration (prune: next_detection)
    prune_unseen: bool | None = None  # remove Gaussians no training view sees, at the first and last iteration
    schedule_scale: float = 0.1
    # retraining (the fit's TrainParams otherwise): a converged scene is fine-tuned, so the position
    # learning rate starts where the fit's schedule is at about two thirds, SH at full degree and
    # the normal-consistency term on from the start
    position_lr_init: float = 0.000016
    position_lr_final: float = 0.0000016
    lambda_normal: float = 0.05
    train: dict = field(default_factory=dict)  # further TrainParams overrides
    seed: int = 0
    highlight_views: int = 4

    # each field's range: refused on input and in the config schema (trace3d.params.check_ranges)
    RANGES = {"gamma": "(0, 1]", "ambiguity_threshold": "[0, 1)", "scale_divisor": "> 0", "iterations": ">= 1",
              "detect_at": ">= 0", "schedule_scale": "> 0", "seed": ">= 0"}

    def __post_init__(self) -> None:
        for key, value in PRESET_VALUES[self.preset].items():
            if getattr(self, key) is None:
                setattr(self, key, list(value) if isinstance(value, list) else value)
        if not 0.0 < self.gamma <= 1.0:
            raise ValueError(f"gamma must be in (0, 1], got {self.gamma}")
        if not 0.0 <= self.ambiguity_threshold < 1.0:
            raise ValueError(f"ambiguity_threshold must be in [0, 1), got {self.ambiguity_threshold}")
        if not self.scale_divisor > 0:
            raise ValueError(f"scale_divisor must be > 0, got {self.scale_divisor}")
        if self.prune not in ("next_detection", "after_split"):
            raise ValueError(f"prune must be 'next_detection' or 'after_split', got {self.prune!r}")
        if self.final_prune and self.prune == "after_split":
            raise ValueError("final_prune checks the last round's children, which prune: after_split has already "
                             "checked; set final_prune: false with it")
        if self.iterations < 1 or any(d < 0 for d in self.detect_at):
            raise ValueError(f"iterations must be >= 1 and detect_at >= 0, got {self.iterations}, {self.detect_at}")
        late = [d for d in self.detect_at if d > self.iterations]
        if late:
            raise ValueError(f"detect_at {late} lies after the last iteration ({self.iterations}, both on the 30k "
                             f"scale); lower detect_at or raise iterations")
        if not self.schedule_scale > 0:
            raise ValueError(f"schedule_scale must be > 0, got {self.schedule_scale}")

    def scaled(self, value: int) -> int:
        return 0 if value == 0 else max(1, int(round(value * self.schedule_scale)))

    def detection_iterations(self) -> list[int]:
        """The scaled detection iterations inside the retraining (sorted, unique)."""
        total = self.scaled(self.iterations)
        return sorted({min(max(self.scaled(d), 1), total) for d in self.detect_at})


def ambiguity_scores(stats: GITStats, gamma: float, min_visibility: float) -> tuple[np.ndarray, np.ndarray]:
    """As_i [N] (0 where the Gaussian sees no view) and |V_i| [N]."""
    seen = stats.visible(min_visibility)
    views = seen.sum(axis=1)
    unsure = (seen & (stats.prob < gamma)).sum(axis=1)
    return np.where(views > 0, unsure / np.maximum(views, 1), 0.0), views


def find_ambiguous(stats: GITStats, gamma: float, threshold: float, min_visibility: float) -> np.ndarray:
    """[N] bool: As_i > threshold."""
    scores, _ = ambiguity_scores(stats, gamma, min_visibility)
    return scores > threshold


GENERATION = "split_generation"  # extra attribute: 0 for original Gaussians, parent's + 1 for children


class GITStrategy(Strategy):
    """GIT-guided density control as a training-loop strategy (see the module docstring).

    The model must carry the extra attribute ``split_generation`` [N] (see :func:`with_generation`);
    it follows every edit, so children are recognised at the next detection.

    Args:
        cameras, label_maps: the training views and their consistent instance maps.
        params: the refine parameters.
        generator: random source of the children's positions.
    """

    def __init__(self, cameras: Sequence[Camera], label_maps: Sequence[np.ndarray], params: RefineParams,
                 generator: torch.Generator | None = None, near: float = 0.01):
        self.cameras = list(cameras)
        self.label_maps = list(label_maps)
        self.params = params
        self.generator = generator
        self.near = near
        self.detect_at = set(params.detection_iterations())
        self.rounds: list[dict] = []

    def detect(self, model: GaussianModel) -> np.ndarray:
        """[N] bool ambiguous Gaussians of ``model`` under the consistent maps."""
        p = self.params
        stats = trace_views(model, self.cameras, self.label_maps, count_pixels=p.statistic == "pixels", near=self.near)
        return find_ambiguous(stats, p.gamma, p.ambiguity_threshold, p.min_visibility)

    def initialize(self, state: GaussianOptimizer, schedule: dict[str, int]) -> None:
        if GENERATION not in state.model.extras:
            raise ValueError(f"GITStrategy: the model needs the extra attribute {GENERATION!r} (with_generation()).")

    def unseen(self, model: GaussianModel) -> np.ndarray:
        """[N] bool: Gaussians that no training view sees (no pixel's blending touches them)."""
        stats = trace_views(model, self.cameras, self.label_maps, count_pixels=True, near=self.near)
        return ~(stats.visibility > 0).any(axis=1)

    def _split(self, state: GaussianOptimizer, split: torch.Tensor, prune: torch.Tensor) -> int:
        """Replace the ``split`` Gaussians by two children each and remove the ``prune`` ones."""
        n_before = len(state)
        n_split = int(split.sum())
        if n_split:
            children = split_gaussians(state.model.subset(split), 2, self.generator,
                                       scale_divisor=self.params.scale_divisor, position_std=self.params.position_std)
            children.extras[GENERATION] = children.extras[GENERATION] + 1
            state.append(children)
        remove = torch.cat([prune | split, torch.zeros(len(state) - n_before, dtype=torch.bool, device=prune.device)])
        if bool(remove.any()):
            state.keep(~remove)
        return n_split

    @torch.no_grad()
    def after_step(self, iteration: int, state: GaussianOptimizer) -> dict | None:
        detect_now = iteration in self.detect_at
        unseen_now = bool(self.params.prune_unseen) and iteration == 1
        if not (detect_now or unseen_now):
            return None
        start = time.perf_counter()
        device = state.model.device
        n_before = len(state)
        n_unseen = n_ambiguous = n_split = n_pruned = 0
        if unseen_now:  # the released code removes what no view sees before its first detection
            unseen = torch.from_numpy(self.unseen(state.model)).to(device)
            n_unseen = int(unseen.sum())
            if n_unseen:
                state.keep(~unseen)
        if detect_now:
            ambiguous = torch.from_numpy(self.detect(state.model)).to(device)
            n_ambiguous = int(ambiguous.sum())
            if self.params.prune == "after_split":
                # every ambiguous Gaussian is split; whatever is still ambiguous right after goes
                n_split = self._split(state, ambiguous, torch.zeros_like(ambiguous))
                still = torch.from_numpy(self.detect(state.model)).to(device)
                n_pruned = int(still.sum())
                if n_pruned:
                    state.keep(~still)
            else:
                # ambiguous originals are split; ambiguous children (of an earlier round) go
                generation = state.model.extras[GENERATION]
                prune = ambiguous & (generation > 0)
                n_split = self._split(state, ambiguous & (generation == 0), prune)
                n_pruned = int(prune.sum())
        event = {"iteration": iteration, "gaussians_before": n_before, "ambiguous": n_ambiguous,
                 "split": n_split, "pruned": n_pruned, "unseen_pruned": n_unseen, "gaussians_after": len(state),
                 "seconds": round(time.perf_counter() - start, 3)}
        self.rounds.append(event)
        log.info("GIT density control at %d: %d ambiguous of %d, split %d, pruned %d (+%d unseen)", iteration,
                 n_ambiguous, n_before, n_split, n_pruned, n_unseen)
        return {"git_ambiguous": n_ambiguous, "git_split": n_split, "git_pruned": n_pruned,
                "git_unseen_pruned": n_unseen, "total": len(state)}

    @torch.no_grad()
    def prune_unseen(self, model: GaussianModel, iteration: int) -> GaussianModel:
        """After training: remove the Gaussians no training view sees (the released code's last prune)."""
        start = time.perf_counter()
        unseen = self.unseen(model)
        self.rounds.append({"iteration": iteration, "gaussians_before": len(model), "ambiguous": 0, "split": 0,
                            "pruned": 0, "unseen_pruned": int(unseen.sum()), "gaussians_after": len(model) - int(unseen.sum()),
                            "seconds": round(time.perf_counter() - start, 3), "final": True})
        return model.subset(torch.from_numpy(~unseen).to(model.device))

    @torch.no_grad()
    def final_prune(self, model: GaussianModel, iteration: int) -> GaussianModel:
        """The last detection after training: remove children that are still ambiguous (no new splits)."""
        start = time.perf_counter()
        ambiguous = torch.from_numpy(self.detect(model)).to(model.device)
        prune = ambiguous & (model.extras[GENERATION] > 0)
        self.rounds.append({"iteration": iteration, "gaussians_before": len(model), "ambiguous": int(ambiguous.sum()),
                            "split": 0, "pruned": int(prune.sum()), "gaussians_after": len(model) - int(prune.sum()),
                            "seconds": round(time.perf_counter() - start, 3), "final": True})
        return model.subset(~prune)


def with_generation(model: GaussianModel) -> GaussianModel:
    """``model`` with a zero ``split_generation`` extra (original Gaussians)."""
    out = model.detached_copy()
    out.set(GENERATION, torch.zeros(len(model), dtype=model.means.dtype, device=model.device))
    return out


# ----------------------------------------------------------------------------------------------
# Where the ambiguous Gaussians are (synthetic benchmark: next to ground-truth boundaries?)
# ----------------------------------------------------------------------------------------------


def boundary_band(truth: np.ndarray, width: int = 2) -> np.ndarray:
    """[H, W] bool: pixels within ``width`` px (Chebyshev) of a change of ground-truth id."""
    import cv2

    edge = np.zeros(truth.shape, bool)
    edge[:, 1:] |= truth[:, 1:] != truth[:, :-1]
    edge[:, :-1] |= truth[:, 1:] != truth[:, :-1]
    edge[1:, :] |= truth[1:, :] != truth[:-1, :]
    edge[:-1, :] |= truth[1:, :] != truth[:-1, :]
    if width > 0:
        kernel = np.ones((2 * width + 1, 2 * width + 1), np.uint8)
        edge = cv2.dilate(edge.astype(np.uint8), kernel) > 0
    return edge


@torch.no_grad()
def near_boundary(model: GaussianModel, cameras: Sequence[Camera], stats: GITStats, bands: Sequence[np.ndarray],
                  near: float = 0.01) -> np.ndarray:
    """[N] bool: the Gaussian's footprint box in its dominant view (largest GIT visibility) touches
    the boundary band of that view (False for Gaussians no view sees)."""
    from ..render import project

    dominant = np.argmax(stats.visibility, axis=1)
    seen = stats.visibility.max(axis=1) > 0
    out = np.zeros(len(model), bool)
    splats = model.splats()
    for v, (cam, band) in enumerate(zip(cameras, bands)):
        rows = np.nonzero(seen & (dominant == v))[0]
        if rows.size == 0:
            continue
        boxes = np.asarray(project(splats, cam, near).boxes)[rows]  # x0, y0, x1, y1 (exclusive)
        integral = np.pad(band.astype(np.int64).cumsum(0).cumsum(1), ((1, 0), (1, 0)))
        h, w = band.shape
        x0 = np.clip(boxes[:, 0], 0, w)
        y0 = np.clip(boxes[:, 1], 0, h)
        x1 = np.clip(boxes[:, 2], 0, w)
        y1 = np.clip(boxes[:, 3], 0, h)
        count = integral[y1, x1] - integral[y0, x1] - integral[y1, x0] + integral[y0, x0]
        out[rows] = (count > 0) & (x1 > x0) & (y1 > y0)
    return out


# ----------------------------------------------------------------------------------------------
# The `refine` step
# ----------------------------------------------------------------------------------------------


def retrain_params(fit_config: dict, p: RefineParams):
    """The retraining's TrainParams: the fit's, with the refine schedule and fine-tune settings."""
    from ..params import from_mapping
    from ..training import TrainParams

    base = dict(fit_config.get("params", {}))
    sh = int(base.get("sh_degree", 3))
    values = {**base, "schedule_scale": p.schedule_scale, "iterations": p.iterations, "densify": False,
              "position_lr_init": p.position_lr_init, "position_lr_final": p.position_lr_final,
              "lambda_normal": p.lambda_normal, "normal_from": 0, "initial_sh_degree": sh,
              "seed": p.seed, **p.train}
    return from_mapping(TrainParams, values, "refine params.train")


def _db(value) -> str:
    """A PSNR for the log: two decimals (the JSON keeps every digit), n/a without test views."""
    return "n/a" if value is None else f"{float(value):.2f}"


def run_refine(scene, poses_dir: Path | None, gaussians_dir: Path, labels_dir: Path, out_dir: Path,
               params: dict) -> dict:
    """The ``refine`` step: GIT-guided density control while retraining the fitted scene on the
    (consistent) label maps in ``labels_dir``. Writes ``point_cloud.ply``, ``refine.json``,
    ``train.csv`` and ``ambiguous.png`` into ``out_dir``."""
    import json

    from ..io import write_json
    from ..params import from_mapping, to_dict
    from ..training import evaluate_views, fit, load_images, torch_threads
    from ..training.step import plot_history, write_history_csv
    from .git import load_fitted, load_label_maps

    p = from_mapping(RefineParams, params, "refine params")
    gaussians_dir = Path(gaussians_dir)
    model, cameras = load_fitted(scene, poses_dir, gaussians_dir)
    config_path = gaussians_dir / "config.json"
    fit_config = json.loads(config_path.read_text()) if config_path.is_file() else {}
    train_params = retrain_params(fit_config, p)
    extent = float(fit_config.get("extent", 1.0))
    train = [c for c in cameras if c.split == "train"]
    test = [c for c in cameras if c.split == "test"]
    maps = load_label_maps(labels_dir, [c.name for c in train], "instance map", [(c.width, c.height) for c in train])
    images = load_images(scene, train)
    test_images = load_images(scene, test)
    background = torch.tensor(train_params.background, dtype=torch.float32)
    start = time.perf_counter()
    strategy = GITStrategy(train, maps, p, torch.Generator().manual_seed(p.seed), near=train_params.near)

    # before: ambiguity of the fitted scene, where it sits, and the test PSNR
    stats0 = trace_views(model, train, maps, count_pixels=p.statistic == "pixels", near=train_params.near)
    ambiguous0 = find_ambiguous(stats0, p.gamma, p.ambiguity_threshold, p.min_visibility)
    report: dict = {"params": to_dict(p), "train_params": to_dict(train_params),
                    "gaussians_before": len(model), "ambiguous_before": int(ambiguous0.sum()),
                    "ambiguous_fraction_before": float(ambiguous0.mean()) if len(model) else 0.0}
    with torch_threads(train_params.torch_threads):
        rows_before, _ = evaluate_views(model, test, test_images, train_params.sh_degree, background, train_params.near)
    report["test_psnr_before"] = float(np.mean([r["psnr"] for r in rows_before])) if rows_before else None
    bands = None
    if scene.has_instances and scene.objects is not None:
        table = scene.objects.lookup("object")
        bands = [boundary_band(table[np.clip(scene.instances(c.name).astype(np.int64), 0, len(table) - 1)])
                 for c in train]
        near_edge = near_boundary(model, train, stats0, bands, train_params.near)
        report["boundary"] = {
            "definition": "footprint box in the dominant view touches the 2-px band around a ground-truth object boundary",
            "ambiguous_near_boundary": float(near_edge[ambiguous0].mean()) if ambiguous0.any() else None,
            "all_near_boundary": float(near_edge.mean()) if len(model) else None,
        }
    # the fitted scene's GIT table [N, L] is not needed past here: not held through the retraining, whose
    # detections build their own (3.4 GB each at 1.28 M Gaussians x 219 views, docs/scale.md)
    del stats0

    result = fit(with_generation(model), train, images, train_params, extent=extent, strategy=strategy,
                 desc="GIT-guided refine")
    refined = result.model
    if p.final_prune:
        refined = strategy.final_prune(refined, train_params.scaled("iterations"))
    if p.prune_unseen:
        refined = strategy.prune_unseen(refined, train_params.scaled("iterations"))
    stats1 = trace_views(refined, train, maps, count_pixels=p.statistic == "pixels", near=train_params.near)
    ambiguous1 = find_ambiguous(stats1, p.gamma, p.ambiguity_threshold, p.min_visibility)
    with torch_threads(train_params.torch_threads):
        rows_after, _ = evaluate_views(refined, test, test_images, train_params.sh_degree, background, train_params.near)
    report.update({
        "rounds": strategy.rounds,
        "found": int(sum(r["ambiguous"] for r in strategy.rounds)),
        "split": int(sum(r["split"] for r in strategy.rounds)),
        "pruned": int(sum(r["pruned"] for r in strategy.rounds)),
        "unseen_pruned": int(sum(r.get("unseen_pruned", 0) for r in strategy.rounds)),
        "gaussians_after": len(refined),
        "ambiguous_after": int(ambiguous1.sum()),
        "ambiguous_fraction_after": float(ambiguous1.mean()) if len(refined) else 0.0,
        "test_psnr_after": float(np.mean([r["psnr"] for r in rows_after])) if rows_after else None,
        "iterations": train_params.scaled("iterations"),
        "seconds": time.perf_counter() - start,
    })
    out_dir = Path(out_dir)
    refined.write_ply(out_dir / "point_cloud.ply")
    write_history_csv(out_dir / "train.csv", result.history)
    if result.history:
        plot_history(out_dir / "train_curve.png", result.history)
    if p.highlight_views > 0:
        plot_ambiguous(out_dir / "ambiguous.png", model, ambiguous0, refined, ambiguous1, train, images, bands,
                       train_params, p.highlight_views)
    write_json(out_dir / "refine.json", report)
    log.info("refine: %d -> %d Gaussians, ambiguous %d -> %d, test PSNR %s -> %s dB", len(model), len(refined),
             int(ambiguous0.sum()), int(ambiguous1.sum()), _db(report["test_psnr_before"]), _db(report["test_psnr_after"]))
    return report


@torch.no_grad()
def plot_ambiguous(path: Path, before: GaussianModel, amb_before: np.ndarray, after: GaussianModel,
                   amb_after: np.ndarray, cameras: Sequence[Camera], images: Sequence[torch.Tensor],
                   bands: Sequence[np.ndarray] | None, train_params, count: int) -> None:
    """Rows of views: the render with the ambiguous Gaussians' share of each pixel in red, before
    and after refinement, and the ground-truth boundaries when known."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..render import render
    from ..training import render_view

    picks = np.linspace(0, len(cameras) - 1, min(count, len(cameras))).round().astype(int)
    columns = 3 if bands is not None else 2
    fig, axes = plt.subplots(len(picks), columns, figsize=(3.6 * columns, 2.8 * len(picks)), squeeze=False)
    for row, v in enumerate(picks):
        cam = cameras[v]
        for col, (model, amb, label) in enumerate(((before, amb_before, "fitted"), (after, amb_after, "refined"))):
            rgb = render_view(model, cam, train_params.sh_degree, None, train_params.near).features.clamp(0, 1).numpy()
            share = render(model.splats(), cam, torch.from_numpy(amb.astype(np.float32))[:, None],
                           near=train_params.near).features[..., 0].clamp(0, 1).numpy()
            grey = rgb.mean(axis=2, keepdims=True) * 0.6
            overlay = grey * (1 - share[..., None]) + np.array([1.0, 0.1, 0.1]) * share[..., None]
            axes[row, col].imshow(np.clip(overlay, 0, 1))
            axes[row, col].set_title(f"{cam.name} {label}: {int(amb.sum())} ambiguous (red)", fontsize=8)
        if bands is not None:
            image = images[v].numpy() * 0.5
            image[bands[v]] = [1.0, 1.0, 0.2]
            axes[row, 2].imshow(image)
            axes[row, 2].set_title("ground-truth object boundaries (2 px band)", fontsize=8)
        for ax in axes[row]:
            ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
