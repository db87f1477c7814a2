"""Parameters of the 2DGS fit (:class:`TrainParams`).

The defaults follow the 2DGS reference training (Huang et al. 2024), scaled so that the synthetic
benchmark rooms train in minutes on 2 CPU cores; see the class and :meth:`TrainParams.reference_2dgs`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal


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
    initial_sh_degree: int = 0  # SH degree active at iteration 1 (a fine-tune of a fitted scene starts at sh_degree)
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
    fused_adam: bool = True  # torch's fused Adam kernel (same update up to rounding; several times faster)
    # Adam on the Gaussians the view rendered only (as gsplat's "visible Adam"): the others keep their
    # parameters and moments unchanged instead of drifting on their momentum; the bias corrections
    # count every step. Off by default: it changes the fit (docs/history/performance.md has the comparison).
    visible_adam: bool = False
    # Compact gradients on the CPU renderer: the backward works on the Gaussians the view sees only
    # and Adam gets them through dense gradient buffers (trace3d.training.sparse); the same update
    # bit for bit, faster. Off: the dense autograd path over all N (the reference for the tests).
    sparse_grad: bool = True
    # torch intra-op threads during training (0 = leave torch's setting). The heavy work is in the
    # rasterizer's numba kernels, which run their own threads; torch's OpenMP threads spin-waiting
    # beside them made an iteration 15x slower on a busy 2-core machine (5.0 vs 0.33 s at 80k splats).
    torch_threads: int = 1
    # The CPU rasterizer's backward deals the tiles to this many gradient buffers, summed in order:
    # the fit's bits depend on this number, never on the thread count (--threads), so a 1-thread and
    # a 2-thread job give the same files. At most this many threads share the backward; more buffers
    # give other bits, as deterministic (trace3d.render.gradient_buffers).
    grad_buffers: int = 2

    # each field's range: refused on input and in the config schema (trace3d.params.check_ranges)
    RANGES = {"iterations": ">= 1", "densify_interval": ">= 1", "opacity_reset_interval": ">= 1",
              "sh_degree_interval": ">= 1", "checkpoint_interval": ">= 1", "init_max_points": ">= 1",
              "depth_init_stride": ">= 1", "random_init_count": ">= 1", "split_count": ">= 1",
              "max_gaussians": ">= 1", "log_interval": ">= 1", "grad_buffers": ">= 1", "schedule_scale": "> 0",
              "sh_degree": "[0, 3]", "initial_sh_degree": "[0, 3]", "init_opacity": "(0, 1)",
              "lambda_dssim": "[0, 1]", "depth_ratio": "[0, 1]", "position_lr_init": ">= 0",
              "position_lr_final": ">= 0", "feature_lr": ">= 0", "opacity_lr": ">= 0", "scaling_lr": ">= 0",
              "rotation_lr": ">= 0", "lambda_normal": ">= 0", "lambda_distortion": ">= 0",
              "densify_grad_threshold": ">= 0", "percent_dense": ">= 0", "opacity_cull": ">= 0",
              "max_screen_size": ">= 0", "max_world_size": ">= 0", "near": ">= 0", "opacity_reset_grace": ">= 0",
              "torch_threads": ">= 0", "densify_from": ">= 0", "densify_until": ">= 0", "normal_from": ">= 0",
              "distortion_from": ">= 0", "random_init_margin": ">= 0", "seed": ">= 0"}

    def __post_init__(self) -> None:
        positive = ("iterations", "densify_interval", "opacity_reset_interval", "sh_degree_interval",
                    "checkpoint_interval", "init_max_points", "depth_init_stride", "random_init_count",
                    "split_count", "max_gaussians", "log_interval", "grad_buffers")
        for name in positive:
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not self.schedule_scale > 0:
            raise ValueError(f"schedule_scale must be > 0, got {self.schedule_scale}")
        if not 0 <= self.sh_degree <= 3:
            raise ValueError(f"sh_degree must be in 0..3, got {self.sh_degree}")
        if not 0 <= self.initial_sh_degree <= self.sh_degree:
            raise ValueError(f"initial_sh_degree must be in 0..sh_degree, got {self.initial_sh_degree}")
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
                     "opacity_reset_grace", "torch_threads", "densify_from", "densify_until", "normal_from",
                     "distortion_from",
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

