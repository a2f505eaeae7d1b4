"""Rotations: rotation vectors (so(3)), matrices and unit quaternions, and slerp."""

from __future__ import annotations

import numpy as np

# calibration files print their rotations to 6 to 17 digits: a matrix further than this from a
# rotation (rotation_error) is not one
ROTATION_TOLERANCE = 1e-3


def rotation_error(R: np.ndarray) -> float:
    """How far a 3 x 3 matrix is from a rotation: the largest entry of R^T R - I; infinite
    when it is not finite or mirrors (determinant <= 0)."""
    R = np.asarray(R, np.float64)
    if R.shape != (3, 3) or not np.isfinite(R).all() or np.linalg.det(R) <= 0:
        return float("inf")
    return float(np.abs(R.T @ R - np.eye(3)).max())


def skew(v: np.ndarray) -> np.ndarray:
    """[..., 3] -> [..., 3, 3] cross-product matrices."""
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack(
        [np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2
    )


def exp_so3(v: np.ndarray) -> np.ndarray:
    """Rotation matrices [..., 3, 3] of rotation vectors [..., 3] (Rodrigues)."""
    theta = np.linalg.norm(v, axis=-1)[..., None, None]
    K = skew(v)
    small = theta < 1e-8
    t = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6, np.sin(t) / t)
    b = np.where(small, 0.5 - theta**2 / 24, (1 - np.cos(t)) / t**2)
    return np.eye(3) + a * K + b * (K @ K)


def log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation vectors [..., 3] of rotation matrices [..., 3, 3] (angles below 180 deg)."""
    c = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1.0, 1.0)
    theta = np.arccos(c)[..., None]
    w = np.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1
    )
    s = np.sin(theta)
    return np.where(theta < 1e-6, 0.5 * w, w * theta / (2 * np.where(s < 1e-12, 1.0, s)))


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """[..., 3, 3] rotation matrices to unit quaternions [..., 4] (w, x, y, z), w >= 0."""
    R = np.asarray(R, np.float64)
    m = R.reshape(-1, 3, 3)
    # Shepperd: each row of `cand` is 4 s times the quaternion, where s is one of its four
    # components; take the row whose s is largest, for precision near 180 degrees
    d0, d1, d2 = m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]
    a, b, c = m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]
    e, f, g = m[:, 0, 1] + m[:, 1, 0], m[:, 0, 2] + m[:, 2, 0], m[:, 1, 2] + m[:, 2, 1]
    sq = np.stack([1 + d0 + d1 + d2, 1 + d0 - d1 - d2, 1 - d0 + d1 - d2, 1 - d0 - d1 + d2], 1)
    cand = np.stack(
        [
            np.stack([sq[:, 0], a, b, c], 1),
            np.stack([a, sq[:, 1], e, f], 1),
            np.stack([b, e, sq[:, 2], g], 1),
            np.stack([c, f, g, sq[:, 3]], 1),
        ],
        1,
    )
    q = cand[np.arange(len(m)), sq.argmax(1)]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 0] < 0] *= -1
    return q.reshape(R.shape[:-2] + (4,))


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def slerp(q0: np.ndarray, q1: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Spherical interpolation between unit quaternions [..., 4] by fractions s [...]."""
    dot = (q0 * q1).sum(-1)
    q1 = np.where(dot[..., None] < 0, -q1, q1)
    dot = np.abs(dot).clip(max=1.0)
    theta = np.arccos(dot)
    sin = np.sin(theta)
    small = sin < 1e-9
    a = np.where(small, 1 - s, np.sin((1 - s) * theta) / np.where(small, 1, sin))
    b = np.where(small, s, np.sin(s * theta) / np.where(small, 1, sin))
    q = a[..., None] * q0 + b[..., None] * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)
