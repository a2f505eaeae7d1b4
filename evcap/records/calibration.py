"""/calibration: what is known of the sensor (docs/session-format.md). ``Calibration`` is the
one reader and writer of the group: `evcap calibrate` and the simulator write it, the poses,
the reconstruction, the simulator (a measured sensor) and the report read it."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Literal, get_args

import numpy as np

from evcap.errors import InputError
from evcap.hdf5_attributes import read_attributes
from evcap.records._group import Source, array, find_group, optional, path_of, where
from evcap.rotations import ROTATION_TOLERANCE, log_so3, rotation_error
from evcap.session import write_group

GROUP = "calibration"
DistortionModel = Literal["none", "radtan", "equidistant"]
DISTORTION_MODELS: tuple[str, ...] = get_args(DistortionModel)


@dataclass
class BoardViews:
    """The board views the intrinsics were fitted on."""

    t_us: np.ndarray  # [V] int64
    rms_px: np.ndarray  # [V] reprojection error of each
    corners: np.ndarray  # [V] corners found in each


@dataclass
class Calibration:
    """The sensor's calibration. Every part but the size may be unknown (None): a session
    calibrated from a recording without a board has thresholds and no intrinsics."""

    width: int
    height: int
    source: str  # "evcap calibrate", "ground truth"
    K: np.ndarray | None = None  # 3 x 3, pixels; pixel centres at integer coordinates
    distortion_model: DistortionModel = "none"
    dist: np.ndarray = field(default_factory=lambda: np.zeros(0))  # OpenCV's order
    threshold_on: np.ndarray | None = None  # [H, W] log units
    threshold_off: np.ndarray | None = None
    threshold_confidence: np.ndarray | None = None  # [H, W] 0..1 (>= 0.5: fitted)
    hot_pixels: np.ndarray | None = None  # [H, W] bool
    event_rate_hz: np.ndarray | None = None  # [H, W] each pixel's rate over the recording
    views: BoardViews | None = None
    rms_reprojection_px: float = float("nan")
    refractory_period_us: float = 0.0
    background_activity_hz: float = 0.0  # leak events per pixel per second
    shot_noise_hz: float = 0.0  # random ON and OFF events per pixel per second
    # the IMU's frame into the camera's (4 x 4, metres; Kalibr's T_cam_imu) when known, and the
    # IMU's clock against the camera's: t_imu = t_cam + timeshift_cam_imu_us (Kalibr's sign)
    T_cam_imu: np.ndarray | None = None
    timeshift_cam_imu_us: float = 0.0
    notes: dict = field(default_factory=dict)  # more attributes: how each part was measured

    def __post_init__(self) -> None:
        if self.distortion_model not in DISTORTION_MODELS:
            raise InputError(f"calibration: unknown distortion model {self.distortion_model!r}")
        self.dist = np.asarray(self.dist, np.float64).ravel()
        for name in ("threshold_on", "threshold_off", "threshold_confidence", "event_rate_hz"):
            value = getattr(self, name)
            if value is not None:
                setattr(self, name, self._map(name, value, np.float32))
        if self.hot_pixels is not None:
            self.hot_pixels = self._map("hot_pixels", self.hot_pixels, bool)
        if self.T_cam_imu is not None:
            self.T_cam_imu = _rigid(
                np.asarray(self.T_cam_imu, np.float64), "calibration: T_cam_imu"
            )
        if not np.isfinite(self.timeshift_cam_imu_us):
            raise InputError("calibration: timeshift_cam_imu_us must be a finite number")

    def _map(self, name: str, value: np.ndarray, dtype) -> np.ndarray:
        m = np.asarray(value, dtype)
        if m.shape != (self.height, self.width):
            raise InputError(
                f"calibration: {name} is {' x '.join(map(str, m.shape[::-1]))} pixels, the "
                f"sensor {self.width} x {self.height}"
            )
        return m

    # -- reading -----------------------------------------------------------------------------

    @staticmethod
    def present(source: Source) -> bool:
        return find_group(source, GROUP) is not None

    @classmethod
    def read(cls, source: Source) -> Calibration:
        """The calibration of ``source``, checked; InputError naming what to run when it has
        none or when it is damaged."""
        g = find_group(source, GROUP)
        place = where(source, GROUP)
        if g is None:
            raise InputError(
                f"{path_of(source)} has no calibration (/{GROUP}): run "
                "`evcap calibrate` on it (a ChArUco board filmed in it, or `--intrinsics FILE`: "
                "the Kalibr, ROS, VINS or DV calibration you have of the camera), or `evcap "
                "calibrate --apply-to` from a calibration recording of the same camera"
            )
        a = read_attributes(g)
        sensor = getattr(source, "sensor", None)
        width = int(a.get("width", sensor.width if sensor else 0))
        height = int(a.get("height", sensor.height if sensor else 0))
        if sensor is not None and (width, height) != (sensor.width, sensor.height):
            raise InputError(
                f"{place}: the calibration is for {width} x {height}, the sensor is "
                f"{sensor.width} x {sensor.height}"
            )
        K = optional(g, "K", place)
        if K is not None and (K.shape != (3, 3) or K[0, 0] <= 0 or K[1, 1] <= 0):
            raise InputError(
                f"{place}/K is not an intrinsic matrix (3 x 3, positive focal lengths): shape "
                f"{list(K.shape)}; run `evcap calibrate` again"
            )
        # sessions written before the name `dist` hold `distortion`
        name = "dist" if "dist" in g or "distortion" not in g else "distortion"
        dist = optional(g, name, place)
        if dist is not None and dist.ndim != 1:
            raise InputError(f"{place}/{name} is not a list of coefficients")
        maps = {
            key: optional(g, key, place, dtype, (height, width))
            for key, dtype in (
                ("threshold_on", np.float32),
                ("threshold_off", np.float32),
                ("threshold_confidence", np.float32),
                ("hot_pixels", np.uint8),
                ("event_rate_hz", np.float32),
            )
        }
        for key in ("threshold_on", "threshold_off"):
            if maps[key] is not None and (maps[key] <= 0).any():
                raise InputError(f"{place}/{key}: the thresholds must be positive numbers")
        views = None
        if all(k in g for k in ("view_t", "view_rms_px", "view_corners")):
            views = BoardViews(
                array(g, "view_t", place, np.int64, (None,)),
                array(g, "view_rms_px", place, np.float64, (None,)),
                array(g, "view_corners", place, np.int64, (None,)),
            )
        T_cam_imu = optional(g, "T_cam_imu", place, np.float64, (4, 4))
        if T_cam_imu is not None:
            _rigid(T_cam_imu, f"{place}/T_cam_imu")
        model = str(a.pop("distortion_model", "none"))
        if model not in DISTORTION_MODELS:
            raise InputError(f"{place}: unknown distortion model {model!r}")
        # older simulated sessions name the reprojection error reprojection_error_px
        rms = a.pop("rms_reprojection_px", a.pop("reprojection_error_px", float("nan")))
        typed = (
            "refractory_period_us",
            "background_activity_hz",
            "shot_noise_hz",
            "timeshift_cam_imu_us",
        )
        numbers = {k: float(a.pop(k)) for k in typed if k in a}
        for k in ("width", "height"):
            a.pop(k, None)
        return cls(
            width=width,
            height=height,
            source=str(a.pop("source", "unknown")),
            K=K,
            distortion_model=model,  # type: ignore[arg-type]
            dist=np.zeros(0) if dist is None else dist,
            views=views,
            T_cam_imu=T_cam_imu,
            rms_reprojection_px=float(rms),
            notes=a,
            **{k: v for k, v in maps.items() if v is not None},
            **numbers,
        )

    def intrinsics(self, place: str = "the calibration") -> tuple[np.ndarray, str, np.ndarray]:
        """(K, distortion model, coefficients); InputError when the intrinsics are unknown."""
        if self.K is None:
            raise InputError(
                f"{place} has no intrinsics (/{GROUP}/K): run `evcap calibrate` on it (a "
                "board filmed in it, or `--intrinsics FILE`), or `evcap calibrate --apply-to` "
                "from a calibration recording of the same camera"
            )
        return self.K, self.distortion_model, self.dist

    def thresholds(self, place: str = "the calibration") -> tuple[np.ndarray, np.ndarray]:
        """The per-pixel (ON, OFF) thresholds; InputError when they are unknown."""
        if self.threshold_on is None or self.threshold_off is None:
            raise InputError(
                f"{place}: /{GROUP} has no per-pixel thresholds; run `evcap calibrate` on it"
            )
        return self.threshold_on, self.threshold_off

    def hot(self) -> np.ndarray:
        """[H, W] bool: the hot pixels (none when not measured)."""
        if self.hot_pixels is None:
            return np.zeros((self.height, self.width), bool)
        return self.hot_pixels

    # -- writing -----------------------------------------------------------------------------

    def write(self, path: str | os.PathLike, *, replace: bool = True) -> None:
        """Store as the /calibration of the (closed) session at ``path``."""
        data: dict[str, np.ndarray] = {}
        if self.K is not None:
            data["K"] = np.asarray(self.K, np.float64)
            data["dist"] = self.dist
        for name in ("threshold_on", "threshold_off", "threshold_confidence", "event_rate_hz"):
            value = getattr(self, name)
            if value is not None:
                data[name] = value.astype(np.float32)
        if self.hot_pixels is not None:
            data["hot_pixels"] = self.hot_pixels.astype(np.uint8)
        if self.T_cam_imu is not None:
            data["T_cam_imu"] = np.asarray(self.T_cam_imu, np.float64)
        if self.views is not None:
            data["view_t"] = np.asarray(self.views.t_us, np.int64)
            data["view_rms_px"] = np.asarray(self.views.rms_px, np.float64)
            data["view_corners"] = np.asarray(self.views.corners, np.int64)
        attrs = {
            **self.notes,
            "source": self.source,
            "distortion_model": self.distortion_model,
            "width": self.width,
            "height": self.height,
            "rms_reprojection_px": self.rms_reprojection_px,
            "refractory_period_us": self.refractory_period_us,
            "background_activity_hz": self.background_activity_hz,
            "shot_noise_hz": self.shot_noise_hz,
        }
        if self.hot_pixels is not None:
            attrs["hot_pixel_count"] = int(self.hot_pixels.sum())
        if self.T_cam_imu is not None:
            attrs["timeshift_cam_imu_us"] = float(self.timeshift_cam_imu_us)
        write_group(path, GROUP, data, attrs, replace=replace)


def read_intrinsics(source: Source) -> tuple[np.ndarray, str, np.ndarray]:
    """(K, distortion model, coefficients) of the source's /calibration, checked."""
    return Calibration.read(source).intrinsics(path_of(source))


def describe_camera_imu(T_cam_imu: np.ndarray, timeshift_us: float) -> str:
    """A camera-IMU transform and time shift for a person: how far the axes turn, how far
    apart the two are, how the clocks differ."""
    angle = float(np.degrees(np.linalg.norm(log_so3(T_cam_imu[:3, :3]))))
    t = ", ".join(f"{v:+.4f}" for v in T_cam_imu[:3, 3])
    sign = "+" if timeshift_us >= 0 else "-"
    return (
        f"the IMU's axes {angle:.2f} deg from the camera's, ({t}) m apart; "
        f"t_imu = t_cam {sign} {abs(timeshift_us) / 1e3:.3f} ms"
    )


def _rigid(T: np.ndarray, place: str) -> np.ndarray:
    """``T`` checked a rigid transform (4 x 4: a rotation, a translation, last row 0 0 0 1)."""
    if (
        T.shape != (4, 4)
        or not np.isfinite(T).all()
        or not np.array_equal(T[3], [0, 0, 0, 1])
        or rotation_error(T[:3, :3]) > ROTATION_TOLERANCE
    ):
        raise InputError(f"{place} is not a rigid transform (4 x 4: a rotation, a translation)")
    return T
