"""Quaternion helpers and the interpolated camera pose track."""

import numpy as np
import pytest

from evcap.errors import InputError
from evcap.records import Poses
from evcap.rotations import quat_to_rotmat, rotmat_to_quat, slerp
from evcap.session import SensorInfo, Session, SessionWriter

T0 = 1_700_000_000_000_000


def random_quats(rng, n):
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def axis_angle_quat(axis, angle):
    axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])


def quat_angle(q0, q1):
    """Rotation angle between unit quaternions, precise for small and large angles."""
    minus, plus = np.linalg.norm(q0 - q1, axis=-1), np.linalg.norm(q0 + q1, axis=-1)
    return 4 * np.arctan2(np.minimum(minus, plus), np.maximum(minus, plus))


def assert_same_rotation(q, q_ref, atol=1e-12):
    q, q_ref = np.broadcast_arrays(np.asarray(q), np.asarray(q_ref))
    sign = np.where((q * q_ref).sum(-1, keepdims=True) < 0, -1.0, 1.0)
    np.testing.assert_allclose(q, sign * q_ref, atol=atol, rtol=0)


def assert_proper_rotation(R):
    eye = np.broadcast_to(np.eye(3), R.shape)
    np.testing.assert_allclose(np.swapaxes(R, -1, -2) @ R, eye, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)


def make_track(n=5, seed=0, dt=1000):
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = quat_to_rotmat(random_quats(rng, n))
    T[:, :3, 3] = rng.normal(size=(n, 3))
    return Poses(T0 + dt * np.arange(n), T)


def test_quat_rotmat_round_trip_on_random_rotations():
    q = random_quats(np.random.default_rng(1), 500)
    q[q[:, 0] < 0] *= -1
    R = quat_to_rotmat(q)
    assert_proper_rotation(R)
    q_back = rotmat_to_quat(R)
    assert q_back.shape == (500, 4)
    assert (q_back[:, 0] >= 0).all()
    np.testing.assert_allclose(q_back, q, atol=1e-12)
    np.testing.assert_allclose(quat_to_rotmat(q_back), R, atol=1e-12)


def test_quat_rotmat_round_trip_near_180_degrees():
    rng = np.random.default_rng(2)
    axes = rng.normal(size=(200, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    eps = np.concatenate([[0.0, 1e-12, 1e-9], 10.0 ** -rng.uniform(3, 10, 197)])
    angles = np.pi - eps
    q = np.stack([axis_angle_quat(a, t) for a, t in zip(axes, angles, strict=True)])
    q_back = rotmat_to_quat(quat_to_rotmat(q))
    assert (q_back[:, 0] >= 0).all()
    assert_same_rotation(q_back, q, atol=1e-12)


def test_quat_rotmat_identity_and_batch_shapes():
    np.testing.assert_array_equal(rotmat_to_quat(np.eye(3)), [1.0, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(quat_to_rotmat([1.0, 0.0, 0.0, 0.0]), np.eye(3))
    q = random_quats(np.random.default_rng(3), 6).reshape(2, 3, 4)
    R = quat_to_rotmat(q)
    assert R.shape == (2, 3, 3, 3)
    assert rotmat_to_quat(R).shape == (2, 3, 4)


def test_quat_to_rotmat_normalizes_its_input():
    q = random_quats(np.random.default_rng(4), 10)
    np.testing.assert_allclose(quat_to_rotmat(3.5 * q), quat_to_rotmat(q), atol=1e-14)


def test_slerp_endpoints_are_the_inputs():
    rng = np.random.default_rng(5)
    q0, q1 = random_quats(rng, 50), random_quats(rng, 50)
    q1[(q0 * q1).sum(1) < 0] *= -1
    np.testing.assert_allclose(slerp(q0, q1, np.zeros(50)), q0, atol=1e-14)
    np.testing.assert_allclose(slerp(q0, q1, np.ones(50)), q1, atol=1e-14)


def test_slerp_midpoint_about_one_axis_is_the_mean_angle():
    rng = np.random.default_rng(6)
    for _ in range(20):
        axis = rng.normal(size=3)
        a = rng.uniform(-3, 3)
        b = a + rng.uniform(-3, 3)
        mid = slerp(axis_angle_quat(axis, a), axis_angle_quat(axis, b), np.float64(0.5))
        assert_same_rotation(mid, axis_angle_quat(axis, (a + b) / 2))


def test_slerp_has_constant_angular_speed():
    rng = np.random.default_rng(7)
    s = np.linspace(0, 1, 11)
    for _ in range(10):
        q0, q1 = random_quats(rng, 2)
        q = slerp(q0, q1, s)
        angles = quat_angle(q0, q)
        np.testing.assert_allclose(angles, s * quat_angle(q0, q1), atol=1e-12)
        np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-14)


def test_slerp_takes_the_short_way_when_dot_is_negative():
    axis = [0.3, -1.0, 0.5]
    q0, q1 = axis_angle_quat(axis, 0.2), axis_angle_quat(axis, 0.6)
    s = np.linspace(0, 1, 9)
    q = slerp(q0, -q1, s)
    for qi, si in zip(q, s, strict=True):
        assert_same_rotation(qi, axis_angle_quat(axis, 0.2 + 0.4 * si))
    assert quat_angle(q0, q).max() == pytest.approx(0.4, abs=1e-12)


def test_slerp_of_nearly_identical_quaternions_is_finite():
    q0 = axis_angle_quat([1.0, 2.0, 3.0], 0.7)
    s = np.linspace(0, 1, 5)
    for delta in (0.0, 1e-17, 1e-12, 1e-9, 1e-7):
        q1 = axis_angle_quat([1.0, 2.0, 3.0], 0.7 + delta)
        for other in (q1, -q1):
            q = slerp(q0, other, s)
            assert np.isfinite(q).all()
            assert_same_rotation(q, q0, atol=1e-7)


def test_track_at_sample_times_returns_stored_poses():
    track = make_track(6)
    np.testing.assert_allclose(track.at(track.t), track.T_world_cam, atol=1e-12, rtol=0)
    for k in range(6):
        np.testing.assert_allclose(track.at(int(track.t[k])), track.T_world_cam[k], atol=1e-12)
    assert (track.start, track.end) == (T0, T0 + 5000)


def test_track_positions_are_linear_between_samples():
    track = make_track(4, dt=997)
    s = np.linspace(0, 1, 998)
    for k in range(3):
        t = track.t[k] + np.arange(998)
        p0, p1 = track.T_world_cam[k, :3, 3], track.T_world_cam[k + 1, :3, 3]
        np.testing.assert_allclose(
            track.at(t)[:, :3, 3], p0 + s[:, None] * (p1 - p0), atol=1e-12, rtol=0
        )


def test_track_rotations_are_slerped_between_samples():
    track = make_track(4, seed=8)
    q = rotmat_to_quat(track.T_world_cam[:, :3, :3])
    s = np.array([0.0, 0.1, 0.25, 0.5, 0.731, 0.999])
    for k in range(3):
        t = track.t[k] + np.round(s * 1000).astype(np.int64)
        got = rotmat_to_quat(track.at(t)[:, :3, :3])
        assert_same_rotation(got, slerp(q[k], q[k + 1], s), atol=1e-12)


def test_track_rotation_about_one_axis_turns_at_constant_rate_per_segment():
    axis = [0.2, 1.0, -0.4]
    angles = [0.0, 0.8, 2.0, 2.5]
    T = np.tile(np.eye(4), (4, 1, 1))
    T[:, :3, :3] = quat_to_rotmat(np.stack([axis_angle_quat(axis, a) for a in angles]))
    track = Poses(T0 + np.array([0, 400, 1400, 1500]), T)
    t = T0 + np.arange(0, 1501, 50)
    expected = np.interp(t - T0, [0, 400, 1400, 1500], angles)
    got = rotmat_to_quat(track.at(t)[:, :3, :3])
    want = np.stack([axis_angle_quat(axis, a) for a in expected])
    assert_same_rotation(got, want, atol=1e-12)


def test_track_returns_proper_rotations_and_homogeneous_rows():
    track = make_track(7, seed=9)
    t = np.random.default_rng(9).integers(track.start, track.end + 1, 300)
    T = track.at(t)
    assert_proper_rotation(T[:, :3, :3])
    np.testing.assert_array_equal(T[:, 3], np.broadcast_to([0.0, 0.0, 0.0, 1.0], (300, 4)))


def test_track_at_accepts_scalars_and_arrays_of_any_shape():
    track = make_track(3)
    t = track.start + np.array([[0, 250, 1000], [1500, 1999, 2000]])
    T = track.at(t)
    assert T.shape == (2, 3, 4, 4)
    assert track.at(track.start + 250).shape == (4, 4)
    assert track.at(np.int64(track.start + 250)).shape == (4, 4)
    assert track.at([track.start]).shape == (1, 4, 4)
    np.testing.assert_array_equal(track.at(int(t[1, 1])), T[1, 1])


@pytest.mark.parametrize("offset", [-1, 2001, -(10**9), 10**12])
def test_track_at_outside_the_span_raises_naming_it(offset):
    track = make_track(3)
    span = f"{T0}..{T0 + 2000}"
    with pytest.raises(InputError, match=span):
        track.at(T0 + offset)
    with pytest.raises(InputError, match=span):
        track.at(np.array([T0, T0 + 1000, T0 + offset]))


def test_track_construction_errors():
    T = np.tile(np.eye(4), (3, 1, 1))
    with pytest.raises(InputError, match="increase"):
        Poses([0, 10, 10], T)
    with pytest.raises(InputError, match="increase"):
        Poses([0, 20, 10], T)
    with pytest.raises(InputError, match="at least two"):
        Poses([0], T[:1])
    with pytest.raises(InputError, match="at least two"):
        Poses(np.zeros(0, np.int64), np.zeros((0, 4, 4)))
    for bad in (np.nan, np.inf):
        T_bad = T.copy()
        T_bad[1, 0, 3] = bad
        with pytest.raises(InputError, match="NaN"):
            Poses([0, 10, 20], T_bad)
    with pytest.raises(InputError, match="shape"):
        Poses([0, 10], T)
    with pytest.raises(InputError, match="shape"):
        Poses([0, 10, 20], T[:, :3, :])


def test_from_session_without_poses_says_to_run_evcap_poses(tmp_path):
    path = tmp_path / "s.h5"
    with SessionWriter(path, SensorInfo("simulated", 8, 6, "RGBG", "SIM0001", T0)):
        pass
    with Session.open(path) as s, pytest.raises(InputError, match="run `evcap poses`"):
        Poses.read(s)
