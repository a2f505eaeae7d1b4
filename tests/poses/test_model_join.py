"""Models of one path joined through the frame they share (poses/model_join.py)."""

from __future__ import annotations

import numpy as np

from evcap.poses.model_join import Piece, join_pieces, joined_piece
from evcap.rotations import exp_so3

K = np.array([[200.0, 0, 160], [0, 200.0, 120], [0, 0, 1]])


def path(n: int) -> np.ndarray:
    """Cameras on an arc, looking at the origin."""
    T = np.tile(np.eye(4), (n, 1, 1))
    for i, a in enumerate(np.linspace(-0.5, 0.5, n)):
        c = np.array([3 * np.sin(a), 0.2 * a, -3 * np.cos(a)])
        z = -c / np.linalg.norm(c)
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        T[i, :3, :3] = np.stack([x, np.cross(z, x), z], 1)
        T[i, :3, 3] = c
    return T


def piece(frames: list[int], T: np.ndarray, xyz: np.ndarray, ids: np.ndarray) -> Piece:
    """Every point ``xyz`` (point ``ids`` are also its keypoint numbers) seen by every frame."""
    f = np.repeat(frames, len(xyz))
    p = np.tile(np.arange(len(xyz)), len(frames))
    xy = []
    for i in frames:
        Y = (xyz - T[i, :3, 3]) @ T[i, :3, :3]
        xy.append((Y[:, :2] / Y[:, 2:]) * K[0, 0] + K[:2, 2])
    return Piece(
        np.asarray(frames), T[frames], xyz, f, p, np.tile(ids, len(frames)), np.concatenate(xy)
    )


def moved(p: Piece, s: float, R: np.ndarray, t: np.ndarray) -> Piece:
    """The same piece in another world: x -> s R x + t."""
    T = p.T_world_cam.copy()
    T[:, :3, :3] = R @ T[:, :3, :3]
    T[:, :3, 3] = s * T[:, :3, 3] @ R.T + t
    return Piece(p.frames, T, s * p.xyz @ R.T + t, p.frame, p.point, p.keypoint, p.xy)


def scene():
    rng = np.random.default_rng(0)
    T = path(12)
    first = rng.uniform(-0.5, 0.5, (40, 3))
    second = rng.uniform(-0.5, 0.5, (30, 3))
    a = piece(list(range(8)), T, first, np.arange(40))
    # frame 7 is the seam: 5 of its keypoints (0-4) are on points that both models made
    xyz = np.concatenate([first[:5], second])
    b = piece(list(range(7, 12)), T, xyz, np.concatenate([np.arange(5), 100 + np.arange(30)]))
    return T, a, b


def test_a_piece_in_another_world_is_brought_back_exactly() -> None:
    T, a, b = scene()
    other = moved(b, 0.37, exp_so3(np.array([0.3, -1.2, 0.5])), np.array([4.0, -2.0, 1.0]))
    whole, joined = join_pieces([other, a])
    assert joined == 1
    np.testing.assert_array_equal(whole.frames, np.arange(12))
    np.testing.assert_allclose(whole.T_world_cam, T, atol=1e-9)
    # the shared points are one point each, and every sighting names a point in the right place
    assert len(whole.xyz) == 40 + 30
    assert len(whole.frame) == 8 * 40 + 5 * 35 - 5
    Y = np.einsum(
        "oji,oj->oi",
        whole.T_world_cam[whole.frame, :3, :3],
        whole.xyz[whole.point] - whole.T_world_cam[whole.frame, :3, 3],
    )
    np.testing.assert_allclose(Y[:, :2] / Y[:, 2:] * K[0, 0] + K[:2, 2], whole.xy, atol=1e-6)


def test_pieces_that_share_no_frame_or_too_few_points_stay_apart() -> None:
    T, a, b = scene()
    apart = Piece(
        b.frames[1:],
        b.T_world_cam[1:],
        b.xyz,
        b.frame[b.frame != 7],
        b.point[b.frame != 7],
        b.keypoint[b.frame != 7],
        b.xy[b.frame != 7],
    )
    assert joined_piece(a, apart) is None
    few = b.frame != 7
    few |= np.isin(b.keypoint, [0, 1, 100, 101])
    two = Piece(
        b.frames, b.T_world_cam, b.xyz, b.frame[few], b.point[few], b.keypoint[few], b.xy[few]
    )
    assert joined_piece(a, two) is None
    whole, joined = join_pieces([a, two])
    assert joined == 0 and whole is a


def test_a_seam_whose_poses_and_points_disagree_is_not_joined() -> None:
    T, a, b = scene()
    wrong = b.T_world_cam.copy()
    wrong[0, :3, 3] += 1.0  # the seam's pose in the second model moved a metre off
    assert (
        joined_piece(a, Piece(b.frames, wrong, b.xyz, b.frame, b.point, b.keypoint, b.xy)) is None
    )
