"""The camera's orientation from the gyroscope, tied to structure from motion's.

Structure from motion on event frames gets the orientations a degree or several wrong, slowly
varying along the path (the demo's orbit: 1.8 deg median, 5.7 deg at its ends), and the
reconstruction inherits it. The gyroscope measures how the camera turns at 1 kHz: integrated,
it gives the orientations up to one rotation (where the world is) and a drift (the gyroscope's
bias). Both are fitted to the structure from motion's orientations; over a path of many
frames their errors average out, the gyroscope's shape of the path does not.

The gyroscope is taken in the camera's axes, as the accelerometer is (poses/gravity.py): the
session's samples as recorded (the driver and the importers turn libcaer's axes into the
camera's, docs/poses.md), or turned by the
calibration's camera-IMU rotation and moved onto the camera's clock by its time shift when it
has them (`evcap calibrate --intrinsics` with a Kalibr camchain: ``in_camera_axes``). They are
held fixed, not fitted again: Kalibr measures them on a target with the camera swept through
every axis, where a path of event frames gives one rotation a few degrees wrong.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evcap.errors import InputError
from evcap.records import Poses
from evcap.rotations import exp_so3, log_so3
from evcap.streams import ImuSamples

MIN_SAMPLES = 50
MIN_FRAMES = 5
# the fit is refused when the gyroscope and the frames disagree by more than this (median,
# after the fit): the IMU is not in the camera's axes, or the frames' poses are wrong
MAX_DISAGREEMENT_DEG = 10.0
# a gyroscope's zero-rate offset (MPU-6500: +-5 deg/s at most, a fraction of a degree per
# second typically): a prior that keeps a short path's structure-from-motion errors from
# passing for a drift
BIAS_PRIOR_DEG_S = 0.5
# on a short path a gyroscope in other axes can still be turned to within a few degrees of the
# frames overall; the turns between frames a tenth of the path apart tell: on the demo's orbit
# they differ from the frames' by 0.31 of the turn with the right axes, by 0.93 with the axes
# cycled (a gyroscope mounted otherwise), so above this share it is refused
MAX_TURN_DISAGREEMENT = 0.6
MIN_TURN_DEG = 0.5  # turns smaller than this between those frames do not tell
# structure from motion's orientation error on event frames. It varies slowly along the path
# (one error shared by neighbouring frames, not one each), so the frames together weigh as one:
# the bias is then found to about this over the path's duration, and a 1 s path leaves it to
# the prior while a minute-long one is measured (on the demo's 1 s orbit, weighed frame by
# frame, the fit took 3.1 deg/s of bias from the frames' errors; the gyroscope had none)
ROTATION_NOISE_DEG = 2.0


@dataclass
class GyroFit:
    R_world_cam: np.ndarray  # [M, 3, 3] orientations at the given times, from the gyroscope
    bias: np.ndarray  # [3] rad/s, subtracted from the gyroscope's readings
    samples: int
    disagreement_deg: float  # median angle between the fitted and the given orientations

    def summary(self) -> str:
        return (
            f"orientations from the gyroscope ({self.samples:,} samples, bias "
            f"{np.degrees(np.linalg.norm(self.bias)):.2f} deg/s; "
            f"{self.disagreement_deg:.2f} deg from the frames', median)"
        )


def in_camera_axes(imu: ImuSamples, T_cam_imu: np.ndarray, timeshift_us: float) -> ImuSamples:
    """``imu`` in the camera's axes (gyroscope and accelerometer turned by T_cam_imu's
    rotation) and on the camera's clock (t_cam = t_imu - timeshift_us, Kalibr's sign)."""
    R = np.asarray(T_cam_imu, np.float64)[:3, :3]
    return ImuSamples(
        imu.t - int(round(timeshift_us)),
        imu.accel.astype(np.float64) @ R.T,
        imu.gyro.astype(np.float64) @ R.T,
        imu.temperature,
    )


def integrate(t_us: np.ndarray, gyro: np.ndarray, bias: np.ndarray) -> np.ndarray:
    """Orientations [N, 3, 3] at the samples' times, relative to the first: each step turns
    by the mean of its two readings (less the bias) over its length, in the camera's axes."""
    dt = np.diff(t_us).astype(np.float64)[:, None] * 1e-6
    steps = exp_so3((0.5 * (gyro[1:] + gyro[:-1]) - bias) * dt)
    R = np.concatenate([np.eye(3)[None], steps])
    shift = 1
    while shift < len(R):  # prefix products in log2(N) vectorised rounds
        R[shift:] = R[:-shift] @ R[shift:]
        shift *= 2
    return R


def _at(R: np.ndarray, t_us: np.ndarray, times: np.ndarray) -> np.ndarray:
    """R sampled at ``t_us``, at ``times`` (inside), turning at constant rate in between."""
    T = np.tile(np.eye(4), (len(R), 1, 1))
    T[:, :3, :3] = R
    return Poses(t_us, T).at(times)[:, :3, :3]


def _world(Rg: np.ndarray, R_frames: np.ndarray) -> np.ndarray:
    """The rotation G minimising sum |G Rg_i - R_i|^2 (chordal mean)."""
    U, _, Vt = np.linalg.svd(np.einsum("nij,nkj->ik", R_frames, Rg))
    return U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt


def fit_gyro(
    t_us: np.ndarray, R_frames: np.ndarray, imu_t: np.ndarray, gyro: np.ndarray
) -> GyroFit:
    """Orientations at ``t_us`` from the gyroscope, tied to the frames' orientations
    ``R_frames`` [M, 3, 3] (camera-to-world) by one rotation and the gyroscope's bias."""
    t_us, imu_t = np.asarray(t_us, np.int64), np.asarray(imu_t, np.int64)
    gyro = np.asarray(gyro, np.float64)
    ok = np.isfinite(gyro).all(axis=1)
    imu_t, first = np.unique(imu_t[ok], return_index=True)  # one sample per time, in order
    gyro = gyro[ok][first]
    inside = (t_us >= imu_t[0]) & (t_us <= imu_t[-1]) if len(imu_t) else np.zeros(len(t_us), bool)
    if len(imu_t) < MIN_SAMPLES or inside.sum() < MIN_FRAMES or not inside.all():
        raise InputError(
            f"the gyroscope covers {int(inside.sum())} of the {len(t_us)} posed frames "
            f"({len(imu_t)} samples): record with the IMU on for the whole path"
        )
    span = (imu_t >= t_us[0] - 10_000) & (imu_t <= t_us[-1] + 10_000)
    imu_t, gyro = imu_t[span], gyro[span]
    prior = np.sqrt(len(t_us)) * np.radians(ROTATION_NOISE_DEG) / np.radians(BIAS_PRIOR_DEG_S)

    def residuals(bias: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        Rg = _at(integrate(imu_t, gyro, bias), imu_t, t_us)
        R = _world(Rg, R_frames) @ Rg
        r = log_so3(np.swapaxes(R_frames, -1, -2) @ R).ravel()
        return np.concatenate([r, prior * bias]), R

    bias = np.zeros(3)
    for _ in range(5):  # Gauss-Newton on the bias (the world rotation is solved in closed form)
        r, _ = residuals(bias)
        J = np.stack([(residuals(bias + h)[0] - r) / 1e-6 for h in np.eye(3) * 1e-6], 1)
        step = np.linalg.lstsq(J, -r, rcond=None)[0]
        bias = bias + step
        if np.linalg.norm(step) < 1e-7:
            break
    r, R = residuals(bias)
    angles = np.linalg.norm(r[:-3].reshape(-1, 3), axis=1)
    disagreement = float(np.degrees(np.median(angles)))
    if disagreement > MAX_DISAGREEMENT_DEG:
        raise InputError(
            f"the gyroscope and the frames' orientations disagree by {disagreement:.1f} deg "
            "(median): is the IMU in the camera's axes?"
        )
    k = max(1, len(t_us) // 10)
    turns = log_so3(np.swapaxes(R_frames[:-k], -1, -2) @ R_frames[k:])
    gap = log_so3(np.swapaxes(R[:-k], -1, -2) @ R[k:]) - turns
    turn = float(np.median(np.linalg.norm(turns, axis=1)))
    share = float(np.median(np.linalg.norm(gap, axis=1))) / max(turn, 1e-12)
    if np.degrees(turn) >= MIN_TURN_DEG and share > MAX_TURN_DISAGREEMENT:
        raise InputError(
            f"the gyroscope's turns between frames differ from the frames' by {share:.0%} of "
            "them (median): is the IMU in the camera's axes?"
        )
    return GyroFit(R, bias, len(imu_t), disagreement)
