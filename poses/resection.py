"""Frames the mapping left out, registered afterwards against the model's points (resection).

COLMAP's incremental mapping adds a frame when enough of its keypoints (30; relaxed, 15) match
points of the model and agree on a pose. Event frames fall short where they have little to
show: the first frames of a recording, whose filter has no history yet, and frames at the end of
a model. Each frame left out is tried again here: its verified matches to registered frames are
followed to the model's points, and its pose is found from those 2D-3D pairs by PnP (RANSAC,
then Levenberg-Marquardt on the inliers). It is kept when enough inliers fit within a few
pixels; its inlier sightings then join the model, so that the next frame can lean on it.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from evcap.poses.model_join import Piece

MIN_INLIERS = 12  # 2D-3D pairs that fit the pose (PnP needs 4; a dozen make it trustworthy)
MIN_INLIER_SHARE = 0.5  # of the pairs: fewer, and the frame's matches are mostly wrong
MAX_ERROR_PX = 2.0  # reprojection error within which a pair is an inlier
SEED = 0  # RANSAC's draws: the same frames give the same poses


def correspondences(piece: Piece, matches: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The keypoints of a left-out frame that see a point of ``piece``, and those points' rows:
    ``matches`` maps a registered frame to its [K, 2] matches (the left-out frame's keypoint,
    the registered frame's keypoint). A keypoint led to two different points is left out."""
    seen: dict[int, int] = {}
    torn: set[int] = set()
    for frame, pairs in matches.items():
        mine = piece.frame == frame
        point_of = dict(zip(piece.keypoint[mine].tolist(), piece.point[mine].tolist(), strict=True))
        for k, other in np.asarray(pairs, np.int64).reshape(-1, 2).tolist():
            p = point_of.get(other)
            if p is None:
                continue
            if seen.setdefault(k, p) != p:
                torn.add(k)
    keys = np.array(sorted(set(seen) - torn), np.int64)
    return keys, np.array([seen[k] for k in keys.tolist()], np.int64)


def resect(
    xyz: np.ndarray, xy: np.ndarray, K: np.ndarray, dist: np.ndarray
) -> tuple[np.ndarray, np.ndarray] | None:
    """The camera-to-world pose [4, 4] that sees the points ``xyz`` [N, 3] at the pixels ``xy``
    [N, 2] (distorted, OpenCV's convention) and which pairs fit it, or None when fewer than
    MIN_INLIERS (or MIN_INLIER_SHARE of them) fit within MAX_ERROR_PX."""
    if len(xyz) < MIN_INLIERS:
        return None
    obj = np.ascontiguousarray(xyz, np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(xy, np.float64).reshape(-1, 1, 2)
    d = np.asarray(dist, np.float64).ravel()
    d = d if d.size else None
    cv2.setRNGSeed(SEED)
    ok, rvec, tvec, _ = cv2.solvePnPRansac(
        obj,
        img,
        K,
        d,
        iterationsCount=1000,
        reprojectionError=MAX_ERROR_PX,
        confidence=0.999,
        flags=cv2.SOLVEPNP_EPNP,
    )
    if not ok:
        return None
    for _ in range(2):  # refine on the inliers, then take the inliers of the refined pose
        inliers = _fits(obj, img, rvec, tvec, K, d)
        if inliers.sum() < 4:
            return None
        rvec, tvec = cv2.solvePnPRefineLM(obj[inliers], img[inliers], K, d, rvec, tvec)
    inliers = _fits(obj, img, rvec, tvec, K, d)
    R = cv2.Rodrigues(rvec)[0]
    depth = (xyz[inliers] @ R.T + tvec.ravel())[:, 2]
    if inliers.sum() < max(MIN_INLIERS, MIN_INLIER_SHARE * len(xyz)) or (depth <= 0).any():
        return None
    T = np.eye(4)
    T[:3, :3] = R.T
    T[:3, 3] = -R.T @ tvec.ravel()
    return T, inliers


def register_rest(
    piece: Piece,
    frames: int,
    keypoints: Callable[[int], np.ndarray],
    matches: Callable[[int, int], np.ndarray],
    K: np.ndarray,
    dist: np.ndarray,
) -> tuple[Piece, int]:
    """``piece`` with the frames of 0..frames-1 it lacks registered where they can be, nearest
    to the registered ones first; and how many were. ``keypoints(f)``: a frame's keypoints
    [N, 2] (OpenCV's pixel convention); ``matches(f, g)``: the verified matches [K, 2] between
    frames f and g (f's keypoint, g's keypoint)."""
    added = 0
    while True:
        left = np.setdiff1d(np.arange(frames), piece.frames)
        if not len(left):
            return piece, added
        gap = np.abs(left[:, None] - piece.frames[None]).min(1)
        grown = False
        for f in left[np.argsort(gap, kind="stable")].tolist():
            pairs = {g: matches(f, g) for g in piece.frames.tolist()}
            keys, points = correspondences(piece, {g: m for g, m in pairs.items() if len(m)})
            if not len(keys):
                continue
            xy = keypoints(f)[keys]
            found = resect(piece.xyz[points], xy, K, dist)
            if found is None:
                continue
            T, fit = found
            piece = _with_frame(piece, f, T, keys[fit], points[fit], xy[fit])
            grown, added = True, added + 1
            break  # the frames next to it may now lean on it: nearest first again
        if not grown:
            return piece, added


def _fits(obj, img, rvec, tvec, K, d) -> np.ndarray:
    projected = cv2.projectPoints(obj, rvec, tvec, K, d)[0]
    return np.linalg.norm((projected - img).reshape(-1, 2), axis=1) <= MAX_ERROR_PX


def _with_frame(
    piece: Piece, frame: int, T: np.ndarray, keys: np.ndarray, points: np.ndarray, xy: np.ndarray
) -> Piece:
    """``piece`` with ``frame`` registered at ``T`` and its sightings of ``points``."""
    frames = np.append(piece.frames, frame)
    order = np.argsort(frames)
    return Piece(
        frames[order],
        np.concatenate([piece.T_world_cam, T[None]])[order],
        piece.xyz,
        np.concatenate([piece.frame, np.full(len(keys), frame, np.int64)]),
        np.concatenate([piece.point, points]),
        np.concatenate([piece.keypoint, keys]),
        np.concatenate([piece.xy, xy]),
    )
