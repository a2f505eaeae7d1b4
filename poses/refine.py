"""Camera positions and 3D points adjusted to orientations held fixed (the gyroscope's).

Structure from motion's positions and orientations err together: a frame turned a degree too
far is also moved so that its points still project where they were seen. Given better
orientations, the positions and points are adjusted again, by Levenberg-Marquardt on the
reprojection error (Huber-weighted, in pixels), the points eliminated by the Schur complement.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import cv2
import numpy as np

from evcap.poses.sfm import Observations

HUBER_PX = 2.0
MIN_DEPTH = 1e-6


@dataclass
class Refined:
    centres: np.ndarray  # [M, 3] camera positions in the world
    points: np.ndarray  # [P, 3]
    rms_px: float  # reprojection error (root mean square), before the Huber weighting
    start_rms_px: float
    iterations: int


def normalized(xy: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Pixels [N, 2] (distorted, OpenCV) -> undistorted normalized image coordinates."""
    d = np.asarray(dist, np.float64).ravel()
    return cv2.undistortPoints(xy.reshape(-1, 1, 2), K, d if d.size else None).reshape(-1, 2)


def refine_positions(
    R_world_cam: np.ndarray,
    centres: np.ndarray,
    points: np.ndarray,
    obs: Observations,
    K: np.ndarray,
    dist: np.ndarray,
    iterations: int = 30,
) -> Refined:
    """Positions and points that fit the sightings ``obs`` seen by cameras turned as
    ``R_world_cam`` [M, 3, 3] (held fixed), starting from ``centres`` [M, 3] and ``points``."""
    R_cw = np.swapaxes(np.asarray(R_world_cam, np.float64), -1, -2)[obs.frame]  # [O, 3, 3]
    target = normalized(obs.xy, np.asarray(K, np.float64), dist)
    f = np.array([K[0, 0], K[1, 1]], np.float64)
    M, P = len(centres), len(points)
    C, X = np.asarray(centres, np.float64).copy(), np.asarray(points, np.float64).copy()

    def residuals(C: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        Y = np.einsum("oij,oj->oi", R_cw, X[obs.point] - C[obs.frame])
        z = Y[:, 2]
        front = z > MIN_DEPTH
        zs = np.where(front, z, 1.0)
        r = f * (Y[:, :2] / zs[:, None] - target)
        return np.where(front[:, None], r, 0.0), Y, zs

    def cost(r: np.ndarray) -> float:
        a = np.linalg.norm(r, axis=1)
        return float(np.where(a <= HUBER_PX, 0.5 * a**2, HUBER_PX * (a - 0.5 * HUBER_PX)).sum())

    r, Y, z = residuals(C, X)
    start = float(np.sqrt(np.mean(np.sum(r**2, 1))))
    current, lam, done = cost(r), 1e-3, 0
    while done < iterations:
        done += 1
        w = HUBER_PX / np.maximum(np.linalg.norm(r, axis=1), HUBER_PX)  # IRLS weights
        u, v = Y[:, 0] / z, Y[:, 1] / z
        Jy = np.zeros((len(z), 2, 3))
        Jy[:, 0, 0], Jy[:, 0, 2] = f[0] / z, -f[0] * u / z
        Jy[:, 1, 1], Jy[:, 1, 2] = f[1] / z, -f[1] * v / z
        Jp = Jy @ R_cw  # d r / d point; d r / d centre is -Jp
        wJp = w[:, None, None] * Jp
        A = np.einsum("oki,okj->oij", wJp, Jp)  # J^T W J, the same block for point and centre
        U, V = np.zeros((M, 3, 3)), np.zeros((P, 3, 3))
        np.add.at(U, obs.frame, A)
        np.add.at(V, obs.point, A)
        g = np.einsum("oki,ok->oi", wJp, r)
        gc, gp = np.zeros((M, 3)), np.zeros((P, 3))
        np.add.at(gc, obs.frame, g)  # the negative gradients: d r / d centre = -Jp
        np.add.at(gp, obs.point, -g)
        while True:
            dC, dX = _solve(U, V, -A, gc, gp, obs, lam)
            r_new, Y_new, z_new = residuals(C + dC, X + dX)
            trial = cost(r_new)
            if trial < current:
                C, X, r, Y, z = C + dC, X + dX, r_new, Y_new, z_new
                gain, current, lam = current - trial, trial, max(lam / 3, 1e-9)
                break
            lam *= 5
            if lam > 1e6:
                gain = 0.0
                break
        if gain <= 1e-9 * max(current, 1e-12):
            break
    rms = float(np.sqrt(np.mean(np.sum(r**2, 1))))
    return Refined(C, X, rms, start, done)


def _solve(
    U: np.ndarray,
    V: np.ndarray,
    W: np.ndarray,
    gc: np.ndarray,
    gp: np.ndarray,
    obs: Observations,
    lam: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The damped Gauss-Newton step (centres, points) of the normal equations
    [[U, W], [W^T, V]] (block-diagonal U and V, W one 3 x 3 block per sighting) against the
    negative gradients ``gc`` and ``gp``, by the points' Schur complement."""
    import torch

    M, P = len(U), len(V)
    eye = np.eye(3)
    Ud = U + lam * U * eye + 1e-9 * eye
    Vinv = np.linalg.inv(V + lam * V * eye + 1e-9 * eye)
    rows = (3 * obs.frame[:, None, None] + np.arange(3)[None, :, None]).repeat(3, 2)
    cols = (3 * obs.point[:, None, None] + np.arange(3)[None, None, :]).repeat(3, 1)
    B = _sparse(rows, cols, W, (3 * M, 3 * P))
    prow = (3 * np.arange(P)[:, None, None] + np.arange(3)[None, :, None]).repeat(3, 2)
    pcol = (3 * np.arange(P)[:, None, None] + np.arange(3)[None, None, :]).repeat(3, 1)
    D = _sparse(prow, pcol, Vinv, (3 * P, 3 * P))
    with warnings.catch_warnings():  # torch names its sparse products beta
        warnings.simplefilter("ignore", UserWarning)
        BD = torch.sparse.mm(B, D)
        S = -torch.sparse.mm(BD, B.t().coalesce()).to_dense().numpy()
    for i in range(M):
        S[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] += Ud[i]
    rhs = gc.ravel() - (BD @ torch.from_numpy(gp.ravel())[:, None]).numpy().ravel()
    dC = np.linalg.solve(S, rhs).reshape(M, 3)
    back = gp.ravel() - (B.t() @ torch.from_numpy(dC.ravel())[:, None]).numpy().ravel()
    dX = np.einsum("pij,pj->pi", Vinv, back.reshape(P, 3))
    return dC, dX


def _sparse(rows: np.ndarray, cols: np.ndarray, values: np.ndarray, shape: tuple):
    import torch

    index = torch.from_numpy(np.stack([rows.ravel(), cols.ravel()]).astype(np.int64))
    values = torch.from_numpy(values.ravel())
    return torch.sparse_coo_tensor(index, values, shape, check_invariants=False).coalesce()
