"""The tiny training scene the training tests share: a smoothly textured plane z = 3 seen by cameras on a
small circle (exact images), its points, a short schedule, the scene written as files, and the fixture that
runs these tests single-threaded.  (Split out of the former tests/test_train.py.)"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from trace3d.scene import Camera, Scene, write_cameras, write_frame
from trace3d.training import TrainParams


@pytest.fixture(autouse=True)
def single_thread():
    """Tiny scenes run fastest on one thread, and stay fast on a busy shared machine (parallel
    regions of two threads stall whenever one of them is descheduled)."""
    import numba

    torch_threads, numba_threads = torch.get_num_threads(), numba.get_num_threads()
    torch.set_num_threads(1)
    numba.set_num_threads(1)
    yield
    torch.set_num_threads(torch_threads)
    numba.set_num_threads(numba_threads)


PLANE_Z = 3.0


def look_at(center: np.ndarray, target: np.ndarray) -> np.ndarray:
    z = target - center
    z = z / np.linalg.norm(z)
    x = np.cross(np.array([0.0, 1.0, 0.0]), z)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    w2c = np.eye(4)
    w2c[:3, :3] = np.stack([x, y, z])
    w2c[:3, 3] = -w2c[:3, :3] @ center
    return w2c


def texture(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return np.stack(
        [
            0.5 + 0.35 * np.sin(3 * x + 0.5) * np.cos(2 * y),
            0.5 + 0.35 * np.cos(2.5 * x - 1.5 * y),
            0.45 + 0.3 * np.sin(4 * y + x),
        ],
        axis=-1,
    )


def plane_views(count: int, width: int = 32, height: int = 24, split=lambda i: "train"):
    """``count`` cameras looking at the plane and their exact images [H, W, 3] float."""
    K = np.array([[30.0, 0, width / 2], [0, 30.0, height / 2], [0, 0, 1]])
    cameras, images = [], []
    xs, ys = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    rays_cam = np.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], np.ones_like(xs)], -1)
    for i in range(count):
        angle = 2 * math.pi * i / count
        center = np.array([0.4 * math.cos(angle), 0.3 * math.sin(angle), 0.0])
        cam = Camera(f"v{i:02d}", split(i), width, height, K, look_at(center, np.array([0.0, 0.0, PLANE_Z])))
        rays = rays_cam @ cam.rotation  # camera -> world directions (R^T d)
        t = (PLANE_Z - cam.center[2]) / rays[..., 2]
        hits = cam.center + rays * t[..., None]
        cameras.append(cam)
        images.append(torch.tensor(texture(hits[..., 0], hits[..., 1]), dtype=torch.float32))
    return cameras, images


def plane_points(count: int = 300, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts = np.concatenate([rng.uniform(-2, 2, (count, 2)), np.full((count, 1), PLANE_Z)], 1)
    return pts + rng.normal(0, 0.05, (count, 3))


def tiny_params(**overrides) -> TrainParams:
    values = dict(
        schedule_scale=1.0, iterations=200, densify_from=50, densify_until=150, densify_interval=25,
        opacity_reset_interval=1000, normal_from=100, sh_degree_interval=50, sh_degree=1, device="cpu",
        densify_grad_threshold=0.0002,
    )
    values.update(overrides)
    return TrainParams(**values)


def write_plane_scene(root, count=6):
    cameras, images = plane_views(count, split=lambda i: "test" if i % 3 == 2 else "train")
    for cam, img in zip(cameras, images):
        write_frame(root, cam.name, (img.numpy() * 255).round().astype(np.uint8))
    write_cameras(root, cameras)
    return Scene.read(root)


STEP_PARAMS = {"schedule_scale": 1.0, "iterations": 60, "densify_from": 20, "densify_until": 50,
               "densify_interval": 10, "normal_from": 30, "sh_degree": 1, "sh_degree_interval": 20,
               "random_init_count": 300, "device": "cpu", "num_render_views": 2}
