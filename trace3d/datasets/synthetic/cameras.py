"""The camera loop of a synthetic room: a closed path around the room centre, looking outwards."""

from __future__ import annotations

import math

import numpy as np

from ...scene import Camera
from .params import SyntheticParams


def look_rotation(yaw: float, pitch: float) -> np.ndarray:
    """[3, 3] world-to-camera rotation (OpenCV axes) of a camera looking along ``yaw`` (radians from +x,
    counter-clockwise) with ``pitch`` (radians, positive looks up) in the z-up world."""
    forward = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), math.sin(pitch)])
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return np.stack([right, down, forward])


def intrinsics(params: SyntheticParams) -> np.ndarray:
    """[3, 3] pinhole K with the horizontal field of view ``fov_x_deg`` and square pixels."""
    f = params.width / 2 / math.tan(math.radians(params.fov_x_deg) / 2)
    return np.array([[f, 0.0, params.width / 2], [0.0, f, params.height / 2], [0.0, 0.0, 1.0]])


def camera_trajectory(params: SyntheticParams) -> list[Camera]:
    """A closed loop of ``num_views`` cameras around the room centre, looking outwards.

    Radius, height, pitch and yaw oscillate smoothly (phases from the seed); view i is a test view
    when ``i % test_every == test_every // 2``.
    """
    rng = np.random.default_rng([params.seed, 1])
    phase = rng.uniform(0, 2 * math.pi, 5)
    K = intrinsics(params)
    cameras = []
    for i in range(params.num_views):
        theta = phase[0] + 2 * math.pi * i / params.num_views
        radius = params.camera_radius * (1.0 + 0.25 * math.sin(2 * theta + phase[1]))
        height = params.camera_height + params.camera_height_amplitude * math.sin(3 * theta + phase[2])
        yaw = theta + math.radians(params.camera_yaw_amplitude_deg) * math.sin(2 * theta + phase[3])
        pitch_deg = params.camera_pitch_deg + params.camera_pitch_amplitude_deg * math.sin(3 * theta + phase[4])
        pitch = math.radians(pitch_deg)
        position = np.array([radius * math.cos(theta), radius * math.sin(theta), height])
        rotation = look_rotation(yaw, pitch)
        w2c = np.eye(4)
        w2c[:3, :3] = rotation
        w2c[:3, 3] = -rotation @ position
        split = "test" if i % params.test_every == params.test_every // 2 else "train"
        cameras.append(Camera(name=f"view_{i:03d}", split=split, width=params.width, height=params.height, K=K,
                              world_to_camera=w2c))
    return cameras
