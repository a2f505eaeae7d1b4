"""The similarity alignment (Umeyama) and the pose errors measured after it."""

import numpy as np
import pytest

from evcap.errors import InputError
from evcap.sim.trajectory import look_at, rotation_about
from evcap.trajectory_alignment import align_similarity, apply_similarity, pose_errors


def random_rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def orbit_poses(n: int, rng=None) -> np.ndarray:
    """Cameras on a rising arc, all looking at the origin: centres spread in 3D."""
    a = np.linspace(0, np.pi, n)
    eye = np.stack([2 * np.cos(a), 2 * np.sin(a), 0.5 + 0.4 * np.sin(3 * a)], 1)
    T = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        T[i, :3, :3] = look_at(eye[i], np.zeros(3))
        T[i, :3, 3] = eye[i]
    return T


def test_recovers_a_known_similarity_exactly():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(50, 3))
    R, s, t = random_rotation(rng), 2.5, np.array([1.0, -2.0, 0.3])
    scale, R_est, t_est = align_similarity(src, s * src @ R.T + t)
    assert scale == pytest.approx(s, rel=1e-12)
    np.testing.assert_allclose(R_est, R, atol=1e-12)
    np.testing.assert_allclose(t_est, t, atol=1e-12)
    assert np.linalg.det(R_est) == pytest.approx(1.0)


def test_three_points_and_a_planar_set_are_enough():
    rng = np.random.default_rng(1)
    src = np.array([[0.0, 0, 0], [1, 0, 0], [0, 2, 0]])
    R, t = random_rotation(rng), rng.normal(size=3)
    scale, R_est, t_est = align_similarity(src, 0.3 * src @ R.T + t)
    assert scale == pytest.approx(0.3)
    np.testing.assert_allclose(R_est, R, atol=1e-12)  # a plane's mirror is not taken
    np.testing.assert_allclose(t_est, t, atol=1e-12)


def test_a_mirrored_target_still_gives_a_rotation():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(30, 3))
    _, R_est, _ = align_similarity(src, src * [1, 1, -1])
    assert np.linalg.det(R_est) == pytest.approx(1.0)
    np.testing.assert_allclose(R_est.T @ R_est, np.eye(3), atol=1e-12)


def test_noise_moves_the_estimate_only_a_little():
    rng = np.random.default_rng(3)
    src = rng.uniform(-1, 1, size=(400, 3))
    R, s, t = random_rotation(rng), 0.7, np.array([3.0, 0.0, -1.0])
    dst = s * src @ R.T + t + rng.normal(scale=0.01, size=src.shape)
    scale, R_est, t_est = align_similarity(src, dst)
    assert scale == pytest.approx(s, rel=0.01)
    angle = np.degrees(np.arccos(np.clip((np.trace(R.T @ R_est) - 1) / 2, -1, 1)))
    assert angle < 0.2
    np.testing.assert_allclose(t_est, t, atol=0.01)
    # an outlier-free fit: the residual is the noise (sigma 0.01 per axis)
    residual = np.linalg.norm(scale * src @ R_est.T + t_est - dst, axis=1)
    assert np.sqrt((residual**2).mean()) == pytest.approx(0.01 * np.sqrt(3), rel=0.1)


@pytest.mark.parametrize(
    ("src", "message"),
    [
        (np.zeros((0, 3)), "at least 3"),
        (np.array([[0.0, 0, 0], [1, 1, 1]]), "at least 3"),
        (np.array([[0.0, 0, 0], [1, 1, 1], [2, 2, 2], [5, 5, 5]]), "one line"),
        (np.ones((5, 3)), "one line"),
        (np.array([[0.0, 0, 0], [1, 0, 0], [0, np.nan, 0]]), "finite"),
        (np.zeros((4, 2)), r"\[N, 3\]"),
    ],
)
def test_degenerate_input_is_refused(src, message):
    with pytest.raises(InputError, match=message):
        align_similarity(src, src)


def test_a_line_in_the_target_is_refused_too():
    src = np.random.default_rng(4).normal(size=(10, 3))
    dst = np.outer(np.arange(10.0), [1, 2, 3])
    with pytest.raises(InputError, match="one line"):
        align_similarity(src, dst)
    with pytest.raises(InputError, match="cannot align 10 points to 9"):
        align_similarity(src, dst[:9])


def test_apply_similarity_moves_cameras_and_keeps_their_axes():
    rng = np.random.default_rng(5)
    T = orbit_poses(7)
    R, s, t = random_rotation(rng), 3.0, np.array([0.5, 1.0, -2.0])
    out = apply_similarity(T, s, R, t)
    np.testing.assert_allclose(out[:, :3, 3], s * T[:, :3, 3] @ R.T + t, atol=1e-12)
    np.testing.assert_allclose(out[:, :3, :3], R @ T[:, :3, :3], atol=1e-12)
    np.testing.assert_allclose(out[:, 3], np.tile([0, 0, 0, 1.0], (7, 1)))
    # a world point seen by a camera is seen at the same place after both move
    p_world = np.array([0.1, -0.2, 0.3])
    cam = (p_world - T[2, :3, 3]) @ T[2, :3, :3]
    cam_after = (s * R @ p_world + t - out[2, :3, 3]) @ out[2, :3, :3]
    np.testing.assert_allclose(cam_after, s * cam, atol=1e-12)
    assert apply_similarity(T[0], s, R, t).shape == (4, 4)


def test_pose_errors_are_zero_for_a_similar_copy():
    rng = np.random.default_rng(6)
    T_true = orbit_poses(20)
    R, s, t = random_rotation(rng), 0.13, rng.normal(size=3)
    T_est = apply_similarity(T_true, s, R, t)  # SfM's own frame and scale
    e = pose_errors(T_est, T_true)
    assert e["aligned_by"] == "centres"
    assert e["rotation_deg"].shape == (20,) and e["translation_pct"].shape == (20,)
    assert e["rotation_median_deg"] < 1e-6 and e["translation_rms_pct"] < 1e-9
    assert e["scale"] == pytest.approx(1 / s)
    # the extent is the largest distance between two true centres: the arc's two ends
    assert e["extent"] == pytest.approx(np.linalg.norm(T_true[0, :3, 3] - T_true[-1, :3, 3]))


def test_pose_errors_measure_known_perturbations():
    T_true = orbit_poses(21)
    extent = 4.0  # the arc's ends: (2, 0) and (-2, 0) at one height
    # every camera turned by 0.3 deg about its own axis: the centres, and so the fit, stay
    T_est = T_true.copy()
    T_est[:, :3, :3] = T_est[:, :3, :3] @ rotation_about(np.array([1.0, 0, 0]), np.radians(0.3))
    e = pose_errors(T_est, T_true)
    np.testing.assert_allclose(e["rotation_deg"], 0.3, atol=1e-9)
    assert e["rotation_rms_deg"] == pytest.approx(0.3, abs=1e-9)
    assert e["translation_rms_pct"] < 1e-9 and e["extent"] == pytest.approx(extent)
    # one centre moved by 1 % of the extent: the fit spreads it a little over the others
    T_est = T_true.copy()
    T_est[10, :3, 3] += [0.0, 0.0, 0.01 * extent]
    e = pose_errors(T_est, T_true)
    assert 0.8 < e["translation_pct"][10] < 1.0
    assert e["translation_median_pct"] < 0.1
    # and tilts the cameras with it: on a flat arc a centre's height pulls on the tilt
    assert 0.0 < e["rotation_median_deg"] < 0.3


def test_centres_on_a_line_are_aligned_with_the_rotations():
    n = 12
    T_true = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        eye = np.array([-1.0 + 0.2 * i, 2.0, 0.5])
        T_true[i, :3, :3] = look_at(eye, np.array([0.2 * i - 1, 0.0, 0.0]))
        T_true[i, :3, 3] = eye
    rng = np.random.default_rng(7)
    T_est = apply_similarity(T_true, 2.0, random_rotation(rng), rng.normal(size=3))
    e = pose_errors(T_est, T_true)
    assert e["aligned_by"] == "centres+rotations"
    assert e["rotation_median_deg"] < 1e-6 and e["translation_median_pct"] < 1e-9


def test_pose_errors_refuse_bad_input():
    T = orbit_poses(5)
    with pytest.raises(InputError, match=r"\[N, 4, 4\]"):
        pose_errors(T, T[:4])
    with pytest.raises(InputError, match="one point"):
        pose_errors(T, np.tile(np.eye(4), (5, 1, 1)))
    bad = T.copy()
    bad[1, 0, 3] = np.inf
    with pytest.raises(InputError, match="finite"):
        pose_errors(bad, T)


def test_against_the_truth_at_its_own_poses_where_it_is_exact():
    """An exact estimate on a dense track scores 0 at the truth's few views, where comparing at
    the estimate's times would count the truth's own interpolation between them as error."""
    from evcap.records import Poses
    from evcap.trajectory_alignment import errors_against_truth

    dense = orbit_poses(201)
    t = np.arange(201, dtype=np.int64) * 5000
    truth = Poses(t[::25], dense[::25], source="ground truth")  # 9 views
    estimate = Poses(t[10:190], apply_similarity(dense[10:190], 0.2, np.eye(3), np.ones(3)))
    e = errors_against_truth(estimate, truth)
    assert e["compared"] == 7  # the truth's views inside the estimate's span
    assert np.allclose(e["seconds"], t[25:176:25] / 1e6)
    assert e["rotation_median_deg"] < 1e-6 and e["translation_median_pct"] < 1e-6
    at_estimate = pose_errors(estimate.T_world_cam, truth.at(estimate.t), by="poses")
    assert at_estimate["translation_median_pct"] > 0.1
