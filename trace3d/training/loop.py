"""The 2DGS training loop (:func:`fit`) and per-view evaluation.

The loop follows the 2DGS reference training (Huang et al. 2024), with its defaults:

- Adam (eps 1e-15) with one learning rate per parameter group; the position learning rate decays
  exponentially from ``position_lr_init`` to ``position_lr_final`` (both times the scene extent)
  over the run.
- Loss ``(1 - 0.2) L1 + 0.2 (1 - SSIM)``, plus the normal-consistency term (weight 0.05, from 7k of
  30k iterations) between the rendered normal and the normal of the rendered depth, and the
  optional depth distortion (weight 0 by default, as in the official Trace3D code; from 3k).
- SH degree raised by one every 1000 iterations up to ``sh_degree``.
- Density control by a :class:`~trace3d.training.strategy.Strategy`; the default is the 2DGS one
  (:class:`~trace3d.training.strategy.DefaultStrategy`): from 500 to 15k, every 100 iterations,
  Gaussians whose mean view-space positional gradient (in NDC units, the 3DGS convention) reaches
  a threshold (2DGS: 2e-4) are cloned when small (largest scale at most 1 % of the scene extent) or
  split in two when large; Gaussians with opacity below 0.05, or (after the first opacity reset) a
  screen radius above 20 px or a world scale above 10 % of the extent, are pruned. Opacities are
  reset to at most 0.01 every 3000 iterations. After an opacity reset, pruning by opacity waits
  ``opacity_reset_grace`` (unscaled) iterations, as the reference's next densification does.

Every iteration count and interval above is multiplied by ``schedule_scale`` (1.0 = the 2DGS
reference schedule of 30k iterations); see :class:`~trace3d.training.params.TrainParams`. The CPU
loop flushes denormal floats to zero (``flush_denormals``), which speeds up Adam and the backward
pass several-fold late in training.

Divergence (a non-finite loss, gradient or parameter) stops training with a
:class:`TrainingDiverged` error that carries the last good checkpoint.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import sys
import time
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import torch
from tqdm import tqdm

from ..tooling.compiling import track as track_compile_time
from ..errors import ConfigError, Trace3DError
from ..gaussians import GaussianModel, all_finite
from .kernels.losses import surface_depth
from .losses import depth_normal_consistency, photometric_terms, psnr, ssim
from ..scene import Camera
from ..render import gradient_buffers
from ..threads import torch_threads
from .optimizer import GaussianOptimizer, learning_rates
from .params import TrainParams
from .sparse import CompactView, sparse_applies, visible_rows
from .strategy import DefaultStrategy, Strategy

log = logging.getLogger(__name__)


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


def render_view(model: GaussianModel | CompactView, camera: Camera, sh_degree: int, background: torch.Tensor | None,
                near: float = 0.01, with_distortion: bool = False):
    """Render ``model`` (colours from SH up to ``sh_degree``) into ``camera``; the renderer's RenderOutput.
    ``model`` may be a :class:`~trace3d.training.sparse.CompactView` (the Gaussians a view sees)."""
    from ..render import render

    center = torch.as_tensor(camera.center, dtype=model.means.dtype, device=model.device)
    # colours of the splats the view sees only (the renderer passes their rows)
    return render(model.splats(), camera, lambda rows: model.colors(center, sh_degree, rows), background,
                  near=near, with_distortion=with_distortion)


def fit(
    model: GaussianModel,
    cameras: Sequence[Camera],
    images: Sequence[torch.Tensor],
    params: TrainParams,
    extent: float | None = None,
    progress: bool = True,
    callback: Callable[[int, "GaussianOptimizer"], None] | None = None,
    strategy: Strategy | None = None,
    lrs: dict[str, float] | None = None,
    desc: str = "2DGS fit",
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
        strategy: density control (default: :class:`DefaultStrategy`, the 2DGS one).
        lrs: learning rate by attribute (default: the 2DGS rates of the core parameters; extras
            not named are carried along unoptimised).
        desc: the progress bar's label.
    Returns:
        a :class:`TrainResult`.
    Raises:
        TrainingDiverged: on a non-finite loss, gradient or parameter.
    """
    if len(cameras) == 0 or len(cameras) != len(images):
        raise Trace3DError(f"fit: need one image per camera and at least one view, got {len(cameras)} cameras "
                           f"and {len(images)} images.")
    for cam, img in zip(cameras, images):
        if tuple(img.shape) != (cam.height, cam.width, 3):
            raise Trace3DError(f"fit: image of frame {cam.name!r} has shape {tuple(img.shape)}, "
                               f"expected ({cam.height}, {cam.width}, 3).")
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
        # the default density control runs with the process's torch threads (``--threads``), Adam on
        # optimizer.ADAM_THREADS, the rest of the loop with params.torch_threads (docs/performance.md)
        bulk_threads = torch.get_num_threads()
        with torch_threads(params.torch_threads), gradient_buffers(params.grad_buffers):
            return _fit_loop(model, cameras, images, params, extent, progress, device, callback, strategy, lrs, desc,
                             bulk_threads)
    finally:
        if flushing:
            torch.set_flush_denormal(False)


def _fit_loop(model: GaussianModel, cameras: Sequence[Camera], images: list[torch.Tensor], params: TrainParams,
              extent: float, progress: bool, device: torch.device,
              callback: Callable[[int, "GaussianOptimizer"], None] | None, strategy: Strategy | None,
              lrs: dict[str, float] | None, desc: str, bulk_threads: int = 0) -> TrainResult:
    schedule = params.schedule()
    generator = torch.Generator().manual_seed(params.seed)
    rng = np.random.default_rng(params.seed)
    state = GaussianOptimizer(model.to(device), learning_rates(params, extent) if lrs is None else lrs, params, extent)
    state.bulk_threads = bulk_threads
    strategy = DefaultStrategy(generator) if strategy is None else strategy
    strategy.initialize(state, schedule)
    fixed_background = torch.tensor(params.background, dtype=torch.float32, device=device)
    sparse = params.sparse_grad and sparse_applies(state.model)
    trainable = {g["name"] for g in state.optimizer.param_groups}
    view_model = None

    history: list[dict] = []
    densify_events: list[dict] = []
    checkpoint, checkpoint_iteration = state.model.detached_copy("cpu"), 0
    order: list[int] = []
    active_sh = params.initial_sh_degree
    start = time.perf_counter()
    sums = {"loss": 0.0, "l1": 0.0, "ssim": 0.0, "normal": 0.0, "distortion": 0.0, "psnr": 0.0}
    sums_count = 0
    iterations = schedule["iterations"]
    interactive = sys.stderr.isatty()
    bar = tqdm(range(1, iterations + 1), desc=desc, disable=not progress, dynamic_ncols=True, leave=False,
               mininterval=0.5 if interactive else 30.0)  # log files get a line every 30 s
    track_compile_time(bar)  # the ETA leaves out a first run's kernel compilation
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
        if sparse:  # compact gradients: differentiate the Gaussians the view sees only (trace3d.training.sparse)
            rows, scales, opacities = visible_rows(state.model, camera, params.near)
            view_model = CompactView(state.model, rows, scales, opacities, trainable)
            out = render_view(view_model, camera, active_sh, background, params.near, with_distortion=lambda_dist > 0)
        else:
            out = render_view(state.model, camera, active_sh, background, params.near, with_distortion=lambda_dist > 0)
        photo, l1, s, view_psnr = photometric_terms(out.features, target, params.lambda_dssim)
        loss = photo
        normal_term = torch.zeros((), device=device)
        dist_term = torch.zeros((), device=device)
        if lambda_normal > 0:
            # (1 - r) expected depth + r median depth, 0 where nothing was rendered
            surface = surface_depth(out.depth, out.alpha, out.median_depth, params.depth_ratio)
            normal_term = depth_normal_consistency(out.normal, surface, out.alpha, camera.K)
            loss = loss + lambda_normal * normal_term
        if lambda_dist > 0:
            dist_term = out.distortion.mean()
            loss = loss + lambda_dist * dist_term

        if not torch.isfinite(loss):
            _diverged(f"the loss became {float(loss.detach())} at iteration {iteration}", iteration, checkpoint,
                      checkpoint_iteration, history)
        loss.backward()

        with torch.no_grad():
            # with compact gradients the render's per-splat outputs are per row of view_model.rows
            seen = dataclasses.replace(out, rows=view_model.rows) if sparse else out
            event = strategy.after_backward(iteration, state, seen, camera)
            edited = bool(event)
            if event:
                densify_events.append({**event, "iteration": iteration})
            if sparse:
                grads = view_model.grads()
                state.sparse_step(view_model.rows, grads, view_model.sources, out.visible)
            else:
                state.step(out.visible)
            event = strategy.after_step(iteration, state)
            edited = edited or bool(event)
            if event:
                densify_events.append({**event, "iteration": iteration})
            checkpointing = iteration % schedule["checkpoint_interval"] == 0
            if sparse and not (edited or checkpointing or iteration == iterations):
                # the view's gradients (the rows it saw): a non-finite one is what makes a parameter
                # non-finite in a step (Adam propagates it to that row), and it is caught here in the
                # same iteration without a pass over every parameter; all parameters are checked
                # before each checkpoint, after density control and at the end
                finite = all_finite(grads.values())
            else:
                finite = state.model.is_finite()  # also catches non-finite gradients (Adam propagates them)
            if not finite:
                _diverged(f"a parameter became non-finite at iteration {iteration}", iteration, checkpoint,
                          checkpoint_iteration, history)
            if checkpointing:
                checkpoint, checkpoint_iteration = state.model.detached_copy("cpu"), iteration

        sums_count += 1
        for key, value in (("loss", loss), ("l1", l1), ("ssim", s), ("normal", normal_term), ("distortion", dist_term)):
            sums[key] += float(value.detach())
        sums["psnr"] += view_psnr
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
                   sh_degree: int, background: torch.Tensor | None,
                   near: float = 0.01) -> tuple[list[dict], list[torch.Tensor]]:
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

