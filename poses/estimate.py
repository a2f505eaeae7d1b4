"""`evcap poses`: the camera's path from the events alone. Frames are made from the events
(poses/frames.py), structure from motion runs on them with the calibrated intrinsics fixed
(poses/sfm.py), and the registered frames' camera-to-world transforms are written to /poses
(the Poses record, which the reconstruction interpolates at any time)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from evcap.errors import InputError, PosesError
from evcap.poses.frames import FrameKind, check_kind, event_frames, frame_rate, memory_us
from evcap.poses.gravity import Gravity, gravity_up, level, level_rotation
from evcap.poses.gyro import GyroFit, fit_gyro, in_camera_axes
from evcap.poses.refine import Refined, refine_positions
from evcap.poses.sfm import SfmResult, run_sfm
from evcap.records import Calibration, Poses
from evcap.records.calibration import describe_camera_imu
from evcap.session import Session
from evcap.streams import Frames, ImuSamples

MIN_EVENTS = 10_000
# The complementary filter leans on the latest APS frame; when the camera turns more than this
# between two frames, the events on top of it ghost and the high-pass filter registers better
# (measured: 1.4 deg per frame on the hand-held board, 0.3 deg median error with the frames;
# 7 deg on the demo orbit, 17 deg with them and 2.2 deg without).
APS_MAX_TURN_DEG = 2.0
APS_MIN_RATE_HZ = 20.0  # without the IMU, the frames' rate stands in for the motion
# the gyroscope's orientations are refused when the positions and points cannot be made to fit
# them within this (reprojection, px RMS; on the demo's orbit 2.2 px, the frames' own 1.1):
# the gyroscope's clock or axes are not the camera's
MAX_GYRO_REPROJECTION_PX = 5.0
# an IMU that moved no more than this (99 % of its samples, about their median or mean) was on a
# camera standing still: the real DAVIS346 recording on a desk reads 0.34 deg/s and 0.09 m/s^2,
# its sensors' noise; a hand-held camera turns tens of degrees a second
STILL_GYRO_DEG_S = 2.0
STILL_ACCEL_M_S2 = 0.3


@dataclass
class PosesResult:
    """What `evcap poses` found."""

    t_us: np.ndarray  # [M] int64, times of the registered frames
    T_world_cam: np.ndarray  # [M, 4, 4] camera-to-world, OpenCV axes, arbitrary scale
    frames: int  # frames made from the events
    rate_hz: float
    kind: FrameKind  # how the frames were made
    mean_reprojection_px: float
    points: int  # 3D points of the model
    seconds: float  # structure from motion's time
    gravity: Gravity | None = None  # when the world was leveled with the IMU
    points_xyz: np.ndarray | None = None  # [P, 3] the model's points, in the poses' world
    gyro: GyroFit | None = None  # when the orientations are the gyroscope's
    refined: Refined | None = None  # the positions adjusted to the gyroscope's orientations

    def record(self) -> Poses:
        """The /poses record of the estimate: the registered frames' transforms and points,
        with how they were found in its notes."""
        return Poses(
            self.t_us,
            self.T_world_cam,
            source=f"evcap poses ({self.kind} frames, pycolmap)",
            scale="arbitrary (structure from motion: no metric scale)",
            points_xyz=self.points_xyz,
            notes={
                "up": self.up,
                "orientations": self.turned,
                "registered": self.registered,
                "frames": self.frames,
                "rate_hz": self.rate_hz,
                "mean_reprojection_px": self.mean_reprojection_px,
                "points": self.points,
            },
        )

    @property
    def registered(self) -> int:
        return len(self.t_us)

    def summary(self) -> str:
        return (
            f"{self.registered} of {self.frames} frames registered ({self.kind} frames at "
            f"{self.rate_hz:.1f} Hz), {self.points:,} points, mean reprojection error "
            f"{self.mean_reprojection_px:.3f} px; {self.turned}; scale arbitrary; {self.up}"
        )

    @property
    def turned(self) -> str:
        if self.gyro is None or self.refined is None:
            return "orientations from the frames"
        return (
            f"{self.gyro.summary()}, positions adjusted to them (reprojection "
            f"{self.refined.start_rms_px:.2f} -> {self.refined.rms_px:.2f} px RMS)"
        )

    @property
    def up(self) -> str:
        if self.gravity is None:
            return "orientation arbitrary"
        return (
            f"z up (leveled with {self.gravity.samples:,} IMU samples; their force "
            f"{self.gravity.magnitude:.2f} m/s^2, spread {self.gravity.spread_deg:.1f} deg)"
        )


def estimate_poses(
    path: str | Path,
    *,
    kind: FrameKind = "filter",
    weights: str | Path | None = None,
    rate_hz: float | None = None,
    export_frames: str | Path | None = None,
    gravity: bool = True,
    gyro: bool = True,
    aps: bool | None = None,
    threads: int = 1,
    say: Callable[[str], None] = lambda line: None,
    progress: Callable[[int, int, str], None] | None = None,
) -> PosesResult:
    """Make frames from the session's events and register them by structure from motion;
    with ``gyro``, take the orientations from the gyroscope when the session has it
    (poses/gyro.py) and adjust the positions to them (poses/refine.py); with ``gravity``, turn
    the world so that z is up when the session has the IMU. ``aps``:
    whether the filter's frames lean on the APS frames; None decides from the motion between
    them (`aps_frames_usable`). ``threads``: structure from motion's (see run_sfm)."""

    with Session.open(path) as s:
        cal = Calibration.read(s)
        K, model, dist = cal.intrinsics(str(path))
        if model not in ("none", "radtan"):
            raise InputError(f"{path}: structure from motion takes radtan distortion only")
        events = s.events()
        frames = s.frames()
        imu = s.imu()
    if len(imu) and cal.T_cam_imu is not None:
        imu = in_camera_axes(imu, cal.T_cam_imu, cal.timeshift_cam_imu_us)
        source = cal.notes.get("camera_imu_source", cal.source)
        say(
            "IMU turned into the camera's axes and clock by the calibration's camera-IMU "
            f"transform ({source}): {describe_camera_imu(cal.T_cam_imu, cal.timeshift_cam_imu_us)}"
        )
    on = cal.threshold_on if cal.threshold_on is not None else 0.2
    off = cal.threshold_off if cal.threshold_off is not None else 0.2
    if len(events) < MIN_EVENTS:
        raise InputError(
            f"{path}: {len(events):,} events; poses from events need at least {MIN_EVENTS:,} "
            "(a longer recording, with the camera moving)"
        )
    rate = frame_rate(events) if rate_hz is None else float(rate_hz)
    if not 0 < rate <= 1000:
        raise InputError(f"--rate must be in (0, 1000] Hz, got {rate_hz}")
    check_kind(kind)
    with_aps = False
    if kind == "filter" and len(frames):
        usable, why = aps_frames_usable(frames, imu)
        with_aps = usable if aps is None else aps
        if aps is None:
            say(f"APS frames {'used' if usable else 'left out'}: {why}")
    step = int(round(1e6 / rate))
    # the first frame once the frame has its memory's worth of events (an APS frame gives the
    # complementary filter its memory at once), on the same grid of times: on the single-object
    # orbit the filter's first frame, 17 ms in, did not register; a first frame off the grid
    # (53 ms in) moved every frame's time and left 22 of the demo's 57 frames out
    warm = 0 if with_aps else memory_us(kind)
    first = int(events.t[0]) + step * max(1, -(-warm // step))
    times = np.arange(first, int(events.t[-1]) + 1, step, dtype=np.int64)
    if len(times) < 3:
        raise InputError(f"{path}: the events span too short a time for {rate:g} Hz frames")
    name = "complementary filter (events and APS frames)" if with_aps else kind
    say(f"frames: {len(times)} at {rate:.1f} Hz, {name}, from {len(events):,} events")
    images = event_frames(
        events,
        times,
        kind=kind,
        weights=weights,
        threshold_on=on,
        threshold_off=off,
        hot_pixels=cal.hot_pixels,
        aps=frames if with_aps else None,
        progress=(lambda done, total: progress(done, total, "frames")) if progress else None,
    )
    if export_frames is not None:
        write_frames(images, times, export_frames)
        say(f"frames written to {export_frames}")
    say("structure from motion (pycolmap), intrinsics fixed to the calibration")
    try:
        sfm = run_sfm(list(images), times, K, dist, threads=threads, progress=progress)
    except PosesError as e:
        still = stood_still(imu)
        if still:
            raise PosesError(f"{e}; {still}") from None
        raise
    T_world_cam, up, points = sfm.T_world_cam, None, sfm.points_xyz
    turned, refined = None, None
    if gyro and len(imu) and sfm.observations is not None:
        T_world_cam, turned, refined = gyro_poses(sfm, imu, K, dist, say)
        points = refined.points if refined is not None else points
    if gravity and len(imu) and len(sfm.t_us) >= 2:
        try:
            up = gravity_up(Poses(sfm.t_us, T_world_cam), imu.t, imu.accel)
            T_world_cam = level(T_world_cam, up.up)
            points = points @ level_rotation(up.up).T
        except InputError as e:  # the poses stand without it
            say(f"not leveled with the IMU: {e}")
    return PosesResult(
        t_us=sfm.t_us,
        T_world_cam=T_world_cam,
        frames=len(times),
        rate_hz=rate,
        kind="complementary filter" if with_aps else kind,
        mean_reprojection_px=float(sfm.mean_reprojection_px),
        points=int(sfm.points),
        seconds=float(sfm.seconds),
        gravity=up,
        points_xyz=points,
        gyro=turned,
        refined=refined,
    )


def gyro_poses(
    sfm: SfmResult, imu: ImuSamples, K: np.ndarray, dist: np.ndarray, say: Callable[[str], None]
) -> tuple[np.ndarray, GyroFit | None, Refined | None]:
    """The registered frames' camera-to-world transforms with the gyroscope's orientations and
    the positions adjusted to them; structure from motion's (and None, None), saying why, when
    the gyroscope does not fit the frames."""
    try:
        turned = fit_gyro(sfm.t_us, sfm.T_world_cam[:, :3, :3], imu.t, imu.gyro)
    except InputError as e:
        say(f"orientations from the frames, not the gyroscope: {e}")
        return sfm.T_world_cam, None, None
    refined = refine_positions(
        turned.R_world_cam, sfm.T_world_cam[:, :3, 3], sfm.points_xyz, sfm.observations, K, dist
    )
    if not refined.rms_px <= MAX_GYRO_REPROJECTION_PX:
        say(
            "orientations from the frames, not the gyroscope: the points fit the gyroscope's "
            f"only to {refined.rms_px:.1f} px (are the IMU's axes and clock the camera's?)"
        )
        return sfm.T_world_cam, None, None
    T = sfm.T_world_cam.copy()
    T[:, :3, :3] = turned.R_world_cam
    T[:, :3, 3] = refined.centres
    return T, turned, refined


def aps_frames_usable(frames: Frames, imu: ImuSamples) -> tuple[bool, str]:
    """Whether the APS frames come often enough for the motion to lean the event frames on
    them, and why: the median angle the gyroscope turns between two frames' mid-exposures,
    or, without the IMU, the frames' rate."""
    if len(frames) < 2:
        return False, "fewer than two"
    mid = frames.t + frames.exposure_us // 2
    rate = 1e6 / max(float(np.median(np.diff(mid))), 1.0)
    if len(imu) < 2:
        usable = rate >= APS_MIN_RATE_HZ
        return usable, f"{rate:.0f} Hz {'>=' if usable else '<'} {APS_MIN_RATE_HZ:g} Hz, no IMU"
    speed = np.linalg.norm(imu.gyro.astype(np.float64), axis=1)
    turned = np.concatenate([[0.0], np.cumsum((speed[1:] + speed[:-1]) / 2 * np.diff(imu.t) / 1e6)])
    turn = float(np.degrees(np.median(np.diff(np.interp(mid, imu.t, turned)))))
    usable = turn <= APS_MAX_TURN_DEG
    return usable, (
        f"at {rate:.0f} Hz the camera turns {turn:.1f} deg between them "
        f"({'<=' if usable else '>'} {APS_MAX_TURN_DEG:g} deg)"
    )


def stood_still(imu: ImuSamples) -> str:
    """Why the IMU says the camera stood still, or "" when it moved (or there is no IMU)."""
    if len(imu) < 50:
        return ""
    gyro, accel = np.degrees(imu.gyro.astype(np.float64)), imu.accel.astype(np.float64)
    turn = float(np.percentile(np.linalg.norm(gyro - np.median(gyro, 0), axis=1), 99))
    shake = float(np.percentile(np.linalg.norm(accel - accel.mean(0), axis=1), 99))
    if turn > STILL_GYRO_DEG_S or shake > STILL_ACCEL_M_S2:
        return ""
    return (
        f"the IMU says the camera stood still: it turned at most {turn:.2f} deg/s and its "
        f"accelerometer varied by {shake:.2f} m/s^2 (99 % of the samples: its sensors' noise)"
    )


def write_poses(path: str | Path, result: PosesResult) -> None:
    """Replace the session's /poses with ``result``."""
    result.record().write(path)


def write_frames(images: np.ndarray, times_us: np.ndarray, folder: str | Path) -> None:
    """PNG per frame, named by its time (µs), for inspection."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(f"cannot create {folder}: {e.strerror or e}") from None
    for image, t in zip(images, times_us, strict=True):
        if not cv2.imwrite(str(folder / f"frame_{int(t):012d}us.png"), image):
            raise InputError(f"cannot write frames into {folder}")
