"""Photometric 2DGS fitting with the standard adaptive density control (the ``gaussians`` step).

The loop follows the 2DGS reference training (Huang et al. 2024), with its defaults:

- Adam (eps 1e-15) with one learning rate per parameter group; the position learning rate decays
  exponentially from ``position_lr_init`` to ``position_lr_final`` (both times the scene extent)
  over the run.
- Loss ``(1 - 0.2) L1 + 0.2 (1 - SSIM)``, plus the normal-consistency term (weight 0.05, from 7k of
  30k iterations) between the rendered normal and the normal of the rendered depth, and the
  optional depth distortion (weight 0 by default, as in the official Trace3D code; from 3k).
- SH degree raised by one every 1000 iterations up to ``sh_degree``.
- Density control from 500 to 15k, every 100 iterations: Gaussians whose mean view-space positional
  gradient (in NDC units, the 3DGS convention) reaches a threshold (2DGS: 2e-4) are cloned when small (largest scale at
  most 1 % of the scene extent) or split in two when large; Gaussians with opacity below 0.05, or
  (after the first opacity reset) a screen radius above 20 px or a world scale above 10 % of the
  extent, are pruned. Opacities are reset to at most 0.01 every 3000 iterations.

Every iteration count and interval above is multiplied by ``schedule_scale`` (1.0 = the 2DGS
reference schedule of 30k iterations). The defaults of :class:`TrainParams` are tuned so that the
synthetic benchmark rooms train in minutes on 2 CPU cores (3000 iterations, a budget of 80k
Gaussians, fewer opacity resets, a higher gradient threshold, a scene extent that also suits
inside-out captures; see the class);
:meth:`TrainParams.reference_2dgs` restores the reference. After an opacity reset, pruning by
opacity waits ``opacity_reset_grace`` (unscaled) iterations, as the reference's next densification
does. The CPU loop flushes denormal floats to zero (``flush_denormals``), which speeds up Adam and
the backward pass several-fold late in training.

Divergence (a non-finite loss, gradient or parameter) stops training with a
:class:`TrainingDiverged` error. :func:`run_gaussians` then writes the last good checkpoint to
``<out_dir's final name>.failed/checkpoint_last_good.ply`` *beside* the output folder (the CLI deletes
the temporary output folder on error) and says so in the error message.
"""

from __future__ import annotations

import contextlib
import csv
import logging
import math
import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Literal, Sequence

import numpy as np
import torch
from tqdm import tqdm

from .errors import ConfigError, SceneFormatError, Trace3DError
from .gaussians import (
    GaussianModel,
    init_from_depth,
    init_from_points,
    init_random,
    quat_to_rotmat,
)
from .io import write_json
from .losses import depth_to_normal, normal_consistency_loss, photometric_loss, psnr, ssim
from .params import from_mapping, to_dict
from .scene import Camera, Scene, read_cameras

log = logging.getLogger(__name__)


@dataclass
class TrainParams:
    """Parameters of the 2DGS fit.

    Iteration counts are given on the 2DGS 30k-iteration scale and all multiplied by
    ``schedule_scale``. The defaults are tuned for the default synthetic benchmark (160x120 images,
    ~60 train views, 2 CPU cores, a few minutes); they differ from the 2DGS reference in six
    places, each marked "ref:" below. :meth:`reference_2dgs` gives the reference settings.
    """

    # --- schedule (counts on the 30k scale, multiplied by schedule_scale) ------------------------
    schedule_scale: float = 0.1  # ref: 1.0 (30k iterations); 0.1 -> 3000 iterations
    iterations: int = 30_000
    densify_from: int = 500
    densify_until: int = 12_000  # ref: 15_000; ends earlier to leave the short run time to converge
    densify_interval: int = 100
    # ref: 3000. A reset costs an absolute ~100-200 iterations to recover (Adam re-raising the
    # opacities; slow, untruncated blending meanwhile), so a scaled schedule resets less often.
    opacity_reset_interval: int = 5000
    sh_degree_interval: int = 1000
    normal_from: int = 7000
    distortion_from: int = 3000
    checkpoint_interval: int = 1000  # how often the last good checkpoint is refreshed
    # --- model and initialisation --------------------------------------------------------------
    sh_degree: int = 3
    init: Literal["auto", "points", "depth", "random"] = "auto"
    init_opacity: float = 0.1
    init_max_points: int = 30_000
    depth_init_stride: int = 4
    random_init_count: int = 100_000
    random_init_margin: float = 0.5  # random box = camera-centre box grown by this x extent
    # Scene extent (scales the position learning rate, the clone/split size and the world-size
    # prune). "cameras" is the 3DGS/2DGS rule (1.1 x the camera centres' radius), which is tiny for
    # inside-out captures (a room seen from a small loop); "auto" takes the larger of it and 1.1 x
    # the median distance of the initial Gaussians from the camera centroid.
    # ref: "cameras". On the synthetic rooms "auto" (extent ~3.0 instead of 0.7) lifts test PSNR
    # from 28.5 to 31.0 dB at the same cost.
    extent: Literal["cameras", "auto"] = "auto"
    # --- learning rates (2DGS) ------------------------------------------------------------------
    position_lr_init: float = 0.00016
    position_lr_final: float = 0.0000016
    feature_lr: float = 0.0025
    sh_rest_lr_divisor: float = 20.0
    opacity_lr: float = 0.05
    scaling_lr: float = 0.005
    rotation_lr: float = 0.001
    # --- losses ---------------------------------------------------------------------------------
    lambda_dssim: float = 0.2
    lambda_normal: float = 0.05
    lambda_distortion: float = 0.0
    depth_ratio: float = 0.0  # surface depth = (1 - r) expected depth + r median depth
    # --- density control (2DGS) -----------------------------------------------------------------
    densify: bool = True
    # ref: 2e-4 on 2DGS's screen-space gradient. Our renderer's means2d gradient is the full
    # gradient w.r.t. the projected centre (NDC units as in 3DGS), which runs several times larger:
    # at 2e-4 most Gaussians of a fresh scene qualify.
    densify_grad_threshold: float = 0.0005
    percent_dense: float = 0.01
    opacity_cull: float = 0.05
    max_screen_size: float = 20.0  # pixels; used after the first opacity reset
    max_world_size: float = 0.1  # fraction of the scene extent; used after the first opacity reset
    split_count: int = 2
    # ref: unlimited. Densification stops growing beyond this count, keeping the highest-gradient
    # candidates (the time budget: per-iteration cost grows with the count).
    max_gaussians: int = 80_000
    # After an opacity reset, density control does not prune by opacity for this many iterations
    # (NOT scaled: it is set by how fast Adam raises the opacities again; 2DGS's first prune after a
    # reset comes one densify interval = 100 iterations later).
    opacity_reset_grace: int = 100
    # --- misc -----------------------------------------------------------------------------------
    background: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    random_background: bool = False
    near: float = 0.01
    seed: int = 0
    device: Literal["auto", "cpu", "cuda"] = "auto"
    log_interval: int = 10
    num_render_views: int = 4
    flush_denormals: bool = True  # CPU: treat denormal floats as zero during training (much faster Adam/backward)
    # torch intra-op threads during training (0 = leave torch's setting). The heavy work is in the
    # rasterizer's numba kernels, which run their own threads; torch's OpenMP threads spin-waiting
    # beside them made an iteration 15x slower on a busy 2-core machine (5.0 vs 0.33 s at 80k splats).
    torch_threads: int = 1

    def __post_init__(self) -> None:
        positive = ("iterations", "densify_interval", "opacity_reset_interval", "sh_degree_interval",
                    "checkpoint_interval", "init_max_points", "depth_init_stride", "random_init_count",
                    "split_count", "max_gaussians", "log_interval")
        for name in positive:
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not self.schedule_scale > 0:
            raise ValueError(f"schedule_scale must be > 0, got {self.schedule_scale}")
        if not 0 <= self.sh_degree <= 3:
            raise ValueError(f"sh_degree must be in 0..3, got {self.sh_degree}")
        if not 0.0 < self.init_opacity < 1.0:
            raise ValueError(f"init_opacity must be in (0, 1), got {self.init_opacity}")
        if not 0.0 <= self.lambda_dssim <= 1.0:
            raise ValueError(f"lambda_dssim must be in [0, 1], got {self.lambda_dssim}")
        if not 0.0 <= self.depth_ratio <= 1.0:
            raise ValueError(f"depth_ratio must be in [0, 1], got {self.depth_ratio}")
        if len(self.background) != 3:
            raise ValueError(f"background must be an RGB triple, got {self.background}")
        for name in ("position_lr_init", "position_lr_final", "feature_lr", "opacity_lr", "scaling_lr",
                     "rotation_lr", "lambda_normal", "lambda_distortion", "densify_grad_threshold",
                     "percent_dense", "opacity_cull", "max_screen_size", "max_world_size", "near",
                     "opacity_reset_grace", "torch_threads", "densify_from", "densify_until", "normal_from", "distortion_from",
                     "random_init_margin"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")

    @classmethod
    def reference_2dgs(cls, **overrides) -> "TrainParams":
        """The 2DGS reference settings (30k iterations, threshold 2e-4, resets every 3000,
        densification until 15k, no Gaussian budget, camera extent), with ``overrides``."""
        values = dict(schedule_scale=1.0, densify_until=15_000, opacity_reset_interval=3000,
                      densify_grad_threshold=0.0002, max_gaussians=100_000_000, extent="cameras")
        values.update(overrides)
        return cls(**values)

    def scaled(self, name: str) -> int:
        """Iteration count ``name`` times ``schedule_scale`` (at least 1; 0 stays 0)."""
        value = getattr(self, name)
        return 0 if value == 0 else max(1, int(round(value * self.schedule_scale)))

    def schedule(self) -> dict[str, int]:
        """All scaled iteration counts by name."""
        names = ("iterations", "densify_from", "densify_until", "densify_interval", "opacity_reset_interval",
                 "sh_degree_interval", "normal_from", "distortion_from", "checkpoint_interval")
        return {name: self.scaled(name) for name in names}


class TrainingDiverged(Trace3DError):
    """Training produced a non-finite loss, gradient or parameter.

    Attributes:
        iteration: the iteration that failed.
        checkpoint: the last good model (CPU) and ``checkpoint_iteration`` when it was taken.
        history: the rows logged so far.
    """

    def __init__(self, message: str, iteration: int, checkpoint: GaussianModel, checkpoint_iteration: int,
                 history: list[dict]):
        super().__init__(message)
        self.iteration = iteration
        self.checkpoint = checkpoint
        self.checkpoint_iteration = checkpoint_iteration
        self.history = history


# ----------------------------------------------------------------------------------------------
# Learning-rate schedule
# ----------------------------------------------------------------------------------------------


def exponential_lr(step: int, lr_init: float, lr_final: float, max_steps: int) -> float:
    """Log-linear interpolation from ``lr_init`` (step 0) to ``lr_final`` (step ``max_steps``)."""
    if lr_init == 0.0 and lr_final == 0.0:
        return 0.0
    t = min(max(step / max(max_steps, 1), 0.0), 1.0)
    return math.exp(math.log(lr_init) * (1.0 - t) + math.log(lr_final) * t)


def points_extent(points: torch.Tensor, cameras: Sequence[Camera]) -> float:
    """1.1 x the median distance of ``points`` [P, 3] from the centroid of the camera centres."""
    centroid = torch.as_tensor(np.stack([c.center for c in cameras]).mean(axis=0), dtype=points.dtype)
    return float((points.detach().cpu() - centroid).norm(dim=-1).median()) * 1.1


def scene_extent(cameras: Sequence[Camera]) -> float:
    """The 3DGS "cameras extent": 1.1 x the largest distance of a camera centre from their mean.

    Falls back to 1.0 when all centres coincide (a single view).
    """
    centers = np.stack([c.center for c in cameras])
    radius = float(np.linalg.norm(centers - centers.mean(axis=0), axis=1).max()) * 1.1
    return radius if radius > 1e-6 else 1.0


# ----------------------------------------------------------------------------------------------
# Optimiser + density control
# ----------------------------------------------------------------------------------------------


class GaussianOptimizer:
    """A :class:`GaussianModel` under Adam, with the 3DGS/2DGS adaptive density control.

    ``model``'s tensors are replaced by ``torch.nn.Parameter`` objects; clone / split / prune edit
    the parameters *and* the Adam moments (new Gaussians start with zero moments).

    Density statistics (reset after every densification):
        grad_accum: [N] sum of the NDC-space positional gradient norms over the views that saw it.
        grad_count: [N] number of such views.
        max_radii: [N] largest screen radius (pixels) seen since the last densification.
    """

    def __init__(self, model: GaussianModel, params: TrainParams, extent: float):
        self.params = params
        self.extent = float(extent)
        self.model = model.map(lambda t: torch.nn.Parameter(t.detach().clone().contiguous()))
        lrs = {
            "means": params.position_lr_init * self.extent,
            "quats": params.rotation_lr,
            "log_scales": params.scaling_lr,
            "opacity_logits": params.opacity_lr,
            "sh_dc": params.feature_lr,
            "sh_rest": params.feature_lr / params.sh_rest_lr_divisor,
        }
        self.optimizer = torch.optim.Adam(
            [{"params": [getattr(self.model, name)], "lr": lr, "name": name} for name, lr in lrs.items()],
            lr=0.0,
            eps=1e-15,
        )
        self.reset_stats()

    # --- bookkeeping ---------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.model)

    def reset_stats(self) -> None:
        n, device = len(self.model), self.model.device
        self.grad_accum = torch.zeros(n, device=device)
        self.grad_count = torch.zeros(n, device=device)
        self.max_radii = torch.zeros(n, device=device)

    def set_position_lr(self, lr: float) -> None:
        for group in self.optimizer.param_groups:
            if group["name"] == "means":
                group["lr"] = lr

    def lr(self, name: str) -> float:
        return next(g["lr"] for g in self.optimizer.param_groups if g["name"] == name)

    def step(self) -> None:
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)

    def _replace(self, name: str, new_value: torch.Tensor, moment_fn: Callable[[torch.Tensor], torch.Tensor]) -> None:
        """Swap parameter ``name`` for ``new_value``; ``moment_fn`` maps each old Adam moment to the new one."""
        group = next(g for g in self.optimizer.param_groups if g["name"] == name)
        old = group["params"][0]
        new = torch.nn.Parameter(new_value.detach().contiguous())
        state = self.optimizer.state.pop(old, None)
        if state:
            state["exp_avg"] = moment_fn(state["exp_avg"]).contiguous()
            state["exp_avg_sq"] = moment_fn(state["exp_avg_sq"]).contiguous()
            self.optimizer.state[new] = state
        group["params"][0] = new
        setattr(self.model, name, new)

    def append(self, new: GaussianModel) -> None:
        """Add the Gaussians of ``new`` (zero Adam moments, zero density statistics)."""
        count = len(new)
        for name in GaussianModel.PARAM_NAMES:
            old = getattr(self.model, name)
            extra = getattr(new, name).detach().to(old.device, old.dtype)

            def grow(moment: torch.Tensor, extra=extra) -> torch.Tensor:
                return torch.cat([moment, torch.zeros_like(extra)], dim=0)

            self._replace(name, torch.cat([old.detach(), extra], dim=0), grow)
        device = self.model.device
        self.grad_accum = torch.cat([self.grad_accum, torch.zeros(count, device=device)])
        self.grad_count = torch.cat([self.grad_count, torch.zeros(count, device=device)])
        self.max_radii = torch.cat([self.max_radii, torch.zeros(count, device=device)])

    def keep(self, mask: torch.Tensor) -> None:
        """Keep only the Gaussians where ``mask`` [N] bool is true (parameters, moments, statistics)."""
        mask = mask.to(self.model.device)
        for name in GaussianModel.PARAM_NAMES:
            old = getattr(self.model, name)
            self._replace(name, old.detach()[mask], lambda moment: moment[mask])
        self.grad_accum = self.grad_accum[mask]
        self.grad_count = self.grad_count[mask]
        self.max_radii = self.max_radii[mask]

    # --- density control -----------------------------------------------------------------------
    @torch.no_grad()
    def add_stats(self, means2d_grad: torch.Tensor, visible: torch.Tensor, radii: torch.Tensor,
                  width: int, height: int) -> None:
        """Accumulate one view's density statistics.

        Args:
            means2d_grad: [N, 2] gradient of the loss w.r.t. the projected centres (pixels).
            visible: [N] bool, Gaussians the view rendered.
            radii: [N] screen radii (pixels) in the view.
            width, height: image size; the gradient is converted to NDC units (x W/2, x H/2).
        """
        scale = torch.tensor([width / 2.0, height / 2.0], device=means2d_grad.device, dtype=means2d_grad.dtype)
        norms = (means2d_grad * scale).norm(dim=-1)
        self.grad_accum[visible] += norms[visible]
        self.grad_count[visible] += 1
        self.max_radii[visible] = torch.maximum(self.max_radii[visible], radii[visible].to(self.max_radii.dtype))

    @torch.no_grad()
    def mean_grads(self) -> torch.Tensor:
        """[N] mean NDC positional gradient since the last densification (0 where never seen)."""
        return torch.where(self.grad_count > 0, self.grad_accum / self.grad_count.clamp_min(1), torch.zeros_like(self.grad_accum))

    @torch.no_grad()
    def densify_and_prune(self, use_size_limits: bool, generator: torch.Generator | None = None,
                          prune_by_opacity: bool = True) -> dict[str, int]:
        """One 2DGS densification step: clone, split, then prune; resets the statistics.

        Args:
            use_size_limits: also prune Gaussians larger than ``max_screen_size`` pixels or
                ``max_world_size`` x extent (2DGS: after the first opacity reset).
            generator: random source for the split positions.
            prune_by_opacity: prune Gaussians with opacity below ``opacity_cull`` (off shortly
                after an opacity reset).
        Returns:
            counts {"cloned", "split", "pruned", "total"}.
        """
        p = self.params
        grads = self.mean_grads()
        max_scale = self.model.scales.max(dim=1).values
        high_grad = grads >= p.densify_grad_threshold
        room = max(0, p.max_gaussians - len(self))
        clone_mask = high_grad & (max_scale <= p.percent_dense * self.extent)
        split_mask = high_grad & (max_scale > p.percent_dense * self.extent)
        clone_mask, split_mask = _limit_growth(clone_mask, split_mask, grads, room, p.split_count)

        n_before = len(self)
        cloned = int(clone_mask.sum())
        if cloned:
            self.append(self.model.subset(clone_mask))
            split_mask = torch.cat([split_mask, torch.zeros(cloned, dtype=torch.bool, device=split_mask.device)])
        split = int(split_mask.sum())
        if split:
            self.append(split_gaussians(self.model.subset(split_mask), p.split_count, generator))
            keep = torch.cat([~split_mask, torch.ones(split * p.split_count, dtype=torch.bool, device=split_mask.device)])
            self.keep(keep)

        prune_mask = self.model.opacities < p.opacity_cull
        if not prune_by_opacity:
            prune_mask[:] = False
        if use_size_limits:
            prune_mask |= self.max_radii > p.max_screen_size
            prune_mask |= self.model.scales.max(dim=1).values > p.max_world_size * self.extent
        if bool(prune_mask.all()):
            log.warning("density control would prune all %d Gaussians; keeping them", len(self))
            prune_mask[:] = False
        pruned = int(prune_mask.sum())
        if pruned:
            self.keep(~prune_mask)
        self.reset_stats()
        log.debug("densify: %d -> %d (cloned %d, split %d, pruned %d)", n_before, len(self), cloned, split, pruned)
        return {"cloned": cloned, "split": split, "pruned": pruned, "total": len(self)}

    @torch.no_grad()
    def reset_opacity(self, max_opacity: float = 0.01) -> None:
        """Clamp every opacity to at most ``max_opacity`` and zero its Adam moments (3DGS reset)."""
        logits = self.model.opacity_logits.detach()
        limit = math.log(max_opacity / (1.0 - max_opacity))
        self._replace("opacity_logits", torch.minimum(logits, torch.full_like(logits, limit)), torch.zeros_like)


def _limit_growth(clone_mask: torch.Tensor, split_mask: torch.Tensor, grads: torch.Tensor, room: int,
                  split_count: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Keep the highest-gradient candidates so that the model grows by at most ``room`` Gaussians."""
    growth = int(clone_mask.sum()) + int(split_mask.sum()) * (split_count - 1)
    if growth <= room:
        return clone_mask, split_mask
    candidates = torch.nonzero(clone_mask | split_mask).squeeze(1)
    order = candidates[torch.argsort(grads[candidates], descending=True)]
    cost = torch.where(split_mask[order], split_count - 1, 1)
    chosen = order[torch.cumsum(cost, 0) <= room]
    keep = torch.zeros_like(clone_mask)
    keep[chosen] = True
    return clone_mask & keep, split_mask & keep


def split_gaussians(parents: GaussianModel, count: int, generator: torch.Generator | None = None) -> GaussianModel:
    """Replace each parent by ``count`` children (the 2DGS split).

    Children sample their centres from the parent disk (normal with std s_u, s_v along t_u, t_v and
    0 along the normal), shrink the scales by 1 / (0.8 count) and copy rotation, opacity and colour.

    Args:
        parents: M Gaussians.
    Returns:
        M * count Gaussians (children of parent i at rows i, M + i, 2M + i, ...).
    """
    scales = parents.scales.repeat(count, 1)
    stds = torch.cat([scales, torch.zeros_like(scales[:, :1])], dim=1)
    noise = torch.randn(stds.shape, generator=generator, device="cpu").to(stds.device)
    offsets = noise * stds
    rotations = quat_to_rotmat(parents.quats).repeat(count, 1, 1)
    means = torch.bmm(rotations, offsets[..., None])[..., 0] + parents.means.repeat(count, 1)
    return GaussianModel(
        means=means,
        quats=parents.quats.repeat(count, 1),
        log_scales=torch.log(scales / (0.8 * count)),
        opacity_logits=parents.opacity_logits.repeat(count),
        sh_dc=parents.sh_dc.repeat(count, 1, 1),
        sh_rest=parents.sh_rest.repeat(count, 1, 1),
    )


def screen_radii(model: GaussianModel, camera: Camera) -> torch.Tensor:
    """[N] approximate 3-sigma screen radius (pixels) of every Gaussian in ``camera`` (0 behind it)."""
    with torch.no_grad():
        rot = torch.as_tensor(camera.rotation, dtype=model.means.dtype, device=model.device)
        trans = torch.as_tensor(camera.translation, dtype=model.means.dtype, device=model.device)
        depth = model.means.detach() @ rot[2] + trans[2]
        focal = float(max(camera.K[0, 0], camera.K[1, 1]))
        radius = 3.0 * model.scales.detach().max(dim=1).values * focal / depth.clamp_min(1e-6)
        return torch.where(depth > 0, radius, torch.zeros_like(radius))


# ----------------------------------------------------------------------------------------------
# Training loop
# ----------------------------------------------------------------------------------------------


@dataclass
class TrainResult:
    """What :func:`fit` returns.

    Attributes:
        model: the trained Gaussians (detached, on the training device).
        history: logged rows (iteration, loss terms, psnr, gaussians, seconds).
        seconds: wall time of the loop.
        densify_events: the counts returned by every densification step.
    """

    model: GaussianModel
    history: list[dict]
    seconds: float
    densify_events: list[dict]


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError("params.device: 'cuda' was requested but torch sees no CUDA device.")
    return torch.device(name)


def render_view(model: GaussianModel, camera: Camera, sh_degree: int, background: torch.Tensor | None,
                near: float = 0.01, with_distortion: bool = False):
    """Render ``model`` (colours from SH up to ``sh_degree``) into ``camera``; the renderer's RenderOutput."""
    from .render import render

    colors = model.colors(torch.as_tensor(camera.center, dtype=model.means.dtype, device=model.device), sh_degree)
    return render(model.splats(), camera, colors, background, near=near, with_distortion=with_distortion)


def fit(
    model: GaussianModel,
    cameras: Sequence[Camera],
    images: Sequence[torch.Tensor],
    params: TrainParams,
    extent: float | None = None,
    progress: bool = True,
    callback: Callable[[int, "GaussianOptimizer"], None] | None = None,
) -> TrainResult:
    """Optimise ``model`` on the training views.

    Args:
        model: initial Gaussians.
        cameras: L training cameras.
        images: L ground-truth images, each [H, W, 3] float in [0, 1] matching its camera.
        params: training parameters (the schedule is scaled by ``params.schedule_scale``).
        extent: scene extent for the learning rate and size thresholds (default: from the cameras,
            and from the initial Gaussians when ``params.extent`` is "auto").
        progress: show a tqdm bar.
        callback: called as ``callback(iteration, state)`` after every logged iteration (monitoring).
    Returns:
        a :class:`TrainResult`.
    Raises:
        TrainingDiverged: on a non-finite loss, gradient or parameter.
    """
    if len(cameras) == 0 or len(cameras) != len(images):
        raise Trace3DError(f"fit: need one image per camera and at least one view, got {len(cameras)} cameras and {len(images)} images.")
    for cam, img in zip(cameras, images):
        if tuple(img.shape) != (cam.height, cam.width, 3):
            raise Trace3DError(f"fit: image of frame {cam.name!r} has shape {tuple(img.shape)}, expected ({cam.height}, {cam.width}, 3).")
    device = resolve_device(params.device)
    torch.manual_seed(params.seed)
    if extent is None:
        extent = scene_extent(cameras)
        if params.extent == "auto":
            extent = max(extent, points_extent(model.means, cameras))
    extent = float(extent)
    images = [img.to(device=device, dtype=torch.float32) for img in images]
    np.finfo(np.float32), np.finfo(np.float64)  # compute numpy's float limits before flushing denormals
    flushing = params.flush_denormals and torch.set_flush_denormal(True)
    try:
        with torch_threads(params.torch_threads):
            return _fit_loop(model, cameras, images, params, extent, progress, device, callback)
    finally:
        if flushing:
            torch.set_flush_denormal(False)


@contextlib.contextmanager
def torch_threads(count: int):
    """Run the block with ``count`` torch intra-op threads (0: unchanged), restoring the setting after."""
    previous = torch.get_num_threads()
    if count > 0:
        torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def _fit_loop(model: GaussianModel, cameras: Sequence[Camera], images: list[torch.Tensor], params: TrainParams,
              extent: float, progress: bool, device: torch.device,
              callback: Callable[[int, "GaussianOptimizer"], None] | None) -> TrainResult:
    schedule = params.schedule()
    generator = torch.Generator().manual_seed(params.seed)
    rng = np.random.default_rng(params.seed)
    state = GaussianOptimizer(model.to(device), params, extent)
    fixed_background = torch.tensor(params.background, dtype=torch.float32, device=device)

    history: list[dict] = []
    densify_events: list[dict] = []
    checkpoint, checkpoint_iteration = state.model.detached_copy("cpu"), 0
    order: list[int] = []
    active_sh = 0
    last_reset = -params.opacity_reset_grace
    start = time.perf_counter()
    sums = {"loss": 0.0, "l1": 0.0, "ssim": 0.0, "normal": 0.0, "distortion": 0.0, "psnr": 0.0}
    sums_count = 0
    iterations = schedule["iterations"]
    interactive = sys.stderr.isatty()
    bar = tqdm(range(1, iterations + 1), desc="2DGS fit", disable=not progress, dynamic_ncols=True, leave=False,
               mininterval=0.5 if interactive else 30.0)  # log files get a line every 30 s
    for iteration in bar:
        state.set_position_lr(exponential_lr(iteration, params.position_lr_init * extent,
                                             params.position_lr_final * extent, iterations))
        if iteration % schedule["sh_degree_interval"] == 0:
            active_sh = min(active_sh + 1, params.sh_degree)
        if not order:
            order = list(rng.permutation(len(cameras)))
        view = int(order.pop())
        camera, target = cameras[view], images[view]
        background = torch.rand(3, generator=generator).to(device) if params.random_background else fixed_background

        lambda_normal = params.lambda_normal if iteration > schedule["normal_from"] else 0.0
        lambda_dist = params.lambda_distortion if iteration > schedule["distortion_from"] else 0.0
        out = render_view(state.model, camera, active_sh, background, params.near, with_distortion=lambda_dist > 0)
        photo, l1, s = photometric_loss(out.features, target, params.lambda_dssim)
        loss = photo
        normal_term = torch.zeros((), device=device)
        dist_term = torch.zeros((), device=device)
        if lambda_normal > 0:
            covered = out.alpha > 1e-6
            expected = torch.where(covered, out.depth / out.alpha.clamp_min(1e-6), torch.zeros_like(out.depth))
            surface_depth = expected * (1.0 - params.depth_ratio) + out.median_depth * params.depth_ratio
            surface_normal = depth_to_normal(surface_depth, camera.K)
            normal_term = normal_consistency_loss(out.normal, surface_normal, out.alpha)
            loss = loss + lambda_normal * normal_term
        if lambda_dist > 0:
            dist_term = out.distortion.mean()
            loss = loss + lambda_dist * dist_term

        if not torch.isfinite(loss):
            _diverged(f"the loss became {float(loss.detach())} at iteration {iteration}", iteration, checkpoint,
                      checkpoint_iteration, history)
        loss.backward()

        with torch.no_grad():
            if params.densify and iteration < schedule["densify_until"]:
                grad2d = out.means2d.grad if out.means2d.grad is not None else torch.zeros_like(out.means2d)
                radii = out.radii if getattr(out, "radii", None) is not None else screen_radii(state.model, camera)
                state.add_stats(grad2d, out.visible, radii, camera.width, camera.height)
                if iteration > schedule["densify_from"] and iteration % schedule["densify_interval"] == 0:
                    event = state.densify_and_prune(
                        iteration > schedule["opacity_reset_interval"], generator,
                        prune_by_opacity=iteration - last_reset >= params.opacity_reset_grace)
                    event["iteration"] = iteration
                    densify_events.append(event)
                if iteration % schedule["opacity_reset_interval"] == 0:
                    state.reset_opacity()
                    last_reset = iteration
            state.step()
            if not state.model.is_finite():  # also catches non-finite gradients (Adam propagates them)
                _diverged(f"a parameter became non-finite at iteration {iteration}", iteration, checkpoint,
                          checkpoint_iteration, history)
            if iteration % schedule["checkpoint_interval"] == 0:
                checkpoint, checkpoint_iteration = state.model.detached_copy("cpu"), iteration

        sums_count += 1
        for key, value in (("loss", loss), ("l1", l1), ("ssim", s), ("normal", normal_term), ("distortion", dist_term)):
            sums[key] += float(value.detach())
        sums["psnr"] += psnr(out.features.detach().clamp(0, 1), target, exact=False)
        if iteration % params.log_interval == 0 or iteration == iterations:
            row = {"iteration": iteration, **{k: v / sums_count for k, v in sums.items()},
                   "gaussians": len(state), "sh_degree": active_sh, "seconds": time.perf_counter() - start}
            history.append(row)
            sums = dict.fromkeys(sums, 0.0)
            sums_count = 0
            bar.set_postfix(loss=f"{row['loss']:.4f}", psnr=f"{row['psnr']:.2f}", n=len(state), refresh=False)
            if callback is not None:
                callback(iteration, state)
    bar.close()
    seconds = time.perf_counter() - start
    trained = state.model.detached_copy()
    return TrainResult(model=trained, history=history, seconds=seconds, densify_events=densify_events)


def _diverged(reason: str, iteration: int, checkpoint: GaussianModel, checkpoint_iteration: int,
              history: list[dict]) -> None:
    raise TrainingDiverged(f"2DGS training diverged: {reason}.", iteration, checkpoint, checkpoint_iteration, history)


# ----------------------------------------------------------------------------------------------
# Evaluation
# ----------------------------------------------------------------------------------------------


@torch.no_grad()
def evaluate_views(model: GaussianModel, cameras: Sequence[Camera], images: Sequence[torch.Tensor],
                   sh_degree: int, background: torch.Tensor | None, near: float = 0.01) -> tuple[list[dict], list[torch.Tensor]]:
    """PSNR / SSIM of every view.

    Returns:
        per-view rows {"name", "psnr", "ssim"} and the renders ([H, W, 3] clamped to [0, 1], CPU).
    """
    rows, renders = [], []
    for cam, target in zip(cameras, images):
        out = render_view(model, cam, sh_degree, background, near)
        image = out.features.clamp(0.0, 1.0)
        target = target.to(image.device)
        rows.append({"name": cam.name, "psnr": psnr(image, target), "ssim": float(ssim(image, target))})
        renders.append(image.cpu())
    return rows, renders


# ----------------------------------------------------------------------------------------------
# The pipeline step
# ----------------------------------------------------------------------------------------------


def read_pose_cameras(poses_dir: Path, scene: Scene) -> list[Camera]:
    """The cameras of ``poses_dir/cameras.json`` for the scene's frames, in the scene's frame order.

    Raises if a test view is missing (the poses step must not drop evaluation views); train views
    that SfM did not register are skipped with a warning.
    """
    path = poses_dir / "cameras.json"
    if not path.is_file():
        raise SceneFormatError(f"{path}: poses cameras.json is missing.")
    by_name = {cam.name: cam for cam in read_cameras(path)}
    unknown = sorted(set(by_name) - {c.name for c in scene.cameras})
    if unknown:
        raise SceneFormatError(f"{path}: frames {unknown[:5]} are not in the scene {scene.root}.")
    missing_test = [c.name for c in scene.test_cameras if c.name not in by_name]
    if missing_test:
        raise SceneFormatError(f"{path}: test views {missing_test[:5]} have no pose ({len(missing_test)} missing).")
    missing_train = [c.name for c in scene.train_cameras if c.name not in by_name]
    if missing_train:
        log.warning("%s: %d train views have no pose and are skipped: %s", path, len(missing_train), missing_train[:5])
    cameras = []
    for scene_cam in scene.cameras:
        cam = by_name.get(scene_cam.name)
        if cam is None:
            continue
        if (cam.width, cam.height) != (scene_cam.width, scene_cam.height):
            raise SceneFormatError(
                f"{path}: frame {cam.name!r} is {cam.width}x{cam.height} but its image is {scene_cam.width}x{scene_cam.height}."
            )
        cam.split = scene_cam.split  # the scene owns the split
        cameras.append(cam)
    return cameras


def initial_model(scene: Scene, poses_dir: Path | None, train_cameras: Sequence[Camera], params: TrainParams,
                  extent: float) -> tuple[GaussianModel, str]:
    """The initial Gaussians and the name of the initialisation used.

    ``init: auto`` takes the SfM points when ``poses_dir`` has ``points3D.ply``, else the depth maps
    when the scene has them, else a random box around the cameras.
    """
    points_path = poses_dir / "points3D.ply" if poses_dir is not None else None
    method = params.init
    if method == "auto":
        if points_path is not None and points_path.is_file():
            method = "points"
        elif scene.has_depth:
            method = "depth"
        else:
            method = "random"
    if method == "points":
        if points_path is None:
            raise ConfigError("params.init: 'points' needs a poses folder (--poses) with points3D.ply.")
        from .pointcloud import read_points_ply

        xyz, rgb = read_points_ply(points_path)
        if len(xyz) == 0:
            raise SceneFormatError(f"{points_path}: the SfM point cloud is empty.")
        if len(xyz) > params.init_max_points:
            keep = np.random.default_rng(params.seed).permutation(len(xyz))[: params.init_max_points]
            xyz, rgb = xyz[keep], rgb[keep]
        model = init_from_points(xyz, rgb, sh_degree=params.sh_degree, opacity=params.init_opacity, seed=params.seed)
    elif method == "depth":
        model = init_from_depth(scene, train_cameras, stride=params.depth_init_stride, max_points=params.init_max_points,
                                sh_degree=params.sh_degree, opacity=params.init_opacity, seed=params.seed)
    else:
        centers = np.stack([c.center for c in train_cameras])
        margin = params.random_init_margin * extent
        model = init_random(params.random_init_count, centers.min(0) - margin, centers.max(0) + margin,
                            sh_degree=params.sh_degree, opacity=params.init_opacity, seed=params.seed)
    log.info("initialised %d Gaussians from %s", len(model), method)
    return model, method


def failed_dir_for(out_dir: Path) -> Path:
    """Where a failed run keeps its last good checkpoint: ``<final name>.failed`` beside ``out_dir``.

    ``out_dir`` is usually the CLI's temporary sibling ``.<name>.tmp-<pid>-<hex>`` of the final
    folder; the final name is recovered from it.
    """
    match = re.fullmatch(r"\.(.+)\.tmp-\d+-[0-9a-f]+", out_dir.name)
    name = match.group(1) if match else out_dir.name
    return out_dir.parent / f"{name}.failed"


def load_images(scene: Scene, cameras: Sequence[Camera]) -> list[torch.Tensor]:
    """[H, W, 3] float images in [0, 1] for ``cameras`` (by frame name)."""
    return [torch.from_numpy(scene.image(c.name)).float() / 255.0 for c in cameras]


def write_history_csv(path: Path, history: list[dict]) -> None:
    columns = ["iteration", "loss", "l1", "ssim", "normal", "distortion", "psnr", "gaussians", "sh_degree", "seconds"]
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=columns)
        writer.writeheader()
        for row in history:
            writer.writerow({k: (f"{row[k]:.6g}" if isinstance(row[k], float) else row[k]) for k in columns})


def plot_history(path: Path, history: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    its = [r["iteration"] for r in history]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    axes[0].plot(its, [r["loss"] for r in history], label="total")
    axes[0].plot(its, [r["l1"] for r in history], label="L1")
    axes[0].set_yscale("log")
    axes[0].set_title("loss")
    axes[0].legend()
    axes[1].plot(its, [r["psnr"] for r in history])
    axes[1].set_title("train PSNR (dB, running)")
    axes[2].plot(its, [r["gaussians"] for r in history])
    axes[2].set_title("Gaussians")
    for ax in axes:
        ax.set_xlabel("iteration")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_renders(path: Path, names: Sequence[str], renders: Sequence[torch.Tensor], targets: Sequence[torch.Tensor],
                 rows: Sequence[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    count = len(renders)
    fig, axes = plt.subplots(count, 3, figsize=(10, 2.7 * count), squeeze=False)
    for i in range(count):
        target = targets[i].cpu().numpy()
        image = renders[i].numpy()
        error = np.abs(image - target).mean(axis=-1)
        axes[i, 0].imshow(target)
        axes[i, 0].set_title(f"{names[i]}: ground truth", fontsize=8)
        axes[i, 1].imshow(image)
        axes[i, 1].set_title(f"render, PSNR {rows[i]['psnr']:.2f} dB", fontsize=8)
        axes[i, 2].imshow(error, cmap="magma", vmin=0, vmax=0.25)
        axes[i, 2].set_title("|error| (0 .. 0.25)", fontsize=8)
        for ax in axes[i]:
            ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run_gaussians(scene: Scene, poses_dir: Path | None, out_dir: Path, params: dict) -> None:
    """The ``gaussians`` pipeline step: fit 2DGS to the scene's train views and evaluate the test views.

    Args:
        scene: the canonical scene (images; cameras unless ``poses_dir`` is given).
        poses_dir: optional poses folder: its ``cameras.json`` replaces the scene's cameras and its
            ``points3D.ply`` initialises the Gaussians (``init: auto``/``points``).
        out_dir: output folder (a temporary folder the CLI renames).
        params: raw parameter mapping, parsed into :class:`TrainParams`.

    Writes into ``out_dir``: point_cloud.ply, cameras.json (the cameras the model lives with),
    train.csv, metrics.json, config.json, train_curve.png, renders.png. On divergence, writes the
    last good checkpoint to :func:`failed_dir_for` and raises :class:`~trace3d.errors.Trace3DError`.
    """
    p = from_mapping(TrainParams, params, "gaussians params")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    cameras = read_pose_cameras(Path(poses_dir), scene) if poses_dir is not None else list(scene.cameras)
    train_cameras = [c for c in cameras if c.split == "train"]
    test_cameras = [c for c in cameras if c.split == "test"]
    if not train_cameras:
        raise SceneFormatError(f"{scene.root}: the scene has no train views to fit.")
    extent = scene_extent(train_cameras)
    model, init_method = initial_model(scene, Path(poses_dir) if poses_dir is not None else None, train_cameras, p, extent)
    if p.extent == "auto":
        extent = max(extent, points_extent(model.means, train_cameras))
    log.info("scene extent %.3f (%s)", extent, p.extent)
    train_images = load_images(scene, train_cameras)
    log.info("fitting 2DGS to %d train views (%d test views), schedule %s", len(train_cameras), len(test_cameras), p.schedule())

    start = time.perf_counter()
    try:
        result = fit(model, train_cameras, train_images, p, extent=extent)
    except TrainingDiverged as exc:
        failed = failed_dir_for(out_dir)
        failed.mkdir(parents=True, exist_ok=True)
        exc.checkpoint.write_ply(failed / "checkpoint_last_good.ply")
        write_history_csv(failed / "train.csv", exc.history)
        write_json(failed / "failure.json", {"reason": str(exc), "iteration": exc.iteration,
                                             "checkpoint_iteration": exc.checkpoint_iteration,
                                             "params": to_dict(p)})
        raise Trace3DError(
            f"{scene.root}: {exc} The last good checkpoint (iteration {exc.checkpoint_iteration}) is kept in "
            f"{failed / 'checkpoint_last_good.ply'}."
        ) from exc

    device = result.model.device
    background = torch.tensor(p.background, dtype=torch.float32, device=device)
    test_images = load_images(scene, test_cameras)
    with torch_threads(p.torch_threads):
        test_rows, test_renders = evaluate_views(result.model, test_cameras, test_images, p.sh_degree, background, p.near)
        train_rows, _ = evaluate_views(result.model, train_cameras, train_images, p.sh_degree, background, p.near)
    minutes = (time.perf_counter() - start) / 60.0

    result.model.write_ply(out_dir / "point_cloud.ply")
    from .scene import write_cameras

    write_cameras(out_dir, cameras)
    write_history_csv(out_dir / "train.csv", result.history)
    metrics = {
        "test_psnr": float(np.mean([r["psnr"] for r in test_rows])) if test_rows else None,
        "test_ssim": float(np.mean([r["ssim"] for r in test_rows])) if test_rows else None,
        "train_psnr": float(np.mean([r["psnr"] for r in train_rows])),
        "train_ssim": float(np.mean([r["ssim"] for r in train_rows])),
        "num_gaussians": len(result.model),
        "iterations": p.scaled("iterations"),
        "minutes": minutes,
        "train_minutes": result.seconds / 60.0,
        "init": init_method,
        "num_train_views": len(train_cameras),
        "num_test_views": len(test_cameras),
        "device": str(device),
        "test_views": test_rows,
    }
    write_json(out_dir / "metrics.json", metrics)
    write_json(out_dir / "config.json", {"params": to_dict(p), "schedule": p.schedule(), "extent": extent,
                                         "init": init_method, "device": str(device),
                                         "poses": str(poses_dir) if poses_dir is not None else None,
                                         "scene": str(scene.root)})
    if result.history:
        plot_history(out_dir / "train_curve.png", result.history)
    shown = min(p.num_render_views, len(test_cameras))
    if shown:
        picks = np.linspace(0, len(test_cameras) - 1, shown).round().astype(int)
        plot_renders(out_dir / "renders.png", [test_cameras[i].name for i in picks], [test_renders[i] for i in picks],
                     [test_images[i] for i in picks], [test_rows[i] for i in picks])
    log.info("2DGS: %d Gaussians, test PSNR %s dB, %.1f min", len(result.model),
             f"{metrics['test_psnr']:.2f}" if metrics["test_psnr"] is not None else "n/a", minutes)
