"""Frames the mapping left out, registered afterwards against the model's points
(poses/resection.py)."""

from __future__ import annotations

import numpy as np
from test_model_join import K, path

from evcap.poses.model_join import Piece
from evcap.poses.resection import MIN_INLIERS, correspondences, register_rest, resect
from evcap.rotations import exp_so3

DIST = np.array([-0.3, 0.1, 0.001, -0.0005])


def seen(T: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """Pixels (distorted by DIST, OpenCV's convention) of ``xyz`` from camera-to-world ``T``."""
    import cv2

    T_cw = np.linalg.inv(T)
    rvec = cv2.Rodrigues(T_cw[:3, :3])[0]
    return cv2.projectPoints(xyz, rvec, T_cw[:3, 3], K, DIST)[0].reshape(-1, 2)


def world(n_frames: int = 8, n_points: int = 60):
    rng = np.random.default_rng(3)
    return path(n_frames), rng.uniform(-0.5, 0.5, (n_points, 3))


def model_of(T: np.ndarray, xyz: np.ndarray, frames: list[int]) -> Piece:
    """Every point seen by every frame of ``frames``; keypoint k of a frame is point k."""
    P = len(xyz)
    return Piece(
        np.asarray(frames),
        T[frames],
        xyz,
        np.repeat(frames, P),
        np.tile(np.arange(P), len(frames)),
        np.tile(np.arange(P), len(frames)),
        np.concatenate([seen(T[f], xyz) for f in frames]),
    )


def test_a_frame_is_found_from_its_points_and_wrong_pairs_are_left_out() -> None:
    T, xyz = world()
    xy = seen(T[3], xyz)
    xy[:10] += 25.0  # ten pairs matched wrongly
    found = resect(xyz, xy, K, DIST)
    assert found is not None
    pose, inliers = found
    assert not inliers[:10].any() and inliers[10:].all()
    np.testing.assert_allclose(pose, T[3], atol=1e-6)


def test_too_few_pairs_or_mostly_wrong_ones_register_nothing() -> None:
    T, xyz = world()
    xy = seen(T[3], xyz)
    assert resect(xyz[: MIN_INLIERS - 1], xy[: MIN_INLIERS - 1], K, DIST) is None
    wrong = xy + np.random.default_rng(0).uniform(-40, 40, xy.shape)
    wrong[:15] = xy[:15]  # 15 of 60 right: a quarter
    assert resect(xyz, wrong, K, DIST) is None


def test_matches_lead_to_the_models_points_and_a_torn_keypoint_is_dropped() -> None:
    T, xyz = world(n_points=6)
    model = model_of(T, xyz, [1, 2])
    # the left-out frame's keypoints 10..15: 10 -> point 0 (via both frames), 11 -> point 1,
    # 12 -> point 2 in frame 1 but point 3 in frame 2 (torn), 13 -> a keypoint on no point
    matches = {1: np.array([[10, 0], [11, 1], [12, 2]]), 2: np.array([[10, 0], [12, 3], [13, 99]])}
    keys, points = correspondences(model, matches)
    assert keys.tolist() == [10, 11] and points.tolist() == [0, 1]


def test_left_out_frames_at_both_ends_are_registered_leaning_on_each_other() -> None:
    T, xyz = world(n_frames=8)
    model = model_of(T, xyz, [2, 3, 4, 5])
    rng = np.random.default_rng(1)
    # a keypoint order of its own for each frame, and frames 0 and 7 match only their
    # neighbours: frame 0 can be found only once frame 1 is
    order = [rng.permutation(len(xyz)) for _ in range(8)]
    model.keypoint = np.concatenate([np.argsort(order[f]) for f in model.frames])
    model.xy = np.concatenate([seen(T[f], xyz) for f in model.frames])

    def keypoints(f: int) -> np.ndarray:
        return seen(T[f], xyz)[order[f]]

    def matches(f: int, g: int) -> np.ndarray:
        if abs(f - g) != 1:
            return np.zeros((0, 2), np.int64)
        return np.stack([np.argsort(order[f]), np.argsort(order[g])], 1)

    grown, added = register_rest(model, 8, keypoints, matches, K, DIST)
    assert added == 4 and grown.frames.tolist() == list(range(8))
    np.testing.assert_allclose(grown.T_world_cam, T, atol=1e-6)
    for f in (0, 1, 6, 7):  # their sightings joined the model, each on its own point
        mine = grown.frame == f
        np.testing.assert_allclose(grown.xy[mine], seen(T[f], xyz[grown.point[mine]]), atol=1e-9)


def test_a_frame_whose_points_disagree_with_every_pose_stays_out() -> None:
    T, xyz = world(n_frames=4)
    model = model_of(T, xyz, [1, 2, 3])
    bent = xyz @ exp_so3(np.array([0.0, 0.6, 0.0])).T * np.array([1.0, 3.0, 0.2])

    def keypoints(f: int) -> np.ndarray:  # frame 0 saw another scene
        return seen(T[0], bent)

    def matches(f: int, g: int) -> np.ndarray:
        return np.stack([np.arange(len(xyz))] * 2, 1) if g == 1 else np.zeros((0, 2), np.int64)

    grown, added = register_rest(model, 4, keypoints, matches, K, DIST)
    assert added == 0 and grown.frames.tolist() == [1, 2, 3]
