"""What the sensor makes of radiance: the log signal of each pixel's color channel, APS frames
(exposure, shot and read noise, 10 bits) and IMU samples (from the camera's path)."""

from __future__ import annotations

import numpy as np

from evcap.events import pixel_channels
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
