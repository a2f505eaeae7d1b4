"""Camera paths: camera-to-world poses as smooth functions of time, and the IMU they imply.

World axes: z is up. Camera axes are OpenCV's (x right, y down, z forward). A pose is a 4 x 4
camera-to-world matrix T_world_cam.
"""

from __future__ import annotations

import numpy as np

from evcap.errors import InputError
from evcap.rotations import exp_so3, log_so3
from evcap.sim.scene import TrajectorySpec

GRAVITY = 9.80665  # m/s^2
UP = np.array([0.0, 0.0, 1.0])


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = UP) -> np.ndarray:
    """The rotations [..., 3, 3] (camera-to-world, columns = camera x, y, z in the world) of
    cameras at ``eye`` [..., 3] looking at ``target`` with their image upright."""
    forward = target - eye
    forward = forward / np.linalg.norm(forward, axis=-1, keepdims=True)
    right = np.cross(forward, up)
    # looking straight up or down: any right will do
    straight = np.linalg.norm(right, axis=-1, keepdims=True) < 1e-9
    right = np.where(straight, np.cross(forward, np.array([1.0, 0.0, 0.0])), right)
    right = right / np.linalg.norm(right, axis=-1, keepdims=True)
    down = np.cross(forward, right)
    return np.stack([right, down, forward], axis=-1)


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    return exp_so3(axis / np.linalg.norm(axis) * angle)


def _vec(params: dict, key: str, default) -> np.ndarray:
    value = params.get(key, default)
    if not isinstance(value, list | tuple) or len(value) != 3:
        raise InputError(f"trajectory: {key} must be 3 numbers, got {value!r}")
    return np.asarray(value, np.float64)


class Trajectory:
    """A camera path over [0, duration_s]."""

    def __init__(self, spec: TrajectorySpec, seed: int = 0) -> None:
        self.spec = spec
        self.duration_s = spec.duration_s
        p = spec.params
        self.kind = spec.kind
        if spec.kind == "orbit":
            self.center = _vec(p, "center", [0, 0, 0])
            self.radius = float(p.get("radius", 2.0))
            self.height = float(p.get("height", 0.5))
            self.height_swing = float(p.get("height_swing", 0.0))
            self.swings = float(p.get("swings", 1.0))
            self.start = np.deg2rad(float(p.get("start_deg", 0.0)))
            self.sweep = np.deg2rad(float(p.get("degrees", 90.0)))
            self.target = _vec(p, "look_at", list(self.center))
            if self.radius <= 0:
                raise InputError("trajectory: radius must be positive")
        elif spec.kind in ("handheld", "linear"):
            self.a = _vec(p, "start", [2, 0, 0.5])
            self.b = _vec(p, "end", list(self.a))
            self.target = _vec(p, "look_at", [0, 0, 0])
            if spec.kind == "handheld":
                rng = np.random.default_rng(seed)
                hz = float(p.get("shake_hz", 2.0))
                self.shake_units = float(p.get("shake_units", 0.02))
                self.shake_rad = np.deg2rad(float(p.get("shake_deg", 1.0)))
                # a few incommensurate sinusoids per axis: smooth, like a hand
                self.freqs = hz * rng.uniform(0.5, 1.5, (2, 3, 3))
                self.phases = rng.uniform(0, 2 * np.pi, (2, 3, 3))
        else:
            self.position = _vec(p, "position", [2, 0, 0.5])
            self.target = _vec(p, "look_at", [0, 0, 0])

    def _shake(self, t: np.ndarray, k: int) -> np.ndarray:
        """[M, 3] at times t [M]."""
        angles = 2 * np.pi * self.freqs[k] * t[:, None, None] + self.phases[k]
        return np.sin(angles).mean(axis=2)

    def pose(self, t: float) -> np.ndarray:
        """T_world_cam at time t (seconds)."""
        return self.poses(np.array([t]))[0]

    def poses(self, times_s: np.ndarray) -> np.ndarray:
        """T_world_cam [M, 4, 4] at times [M] (seconds)."""
        t = np.atleast_1d(np.asarray(times_s, np.float64))
        s = t / self.duration_s
        if self.kind == "orbit":
            a = self.start + self.sweep * s
            z = self.height + self.height_swing * np.sin(2 * np.pi * self.swings * s)
            offset = np.stack([self.radius * np.cos(a), self.radius * np.sin(a), z], axis=1)
            eye = self.center + offset
            r = look_at(eye, self.target)
        elif self.kind in ("handheld", "linear"):
            eye = self.a + (self.b - self.a) * s[:, None]
            r = look_at(eye, self.target)
            if self.kind == "handheld":
                eye = eye + self.shake_units * self._shake(t, 0)
                r = r @ exp_so3(self.shake_rad * self._shake(t, 1))
        else:
            eye = np.broadcast_to(self.position, (len(t), 3))
            r = look_at(eye, self.target)
        T = np.broadcast_to(np.eye(4), (len(t), 4, 4)).copy()
        T[:, :3, :3] = r
        T[:, :3, 3] = eye
        return T

    def imu(
        self, times_s: np.ndarray, units_per_meter: float = 1.0, dt: float = 1e-4
    ) -> tuple[np.ndarray, np.ndarray]:
        """(accel [N, 3] m/s^2, gyro [N, 3] rad/s) an IMU in the camera's axes would read:
        the specific force (acceleration minus gravity) and the angular velocity."""
        t = np.atleast_1d(np.asarray(times_s, np.float64))
        if self.duration_s > 2 * dt:
            t = np.clip(t, dt, self.duration_s - dt)
        p0, p1, p2 = self.poses(t - dt), self.poses(t), self.poses(t + dt)
        a_world = (p2[:, :3, 3] - 2 * p1[:, :3, 3] + p0[:, :3, 3]) / (dt * dt) / units_per_meter
        accel = np.einsum("nji,nj->ni", p1[:, :3, :3], a_world + GRAVITY * UP)
        gyro = log_so3(p0[:, :3, :3].transpose(0, 2, 1) @ p2[:, :3, :3]) / (2 * dt)
        return accel, gyro

    def speed_px(self, t: float, points: np.ndarray, camera, dt: float = 1e-3) -> float:
        """The largest image motion (pixels per second) of ``points`` (world) at time t."""
        a, b = self.pose(t), self.pose(min(t + dt, self.duration_s))
        uv = []
        for T in (a, b):
            pc = (points - T[:3, 3]) @ T[:3, :3]
            front = pc[:, 2] > 1e-6
            uv.append((camera.project(pc[front]) if front.any() else np.zeros((0, 2)), front))
        both = uv[0][1] & uv[1][1]
        if not both.any():
            return 0.0
        ua = camera.project((points[both] - a[:3, 3]) @ a[:3, :3])
        ub = camera.project((points[both] - b[:3, 3]) @ b[:3, :3])
        step = max(min(t + dt, self.duration_s) - t, 1e-9)
        return float(np.linalg.norm(ub - ua, axis=1).max() / step)
