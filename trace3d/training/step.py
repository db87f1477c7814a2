"""The ``gaussians`` pipeline step: read the scene and poses, initialise, fit, evaluate, write.

Also the pieces other steps reuse: :func:`read_pose_cameras` (the cameras a fitted model lives
with), :func:`load_images`, :func:`failed_dir_for`, the history CSV and plots.
"""

from __future__ import annotations

import csv
import logging
import re
import time
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from ..errors import ConfigError, SceneFormatError, Trace3DError
from ..gaussians import GaussianModel, init_from_depth, init_from_points, init_random
from ..io import write_json
from ..params import from_mapping, to_dict
from ..scene import Camera, Scene, read_cameras, read_pose_cameras, require_known_poses  # noqa: F401 (re-exported)
from ..threads import torch_threads
from .loop import TrainingDiverged, evaluate_views, fit, points_extent, scene_extent
from .params import TrainParams

log = logging.getLogger(__name__)


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
        from ..pointcloud import read_points_ply

        xyz, rgb = read_points_ply(points_path)
        if len(xyz) == 0:
            raise SceneFormatError(f"{points_path}: the SfM point cloud is empty.")
        if len(xyz) > params.init_max_points:
            keep = np.random.default_rng(params.seed).permutation(len(xyz))[: params.init_max_points]
            xyz, rgb = xyz[keep], rgb[keep]
        model = init_from_points(xyz, rgb, sh_degree=params.sh_degree, opacity=params.init_opacity, seed=params.seed)
    elif method == "depth":
        model = init_from_depth(scene, train_cameras, stride=params.depth_init_stride,
                                max_points=params.init_max_points, sh_degree=params.sh_degree,
                                opacity=params.init_opacity, seed=params.seed)
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
    if poses_dir is None:
        require_known_poses(scene, "trace3d gaussians")
    cameras = read_pose_cameras(Path(poses_dir), scene) if poses_dir is not None else list(scene.cameras)
    train_cameras = [c for c in cameras if c.split == "train"]
    test_cameras = [c for c in cameras if c.split == "test"]
    if not train_cameras:
        raise SceneFormatError(f"{scene.root}: the scene has no train views to fit.")
    extent = scene_extent(train_cameras)
    model, init_method = initial_model(scene, Path(poses_dir) if poses_dir is not None else None, train_cameras, p,
                                       extent)
    if p.extent == "auto":
        extent = max(extent, points_extent(model.means, train_cameras))
    log.info("scene extent %.3f (%s)", extent, p.extent)
    train_images = load_images(scene, train_cameras)
    log.info("fitting 2DGS to %d train views (%d test views), schedule %s", len(train_cameras), len(test_cameras),
             p.schedule())

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
        test_rows, test_renders = evaluate_views(result.model, test_cameras, test_images, p.sh_degree, background,
                                                 p.near)
        train_rows, _ = evaluate_views(result.model, train_cameras, train_images, p.sh_degree, background, p.near)
    minutes = (time.perf_counter() - start) / 60.0

    result.model.write_ply(out_dir / "point_cloud.ply")
    from ..scene import write_cameras

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
