"""Containers for the sensor's other streams: APS frames, IMU samples and triggers.

Times are microseconds since the session's t = 0, like the events'. Each container checks its
shapes and dtypes and that its times are in order.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from evcap.errors import InputError
from evcap.events import first_unsorted

APS_MAX = 1023
"""Largest APS value: the DAVIS346's ADC gives 10 bits."""


class TriggerKind(IntEnum):
    """What a trigger marks (the numbering of DV's TriggerType)."""

    TIMESTAMP_RESET = 0
    EXTERNAL_SIGNAL_RISING_EDGE = 1
    EXTERNAL_SIGNAL_FALLING_EDGE = 2
    EXTERNAL_SIGNAL_PULSE = 3
    EXTERNAL_GENERATOR_RISING_EDGE = 4
    EXTERNAL_GENERATOR_FALLING_EDGE = 5
    APS_FRAME_START = 6
    APS_FRAME_END = 7
    APS_EXPOSURE_START = 8
    APS_EXPOSURE_END = 9


def _times(values: np.ndarray, what: str) -> np.ndarray:
    t = np.asarray(values)
    if t.ndim != 1 or (t.size and t.dtype.kind not in "iu"):
        raise InputError(f"{what}: t must be 1-D integers (microseconds), got {t.dtype} {t.shape}")
    t = np.ascontiguousarray(t, dtype=np.int64)
    bad = first_unsorted(t)
    if bad >= 0:
        raise InputError(f"{what}: timestamps are not in time order at sample {bad}")
    return t


def _rows(values: np.ndarray, n: int, width: int | None, dtype: type, what: str) -> np.ndarray:
    a = np.ascontiguousarray(values, dtype=dtype)
    shape = (n,) if width is None else (n, width)
    if a.shape != shape:
        raise InputError(f"{what}: expected shape {shape}, got {a.shape}")
    return a


@dataclass(frozen=True, eq=False)
class Frames:
    """APS frames as read from the sensor: raw 10-bit values, not demosaiced."""

    data: np.ndarray  # [N, height, width] uint16, 0..1023
    t: np.ndarray  # [N] int64, start of exposure
    exposure_us: np.ndarray  # [N] int64, exposure time

    def __post_init__(self) -> None:
        t = _times(self.t, "frames")
        data = np.asarray(self.data)
        if data.ndim != 3 or data.shape[0] != t.size:
            raise InputError(f"frames: data must be N x height x width, got {data.shape}")
        if data.dtype.kind not in "iu":
            raise InputError(f"frames: data must hold integers, got {data.dtype}")
        if data.size and (int(data.max()) > APS_MAX or int(data.min()) < 0):
            raise InputError(f"frames: values must be in 0..{APS_MAX} (10-bit)")
        exposure = _rows(self.exposure_us, t.size, None, np.int64, "frames.exposure_us")
        if exposure.size and int(exposure.min()) < 0:
            raise InputError("frames: exposure_us must not be negative")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "data", np.ascontiguousarray(data, dtype=np.uint16))
        object.__setattr__(self, "exposure_us", exposure)

    def __len__(self) -> int:
        return int(self.t.size)


# libcaer's IMU axes (what the DAVIS sends, after its orientation flips, and what DV and cAER
# store) into the camera's (x right, y down, z forward): x and z negated, as rpg_dvs_ros aligns
# them for Kalibr and VINS. On the bundled DV recording the accelerometer then says the camera is
# pitched 15 deg down, as its frames show it (the horizon 75 px above the centre); as libcaer
# gives it, 15 deg up.
LIBCAER_TO_CAMERA = np.array([-1.0, 1.0, -1.0])


@dataclass(frozen=True, eq=False)
class ImuSamples:
    """IMU samples in physical units, in the camera's axes."""

    t: np.ndarray  # [N] int64
    accel: np.ndarray  # [N, 3] float32, m/s^2
    gyro: np.ndarray  # [N, 3] float32, rad/s
    temperature: np.ndarray  # [N] float32, degrees Celsius

    def __post_init__(self) -> None:
        t = _times(self.t, "imu")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "accel", _rows(self.accel, t.size, 3, np.float32, "imu.accel"))
        object.__setattr__(self, "gyro", _rows(self.gyro, t.size, 3, np.float32, "imu.gyro"))
        temperature = _rows(self.temperature, t.size, None, np.float32, "imu.temperature")
        object.__setattr__(self, "temperature", temperature)

    def __len__(self) -> int:
        return int(self.t.size)


@dataclass(frozen=True, eq=False)
class Triggers:
    """External-input edges and the sensor's special signals."""

    t: np.ndarray  # [N] int64
    kind: np.ndarray  # [N] uint8, a TriggerKind

    def __post_init__(self) -> None:
        t = _times(self.t, "triggers")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "kind", _rows(self.kind, t.size, None, np.uint8, "triggers.kind"))

    def __len__(self) -> int:
        return int(self.t.size)
