"""Orientations from the gyroscope, and the positions adjusted to orientations held fixed."""

from __future__ import annotations

import numpy as np
import pytest

from evcap.errors import InputError
from evcap.poses import gyro as gyro_module
from evcap.poses.gyro import fit_gyro, integrate
from evcap.poses.refine import refine_positions
from evcap.poses.sfm import Observations
from evcap.rotations import exp_so3, log_so3, skew
from evcap.sim.trajectory import look_at
from evcap.trajectory_alignment import align_similarity


def transposed(R: np.ndarray) -> np.ndarray:
    return np.swapaxes(R, -1, -2)


def angles_deg(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    return np.degrees(np.linalg.norm(log_so3(transposed(A) @ B), axis=-1))


def best_world(R_from: np.ndarray, R_to: np.ndarray) -> np.ndarray:
    """The rotation G with G R_from_i closest to R_to_i (chordal), computed here, not taken
    from the module under test."""
    U, _, Vt = np.linalg.svd(np.einsum("nij,nkj->ik", R_to, R_from))
    return U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt


def right_jacobian(phi: np.ndarray) -> np.ndarray:
    theta = np.linalg.norm(phi, axis=-1)[..., None, None]
    K = skew(phi)
    a, b = (1 - np.cos(theta)) / theta**2, (theta - np.sin(theta)) / theta**3
    return np.eye(3) - a * K + b * (K @ K)


def sinusoid_path(t_s: np.ndarray, amp, freq, phase) -> tuple[np.ndarray, np.ndarray]:
    """Camera-to-world orientations Exp(phi(t)) with phi a sum of sinusoids, and the angular
    velocity in the camera's axes (R' = R [w]x), in closed form: the truth does not come from
    the integration under test."""
    arg = np.asarray(freq) * t_s[:, None] + np.asarray(phase)
    phi, dphi = np.asarray(amp) * np.sin(arg), np.asarray(amp) * np.asarray(freq) * np.cos(arg)
    return exp_so3(phi), np.einsum("nij,nj->ni", right_jacobian(phi), dphi)


def us(t_s: np.ndarray) -> np.ndarray:
    return (np.asarray(t_s) * 1e6).round().astype(np.int64)


def test_log_undoes_exp_below_half_a_turn():
    rng = np.random.default_rng(0)
    axis = rng.normal(size=(500, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    v = axis * rng.uniform(0, np.radians(179), size=(500, 1))
    R = exp_so3(v)
    np.testing.assert_allclose(R @ transposed(R), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_allclose(log_so3(R), v, atol=1e-7)


def test_exp_of_a_tiny_vector_is_first_order():
    v = np.array([1e-10, -2e-10, 3e-10])
    R = exp_so3(v)
    np.testing.assert_allclose(R, np.eye(3) + skew(v), atol=1e-18)
    np.testing.assert_allclose(log_so3(R), v, rtol=1e-6)
    np.testing.assert_array_equal(exp_so3(np.zeros(3)), np.eye(3))


def test_a_constant_rate_turns_by_rate_times_duration():
    t = us(np.arange(1001) * 1e-3)
    w = 1.3 * np.array([2.0, -1.0, 0.5]) / np.linalg.norm([2.0, -1.0, 0.5])  # rad/s
    gyro = np.tile(w, (len(t), 1))
    R = integrate(t, gyro, np.zeros(3))
    assert R.shape == (1001, 3, 3)
    np.testing.assert_allclose(R[0], np.eye(3))
    np.testing.assert_allclose(log_so3(R[-1]), w * 1.0, atol=1e-6)
    np.testing.assert_allclose(log_so3(R[500]), w * 0.5, atol=1e-6)
    # a bias equal to the rate leaves nothing to turn by
    still = integrate(t, gyro, w)
    np.testing.assert_allclose(still, np.broadcast_to(np.eye(3), still.shape), atol=1e-12)


def test_integration_turns_in_the_cameras_axes():
    # non-commuting rates: integrating in the world's axes would end far from the truth
    t_s = np.arange(1001) * 1e-3
    R, w = sinusoid_path(t_s, [0.5, 0.3, 0.4], [2.0, 3.0, 1.5], [0.3, 1.0, 2.0])
    Rg = R[0] @ integrate(us(t_s), w, np.zeros(3))
    assert angles_deg(Rg, R).max() < 1e-3
    assert angles_deg(R[0], R[-1]) > 30


@pytest.fixture
def one_second():
    """A 1 s path turning ~40 deg, its gyroscope at 1 kHz (no bias), and 48 frames'
    orientations in a world of their own, each wrong by a slowly varying 2-6 deg."""
    amp, freq, phase = [0.5, 0.3, 0.4], [2.0, 3.0, 1.5], [0.3, 1.0, 2.0]
    imu_s = np.arange(1001) * 1e-3
    _, gyro = sinusoid_path(imu_s, amp, freq, phase)
    t_s = np.linspace(0.03, 0.82, 48)
    R_true, _ = sinusoid_path(t_s, amp, freq, phase)
    world = exp_so3(np.array([0.7, -1.9, 0.4]))
    # the error grows from 2 to 6 deg, its axis turning: a trend the bias must not take up
    s = (t_s - t_s[0]) / (t_s[-1] - t_s[0])
    axis = np.stack([np.cos(2.5 * s), np.sin(2.5 * s), 0.4 + 0 * s], 1)
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    error = exp_so3(np.radians(2 + 4 * s)[:, None] * axis)
    return us(t_s), world @ R_true @ error, R_true, us(imu_s), gyro


def test_the_gyroscope_fixes_slowly_varying_frame_errors(one_second):
    t, R_frames, R_true, imu_t, gyro = one_second
    fit = fit_gyro(t, R_frames, imu_t, gyro)
    assert fit.R_world_cam.shape == (48, 3, 3)
    fit_err = angles_deg(best_world(fit.R_world_cam, R_true) @ fit.R_world_cam, R_true)
    frame_err = angles_deg(best_world(R_frames, R_true) @ R_frames, R_true)
    assert np.median(fit_err) < 0.3 and fit_err.max() < 0.5
    assert np.median(frame_err) > 5 * np.median(fit_err)
    # the frames' trend is not mistaken for a drift of the gyroscope
    assert np.degrees(np.linalg.norm(fit.bias)) < 0.3
    assert 1 < fit.disagreement_deg < 6
    assert "deg" in fit.summary()


def long_path(duration_s: float, bias_deg_s: float, seed: int):
    amp, freq, phase = [0.35, 0.25, 0.3], [0.31, 0.47, 0.23], [0.3, 1.0, 2.0]
    imu_s = np.arange(round(duration_s * 1000) + 1) * 1e-3
    _, gyro = sinusoid_path(imu_s, amp, freq, phase)
    bias = np.radians([0.0, bias_deg_s, 0.0])
    t_s = np.arange(0.05, duration_s - 0.05, 0.1)
    R_true, _ = sinusoid_path(t_s, amp, freq, phase)
    rng = np.random.default_rng(seed)
    noise = exp_so3(rng.normal(0, np.radians(1.0) / np.sqrt(3), size=(len(t_s), 3)))
    world = exp_so3(np.array([-0.4, 1.1, 2.5]))
    return us(t_s), world @ R_true @ noise, R_true, us(imu_s), gyro + bias, bias


def test_a_minute_long_path_measures_the_gyroscopes_bias():
    t, R_frames, R_true, imu_t, gyro, bias = long_path(60.0, 0.5, seed=1)
    fit = fit_gyro(t, R_frames, imu_t, gyro)
    assert np.degrees(np.abs(fit.bias - bias)).max() < 0.1
    fit_err = angles_deg(best_world(fit.R_world_cam, R_true) @ fit.R_world_cam, R_true)
    assert np.median(fit_err) < 0.5


def test_a_20s_path_leaves_a_third_of_the_bias_to_the_prior():
    # the frames weigh as one (their errors taken as shared): over a path of T seconds they
    # measure the bias to ROTATION_NOISE / sqrt(T^2 / 12), which the prior then pulls towards 0
    t, R_frames, _, imu_t, gyro, bias = long_path(20.0, 0.5, seed=2)
    fit = fit_gyro(t, R_frames, imu_t, gyro)
    spread = np.var(t / 1e6)  # T^2 / 12
    prior_s = gyro_module.ROTATION_NOISE_DEG / gyro_module.BIAS_PRIOR_DEG_S
    shrink = spread / (spread + prior_s**2)
    assert 0.6 < shrink < 0.75
    np.testing.assert_allclose(np.degrees(fit.bias), np.degrees(shrink * bias), atol=0.03)


def test_a_gyroscope_in_other_axes_is_refused(one_second):
    t, R_frames, _, imu_t, gyro = one_second
    with pytest.raises(InputError, match="camera's axes"):
        fit_gyro(t, R_frames, imu_t, -gyro)
    # mounted turned half a turn about its x axis
    with pytest.raises(InputError, match="camera's axes"):
        fit_gyro(t, R_frames, imu_t, gyro * [1, -1, -1])


@pytest.mark.parametrize(
    "mounted",
    [
        lambda g: g[:, [1, 2, 0]] * [-1, 1, -1],  # axes cycled (a rotation)
        lambda g: g[:, [2, 0, 1]] * [-1, -1, 1],
        lambda g: g[:, [2, 1, 0]] * [1, 1, -1],
        lambda g: g * [-1, 1, 1],  # one axis reversed
        lambda g: g[:, [0, 2, 1]],  # two axes swapped
    ],
)
def test_a_gyroscope_mounted_otherwise_is_refused_on_a_short_path(one_second, mounted):
    # turned as a whole, these come within 10 deg of the frames on a 42 deg path; the turns
    # between frames do not
    t, R_frames, _, imu_t, gyro = one_second
    with pytest.raises(InputError, match="camera's axes"):
        fit_gyro(t, R_frames, imu_t, mounted(gyro))


def test_the_calibrations_camera_imu_transform_brings_the_gyroscope_to_the_camera(one_second):
    """An IMU mounted otherwise, its clock 8 ms ahead: refused as it is; turned and shifted by
    the calibration's T_cam_imu and time shift (Kalibr's), the fit is the one of a gyroscope
    in the camera's axes."""
    from evcap.poses.gyro import in_camera_axes
    from evcap.streams import ImuSamples

    t, R_frames, _, imu_t, gyro = one_second
    R_imu_cam = exp_so3(np.radians([10.0, -20.0, 90.0]))
    shift_us = 8000
    n = len(imu_t)
    mounted = ImuSamples(imu_t + shift_us, gyro @ R_imu_cam.T, gyro @ R_imu_cam.T, np.full(n, 25.0))
    with pytest.raises(InputError, match="camera's axes"):
        fit_gyro(t, R_frames, mounted.t, mounted.gyro)
    T_cam_imu = np.eye(4)
    T_cam_imu[:3, :3] = R_imu_cam.T
    back = in_camera_axes(mounted, T_cam_imu, shift_us)
    np.testing.assert_array_equal(back.t, imu_t)
    np.testing.assert_allclose(back.gyro, gyro, atol=1e-6)  # float32 storage
    np.testing.assert_allclose(back.accel, gyro, atol=1e-6)
    fit, direct = fit_gyro(t, R_frames, back.t, back.gyro), fit_gyro(t, R_frames, imu_t, gyro)
    assert angles_deg(fit.R_world_cam, direct.R_world_cam).max() < 1e-3


def test_too_few_gyroscope_samples_are_refused(one_second):
    t, R_frames, _, imu_t, gyro = one_second
    few = np.linspace(0, len(imu_t) - 1, 40).round().astype(int)
    with pytest.raises(InputError, match="IMU"):
        fit_gyro(t, R_frames, imu_t[few], gyro[few])


K = np.array([[260.0, 0, 173], [0, 260.0, 130], [0, 0, 1]])
WIDTH, HEIGHT = 346, 260


def project(R_world_cam, centres, X):
    """Pixels [M, P, 2] and depths [M, P] of points X [P, 3] in each camera."""
    Y = np.einsum("mji,mpj->mpi", R_world_cam, X[None] - centres[:, None])
    return K[:2, :2].diagonal() * Y[..., :2] / Y[..., 2:] + K[:2, 2], Y[..., 2]


@pytest.fixture
def arc_scene():
    """20 cameras on an arc about 2 m from 200 points, looking near the middle; each point
    seen (0.3 px noise) by the cameras whose image it falls in."""
    rng = np.random.default_rng(5)
    a = np.linspace(-0.7, 0.7, 20)
    centres = np.stack([2.2 * np.sin(a), -2.2 * np.cos(a), 0.3 * np.sin(2 * a)], 1)
    targets = rng.normal(0, 0.15, size=(20, 3))
    R = np.stack([look_at(c, g) for c, g in zip(centres, targets, strict=True)])
    X = rng.uniform([-1.0, -0.6, -0.7], [1.0, 0.8, 0.7], size=(200, 3))
    xy, depth = project(R, centres, X)
    seen = (depth > 0.1) & (xy[..., 0] >= 0) & (xy[..., 0] <= WIDTH - 1)
    seen &= (xy[..., 1] >= 0) & (xy[..., 1] <= HEIGHT - 1)
    frame, point = np.nonzero(seen)
    xy = xy[frame, point] + rng.normal(0, 0.3, size=(len(frame), 2))
    obs = Observations(frame.astype(np.int64), point.astype(np.int64), xy)
    length = np.linalg.norm(np.diff(centres, axis=0), axis=1).sum()
    return R, centres, X, obs, length


def centre_errors(estimate, truth):
    scale, R, t = align_similarity(estimate, truth)
    return np.linalg.norm(scale * estimate @ R.T + t - truth, axis=1)


def perturbed(centres, X, length, seed):
    rng = np.random.default_rng(seed)
    return (
        centres + rng.normal(0, 0.05 * length / np.sqrt(3), centres.shape),
        X + rng.normal(0, 0.03 / np.sqrt(3), X.shape),
    )


def test_positions_are_refined_to_the_noise(arc_scene):
    R, centres, X, obs, length = arc_scene
    assert np.bincount(obs.point, minlength=len(X)).min() >= 2
    C0, X0 = perturbed(centres, X, length, seed=6)
    refined = refine_positions(R, C0, X0, obs, K, np.zeros(5))
    assert refined.start_rms_px > 5
    assert refined.rms_px < 0.6
    assert refined.rms_px < refined.start_rms_px
    assert centre_errors(C0, centres).max() > 0.03 * length
    assert centre_errors(refined.centres, centres).max() < 0.002 * length


def test_gross_outliers_are_held_off_by_the_huber_weights(arc_scene):
    R, centres, X, obs, length = arc_scene
    rng = np.random.default_rng(7)
    bad = rng.random(len(obs.xy)) < 0.05
    direction = rng.normal(size=(bad.sum(), 2))
    xy = obs.xy.copy()
    xy[bad] += 30 * direction / np.linalg.norm(direction, axis=1, keepdims=True)
    C0, X0 = perturbed(centres, X, length, seed=8)
    refined = refine_positions(R, C0, X0, Observations(obs.frame, obs.point, xy), K, np.zeros(5))
    # plain least squares ends 0.4-0.8 % of the path off here, the inliers at ~1.8 px
    assert centre_errors(refined.centres, centres).max() < 0.003 * length
    # the sightings that were not spoiled still fit to about their noise
    fit, _ = project(R, refined.centres, refined.points)
    residual = np.linalg.norm(fit[obs.frame, obs.point] - xy, axis=1)
    assert np.sqrt(np.mean(residual[~bad] ** 2)) < 0.8
