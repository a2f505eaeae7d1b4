"""What the sensor makes of radiance: the log signal of each pixel's color channel, APS frames
(exposure, shot and read noise, 10 bits) and IMU samples (from the camera's path); the
sensor's calibration, measured (a calibrated session's) or true (the simulated one's)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from evcap.errors import InputError
from evcap.events import pixel_channels
from evcap.records import Calibration
from evcap.sim.events import PixelArray
from evcap.sim.scene import ApsSpec, ImuSpec

LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


class ChannelMap:
    """Which part of the radiance each pixel sees, through its color filter."""

    def __init__(self, width: int, height: int, color_filter: str) -> None:
        yy, xx = np.mgrid[0:height, 0:width]
        self.channel = pixel_channels(xx.ravel(), yy.ravel(), color_filter).astype(np.int64)
        self.mono = color_filter == "MONO"

    def of(self, radiance: np.ndarray, pixels: np.ndarray | None = None) -> np.ndarray:
        """[P] the radiance each pixel (flat indices; None: all) measures."""
        if self.mono:
            return radiance @ LUMINANCE
        ch = self.channel if pixels is None else self.channel[pixels]
        return np.take_along_axis(radiance, ch[:, None], axis=1)[:, 0]

    def log(
        self, radiance: np.ndarray, dark: float, pixels: np.ndarray | None = None
    ) -> np.ndarray:
        """log(L + dark): the dark level keeps black pixels (L = 0) finite."""
        return np.log(np.maximum(self.of(radiance, pixels), 0.0) + dark)


def aps_frame(mean_radiance: np.ndarray, spec: ApsSpec, rng: np.random.Generator) -> np.ndarray:
    """A raw APS frame (10-bit) from each pixel's radiance averaged over the exposure:
    gain * radiance * exposure (ms) ADC counts, with Poisson shot noise (in counts) and
    Gaussian read noise."""
    signal = spec.gain * mean_radiance * spec.exposure_us / 1000.0
    if spec.shot_noise:
        signal = rng.poisson(np.maximum(signal, 0)).astype(np.float64)
    signal = signal + rng.normal(0, spec.read_noise, signal.shape)
    return np.clip(np.round(signal), 0, 1023).astype(np.uint16)


def imu_samples(
    trajectory, spec: ImuSpec, units_per_meter: float, rng: np.random.Generator
) -> tuple[np.ndarray, ...]:
    """(t us, accel m/s^2, gyro rad/s, temperature degC) at spec.rate_hz along the path."""
    n = int(trajectory.duration_s * spec.rate_hz) + 1
    t = np.arange(n) / spec.rate_hz
    accel, gyro = trajectory.imu(t, units_per_meter)
    accel = accel + rng.normal(0, spec.accel_noise, accel.shape) if spec.accel_noise else accel
    gyro = gyro + rng.normal(0, spec.gyro_noise, gyro.shape) if spec.gyro_noise else gyro
    return np.round(t * 1e6).astype(np.int64), accel, gyro, np.full(n, 25.0)


def measured_sensor(
    path: Path, effects: dict, n_pixels: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """(threshold ON, OFF per pixel, hot pixels (flat indices), effects) of the sensor that a
    calibrated session measured (`evcap calibrate`); ``effects`` the scene lists win."""
    from evcap.session import Session

    with Session.open(path, validate=False) as s:
        cal = Calibration.read(s)
    on, off = cal.thresholds(str(path))
    if on.size != n_pixels:
        raise InputError(f"{path}: its calibration has {on.size} pixels, the camera {n_pixels}")
    hot = np.flatnonzero(cal.hot())
    measured = {
        "background_activity": {"rate_hz": cal.background_activity_hz},
        "shot_noise": {"rate_hz": cal.shot_noise_hz},
        "refractory": {"period_us": int(cal.refractory_period_us)},
    }
    if len(hot):
        rate = cal.event_rate_hz
        hot_rate = float(np.median(rate.ravel()[hot])) if rate is not None else 200.0
        measured["hot_pixels"] = {"count": len(hot), "rate_hz": hot_rate}
    out = {k: v for k, v in measured.items() if next(iter(v.values())) > 0}
    out.update(effects)
    return on.ravel().astype(np.float64), off.ravel().astype(np.float64), hot, out


def true_calibration(
    pixels: PixelArray,
    width: int,
    height: int,
    K: np.ndarray,
    distortion_model: str = "none",
    distortion: tuple[float, ...] | np.ndarray = (),
) -> Calibration:
    """The /calibration of a simulated sensor: its true intrinsics, thresholds, hot pixels
    and noise rates (what `evcap calibrate` measures of a real one)."""
    hot = np.zeros(width * height, bool)
    hot[pixels.hot] = True
    effects = pixels.effects
    return Calibration(
        width,
        height,
        "ground truth",
        K=K,
        distortion_model=distortion_model,  # type: ignore[arg-type]
        dist=np.asarray(distortion, np.float64),
        threshold_on=pixels.con.reshape(height, width),
        threshold_off=pixels.coff.reshape(height, width),
        hot_pixels=hot.reshape(height, width),
        refractory_period_us=float(effects.get("refractory", {}).get("period_us", 0)),
        background_activity_hz=float(effects.get("background_activity", {}).get("rate_hz", 0)),
        shot_noise_hz=float(effects.get("shot_noise", {}).get("rate_hz", 0)),
        rms_reprojection_px=0.0,
    )
