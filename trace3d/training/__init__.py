"""2DGS training: parameters, the optimiser, density-control strategies, the loop and the step.

    params.py     TrainParams (the 2DGS schedule, scaled)
    optimizer.py  GaussianOptimizer: Adam over every attribute of a GaussianModel, append / keep / edit
    strategy.py   Strategy hooks and the 2DGS adaptive density control (DefaultStrategy)
    loop.py       fit(): the photometric training loop; evaluate_views()
    step.py       run_gaussians(): the `gaussians` pipeline step and its files
"""

from ..threads import torch_threads
from .loop import (TrainingDiverged, TrainResult, evaluate_views, exponential_lr, fit, points_extent,
                   render_view, resolve_device, scene_extent)
from .optimizer import GaussianOptimizer, learning_rates
from .params import TrainParams
from .step import failed_dir_for, load_images, read_pose_cameras, run_gaussians
from .strategy import DefaultStrategy, Strategies, Strategy, densify_and_prune, split_gaussians

__all__ = [
    "DefaultStrategy", "GaussianOptimizer", "Strategies", "Strategy", "TrainParams", "TrainResult",
    "TrainingDiverged", "densify_and_prune", "evaluate_views", "exponential_lr", "failed_dir_for", "fit",
    "learning_rates", "load_images", "points_extent", "read_pose_cameras", "render_view", "resolve_device",
    "run_gaussians", "scene_extent", "split_gaussians", "torch_threads",
]
