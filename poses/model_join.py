"""COLMAP's models of one path joined where they share a frame.

Incremental mapping breaks a path into several models where its frames stop matching (on the
demo's orbit, where the camera's vertical motion reverses and the high-pass frames' edges change
sign: frames 1-48 make one model, 48-58 another). The frame at the seam is then often registered
in both. Its two poses give the rotation and translation between the models' worlds; the points
that both models triangulated from its keypoints give the scale. The smaller model is brought
into the larger one's world, those points become one, and the frames it adds count as registered.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MIN_SHARED_POINTS = 3  # points seen at the seam by both models: the scale needs a few
# the shared points, brought over, must land within this share of their distance from the
# seam's camera (median); further, the seam's two poses or the points disagree: not joined
MAX_SHARED_MISFIT = 0.1


@dataclass
class Piece:
    """One model: its registered frames' poses and its points with their sightings."""

    frames: np.ndarray  # [M] int64 frame indices (into the images given to COLMAP), ascending
    T_world_cam: np.ndarray  # [M, 4, 4] camera-to-world
    xyz: np.ndarray  # [P, 3]
    frame: np.ndarray  # [O] int64 frame index (not row) of each sighting
    point: np.ndarray  # [O] int64 row of xyz
    keypoint: np.ndarray  # [O] int64 the frame's keypoint (COLMAP's point2D index)
    xy: np.ndarray  # [O, 2] pixel, OpenCV convention (top-left pixel's centre at 0, 0)

    def pose(self, frame: int) -> np.ndarray:
        return self.T_world_cam[np.searchsorted(self.frames, frame)]


def piece_of(model, index: dict[str, int]) -> Piece:
    """A pycolmap Reconstruction as a Piece; ``index`` maps image names to frame indices."""
    frames, poses = [], []
    for image in model.images.values():
        if image.has_pose:
            T = np.eye(4)
            T[:3] = image.cam_from_world().matrix()
            frames.append(index[image.name])
            poses.append(np.linalg.inv(T))
    order = np.argsort(frames)
    xyz, frame, point, keypoint, xy = [], [], [], [], []
    for p in model.points3D.values():
        for e in p.track.elements:
            image = model.images[e.image_id]
            frame.append(index[image.name])
            point.append(len(xyz))
            keypoint.append(e.point2D_idx)
            xy.append(image.points2D[e.point2D_idx].xy)
        xyz.append(p.xyz)
    return Piece(
        np.asarray(frames, np.int64)[order],
        np.asarray(poses, np.float64).reshape(-1, 4, 4)[order],
        np.asarray(xyz, np.float64).reshape(-1, 3),
        np.asarray(frame, np.int64),
        np.asarray(point, np.int64),
        np.asarray(keypoint, np.int64),
        np.asarray(xy, np.float64).reshape(-1, 2) - 0.5,  # COLMAP's pixel centres are at 0.5
    )


def join_pieces(pieces: list[Piece]) -> tuple[Piece, int]:
    """The largest piece with every other that can be joined to it (directly or through one
    joined before); and how many were joined."""
    rest = sorted(pieces, key=lambda p: len(p.frames), reverse=True)
    whole, joined = rest.pop(0), 0
    grown = True
    while grown and rest:
        grown = False
        for i, piece in enumerate(rest):
            bigger = joined_piece(whole, piece)
            if bigger is not None:
                whole, joined, grown = bigger, joined + 1, True
                rest.pop(i)
                break
    return whole, joined


def joined_piece(base: Piece, other: Piece) -> Piece | None:
    """``other`` brought into ``base``'s world through the frames both registered, or None
    when they share no frame, too few points, or their poses and points disagree."""
    common = np.intersect1d(base.frames, other.frames)
    if not len(common) or not len(np.setdiff1d(other.frames, base.frames)):
        return None
    pairs = _shared_points(base, other, common)
    if len(pairs) < MIN_SHARED_POINTS:
        return None
    # rotation: the chordal mean over the seam's frames of base R . other R^T
    M = sum(base.pose(f)[:3, :3] @ other.pose(f)[:3, :3].T for f in common)
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    seam = pairs[:, 0]  # the frame each pair was seen from
    Cb = np.stack([base.pose(f)[:3, 3] for f in seam])
    Co = np.stack([other.pose(f)[:3, 3] for f in seam])
    far_b = np.linalg.norm(base.xyz[pairs[:, 1]] - Cb, axis=1)
    far_o = np.linalg.norm(other.xyz[pairs[:, 2]] - Co, axis=1)
    s = float(np.median(far_b / np.maximum(far_o, 1e-12)))
    t = np.mean([base.pose(f)[:3, 3] - s * R @ other.pose(f)[:3, 3] for f in common], axis=0)
    moved = s * other.xyz @ R.T + t
    misfit = np.linalg.norm(moved[pairs[:, 2]] - base.xyz[pairs[:, 1]], axis=1)
    if not np.isfinite(s) or s <= 0 or np.median(misfit / far_b) > MAX_SHARED_MISFIT:
        return None

    T = other.T_world_cam.copy()
    T[:, :3, :3] = R @ T[:, :3, :3]
    T[:, :3, 3] = s * T[:, :3, 3] @ R.T + t
    new = ~np.isin(other.frames, common)
    frames = np.concatenate([base.frames, other.frames[new]])
    order = np.argsort(frames)
    # the other's points after the base's; those seen at the seam by both become the base's
    keep = np.setdiff1d(np.arange(len(other.xyz)), pairs[:, 2])
    renumber = np.full(len(other.xyz), -1)
    renumber[keep] = np.arange(len(keep)) + len(base.xyz)
    renumber[pairs[:, 2]] = pairs[:, 1]
    # a sighting both models have (the seam's keypoint of a shared point) is kept once
    point = renumber[other.point]
    dup = np.isin(other.frame, common) & np.isin(other.point, pairs[:, 2])
    return Piece(
        frames[order],
        np.concatenate([base.T_world_cam, T[new]])[order],
        np.concatenate([base.xyz, moved[keep]]),
        np.concatenate([base.frame, other.frame[~dup]]),
        np.concatenate([base.point, point[~dup]]),
        np.concatenate([base.keypoint, other.keypoint[~dup]]),
        np.concatenate([base.xy, other.xy[~dup]]),
    )


def _shared_points(base: Piece, other: Piece, common: np.ndarray) -> np.ndarray:
    """[K, 3] (frame, base point, other point): the seam's keypoints on a point in each model,
    each other point once."""
    seen = {}
    for f in common:
        b = base.frame == f
        o = other.frame == f
        in_base = dict(zip(base.keypoint[b].tolist(), base.point[b].tolist(), strict=True))
        for k, p in zip(other.keypoint[o].tolist(), other.point[o].tolist(), strict=True):
            if k in in_base and p not in seen:
                seen[p] = (int(f), in_base[k], p)
    return np.asarray(list(seen.values()), np.int64).reshape(-1, 3)
