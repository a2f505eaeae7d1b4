"""Gravity from the IMU: turn an estimated trajectory's world so that its z axis points up.

An accelerometer reads the specific force, acceleration minus gravity, in the camera's axes.
Rotated into the world by the camera's orientation and averaged over a recording, the
hand's accelerations cancel out and what is left points up. Structure from motion leaves the
world's orientation arbitrary; this fixes its tilt (the heading stays arbitrary).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evcap.errors import InputError
from evcap.records import Poses

GRAVITY = 9.80665  # m/s^2
MIN_SAMPLES = 50


@dataclass
class Gravity:
    up: np.ndarray  # [3] unit vector: up, in the estimated world's axes
    samples: int
    spread_deg: float  # median angle between a sample's force and the mean: the hand's share
    magnitude: float  # |mean specific force| (m/s^2): about 9.81 when the estimate holds


def gravity_up(track: Poses, imu_t: np.ndarray, accel: np.ndarray) -> Gravity:
    """Where up is in the track's world, from the accelerometer samples during the track."""
    imu_t, accel = np.asarray(imu_t, np.int64), np.asarray(accel, np.float64)
    inside = (imu_t >= track.start) & (imu_t <= track.end) & np.isfinite(accel).all(axis=1)
    if inside.sum() < MIN_SAMPLES:
        raise InputError(
            f"only {int(inside.sum())} IMU samples during the poses (at least {MIN_SAMPLES} "
            "are needed to find gravity); record with the IMU on, or leave the poses unaligned"
        )
    R = track.at(imu_t[inside])[:, :3, :3]
    force = np.einsum("nij,nj->ni", R, accel[inside])
    mean = force.mean(axis=0)
    magnitude = float(np.linalg.norm(mean))
    if magnitude < 0.5 * GRAVITY:
        raise InputError(
            f"the accelerometer's mean in the estimated world is {magnitude:.2f} m/s^2, far from "
            "gravity's 9.81: the poses and the IMU disagree (is the IMU in the camera's axes?)"
        )
    up = mean / magnitude
    unit = force / np.maximum(np.linalg.norm(force, axis=1, keepdims=True), 1e-12)
    spread = float(np.degrees(np.median(np.arccos(np.clip(unit @ up, -1, 1)))))
    return Gravity(up, int(inside.sum()), spread, magnitude)


def level_rotation(up: np.ndarray) -> np.ndarray:
    """The smallest rotation taking ``up`` to +z."""
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    z = np.array([0.0, 0.0, 1.0])
    axis, c = np.cross(up, z), float(up @ z)
    s = float(np.linalg.norm(axis))
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = axis / s
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * K + (1 - c) * K @ K


def level(T_world_cam: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Camera-to-world transforms [N, 4, 4] in a world turned so that ``up`` is +z."""
    G = np.eye(4)
    G[:3, :3] = level_rotation(up)
    return G @ np.asarray(T_world_cam, np.float64)
