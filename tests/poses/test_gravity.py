"""Leveling an estimated trajectory with the accelerometer."""

from __future__ import annotations

import numpy as np
import pytest

from evcap.errors import InputError
from evcap.poses.gravity import gravity_up, level, level_rotation
from evcap.records import Poses
from evcap.sim.scene import TrajectorySpec
from evcap.sim.trajectory import Trajectory


def rotation(axis, deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = np.radians(deg)
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


@pytest.fixture
def handheld():
    """A hand-held path's true poses (world z up) and what its IMU reads."""
    params = {
        "start": [-0.3, -1.0, 0.2],
        "end": [0.3, -1.0, 0.0],
        "look_at": [0.0, 0.0, 0.0],
        "shake_units": 0.02,
        "shake_deg": 10.0,
        "shake_hz": 1.0,
    }
    path = Trajectory(TrajectorySpec(kind="handheld", duration_s=2.0, params=params))
    s = np.linspace(0, 2.0, 201)
    T = np.stack([path.pose(x) for x in s])
    imu_s = np.arange(0, 2.0, 1e-3)
    accel, _ = path.imu(imu_s)
    rng = np.random.default_rng(0)
    accel = accel + rng.normal(0, 0.05, accel.shape)
    return (s * 1e6).round().astype(np.int64), T, (imu_s * 1e6).round().astype(np.int64), accel


def test_a_tilted_and_scaled_world_is_leveled(handheld):
    t, T, imu_t, accel = handheld
    G = np.eye(4)
    G[:3, :3] = rotation([1, 2, 0.5], 35)
    G[:3, 3] = [3, -1, 2]
    T_est = G @ T
    T_est[:, :3, 3] *= 0.1  # structure from motion's scale is arbitrary
    g = gravity_up(Poses(t, T_est), imu_t, accel)
    assert abs(g.magnitude - 9.80665) < 0.3
    leveled = level(T_est, g.up)
    # the cameras' viewing directions keep their elevation: the world's tilt is undone
    true_up = T[:, :3, :3].transpose(0, 2, 1) @ np.array([0, 0, 1.0])
    est_up = leveled[:, :3, :3].transpose(0, 2, 1) @ np.array([0, 0, 1.0])
    angle = np.degrees(np.arccos(np.clip(np.sum(true_up * est_up, 1), -1, 1)))
    assert angle.max() < 0.5


def test_level_rotation_takes_up_to_z():
    for up in ([0, 0, 1], [0, 0, -1], [1, 0, 0], [0.3, -0.2, 0.9]):
        R = level_rotation(up)
        assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1)
        assert np.allclose(R @ (np.array(up) / np.linalg.norm(up)), [0, 0, 1])


def test_too_few_or_inconsistent_samples_are_refused(handheld):
    t, T, imu_t, accel = handheld
    track = Poses(t, T)
    with pytest.raises(InputError, match="IMU samples"):
        gravity_up(track, imu_t[:10], accel[:10])
    # IMU axes that do not follow the camera: the forces cancel out
    rng = np.random.default_rng(1)
    with pytest.raises(InputError, match="disagree"):
        gravity_up(track, imu_t, rng.normal(0, 9.8, accel.shape))
