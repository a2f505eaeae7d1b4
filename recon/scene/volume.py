"""Where the scene is, from the camera poses alone: the region the cameras look at.

When the optical axes converge (an orbit, a hand-held sweep around an object), the volume is a
ball around the point nearest to all of them, wide enough to hold the field of view there;
random points are drawn inside the cameras' frusta within it. When they do not converge (a
camera moving forward or standing still), points are drawn along the cameras' rays at depths
spread evenly in inverse depth, from a tenth to ten times the path's length (or 0.1 to 10 units
for a still camera).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class SceneVolume:
    center: np.ndarray  # [3]
    radius: float  # the ball's radius; also the scene extent for densification
    converging: bool
    near: float  # depth range of the rays when not converging
    far: float

    def state(self) -> dict:
        """The volume as saved with a training's state."""
        return {
            "center": [float(c) for c in self.center],
            "radius": float(self.radius),
            "converging": bool(self.converging),
            "near": float(self.near),
            "far": float(self.far),
        }

    @classmethod
    def from_state(cls, state: dict) -> SceneVolume:
        return cls(
            np.array(state["center"], np.float64),
            state["radius"],
            state["converging"],
            state["near"],
            state["far"],
        )


@dataclass(frozen=True)
class Ball:
    """Where the scene's foreground lies: what is outside belongs to the background at
    infinity (single_object's ground, a room's far walls)."""

    center: tuple[float, float, float]
    radius: float

    def state(self) -> dict:
        return {"center": list(self.center), "radius": self.radius}

    @classmethod
    def from_state(cls, state: dict) -> Ball:
        return cls(tuple(float(c) for c in state["center"]), float(state["radius"]))


def foreground_ball(volume: SceneVolume, structure: np.ndarray | None) -> Ball | None:
    """The foreground's ball: about the point the cameras look at (else, when they do not
    converge, the middle of the structure's 1st to 99th percentiles), as wide as 99 % of the
    structure's points (the events' stereo: recon/scene/event_stereo.py) lie from it, or the
    volume's ball where there is no structure; None when neither says where the scene is."""
    if structure is not None and len(structure) >= 100:
        if volume.converging:
            center = np.asarray(volume.center, np.float64)
        else:
            lo, hi = np.percentile(structure, [1, 99], axis=0)
            center = 0.5 * (lo + hi)
        radius = float(np.percentile(np.linalg.norm(structure - center, axis=1), 99))
        return Ball(tuple(float(c) for c in center), radius)
    if volume.converging:
        return Ball(tuple(float(c) for c in volume.center), float(volume.radius))
    return None


def scene_volume(T_world_cam: np.ndarray, K: np.ndarray, width: int, height: int) -> SceneVolume:
    """The volume seen by cameras with poses [N, 4, 4] (camera-to-world) and intrinsics K."""
    c = T_world_cam[:, :3, 3]
    f = T_world_cam[:, :3, 2]
    # the point nearest to all optical axes: sum (I - f f^T) (x - c) = 0
    P = np.eye(3)[None] - f[:, :, None] * f[:, None, :]
    A, b = P.sum(0), (P @ c[:, :, None]).sum(0)[:, 0]
    depth = None
    if np.linalg.cond(A) < 1e4:
        x = np.linalg.solve(A, b)
        depth = ((x - c) * f).sum(1)
    half_fov = np.arctan(max(width / (2 * K[0, 0]), height / (2 * K[1, 1])))
    if depth is not None and np.all(depth > 0):
        d = float(np.median(depth))
        return SceneVolume(x, 1.2 * d * np.tan(half_fov), True, 0.0, 0.0)
    span = float(np.linalg.norm(c.max(0) - c.min(0)))
    span = span if span > 1e-6 else 1.0
    return SceneVolume(c.mean(0), 10 * span, False, 0.1 * span, 10 * span)


def sample_points(
    volume: SceneVolume,
    T_world_cam: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    n: int,
    rng: np.random.Generator,
) -> np.ndarray:
    """n random points [n, 3] inside the volume and inside some camera's view."""
    out = []
    Kinv = np.linalg.inv(K)
    while sum(len(o) for o in out) < n:
        m = 4 * n
        cam = T_world_cam[rng.integers(len(T_world_cam), size=m)]
        pix = np.stack([rng.uniform(0, width, m), rng.uniform(0, height, m), np.ones(m)], 1)
        rays = np.einsum("nij,nj->ni", cam[:, :3, :3], pix @ Kinv.T)
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        origin = cam[:, :3, 3]
        if volume.converging:
            dist = np.linalg.norm(origin - volume.center, axis=1)
            d = rng.uniform(np.maximum(dist - volume.radius, 0), dist + volume.radius)
            p = origin + d[:, None] * rays
            p = p[np.linalg.norm(p - volume.center, axis=1) <= volume.radius]
        else:
            inv = rng.uniform(1 / volume.far, 1 / volume.near, m)
            p = origin + (1 / inv)[:, None] * rays
        out.append(p)
    return np.concatenate(out)[:n]
