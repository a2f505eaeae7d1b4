"""One camera's calibration as other tools' files hold it: intrinsics, distortion, and where
the file has them the camera-IMU transform and time shift; checked when made. The readers and
writers of each format (evcap.importers.calibration_files) meet here, and so do the helpers
that turn a file's values into numbers with errors that name the file and the key."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from evcap.errors import InputError
from evcap.rotations import ROTATION_TOLERANCE, rotation_error

# evcap's distortion models (evcap.records.calibration) and how many coefficients each takes
COEFFICIENTS: dict[str, tuple[int, ...]] = {"none": (0,), "radtan": (4, 5), "equidistant": (4,)}


@dataclass(frozen=True, eq=False)
class CameraCalibration:
    """One camera of a calibration file, checked."""

    width: int  # pixels of the images it was calibrated on
    height: int
    K: np.ndarray  # 3 x 3, pixels; pixel centres at integer coordinates (OpenCV, ROS, Kalibr)
    distortion_model: str  # "none", "radtan" (k1 k2 p1 p2 [k3]), "equidistant" (k1 k2 k3 k4)
    dist: np.ndarray  # the model's coefficients, in OpenCV's order
    T_cam_imu: np.ndarray | None = None  # 4 x 4: points in the IMU's frame into the camera's, m
    timeshift_cam_imu_s: float = 0.0  # t_imu = t_cam + this (Kalibr's sign); with T_cam_imu
    camera: str = ""  # its name in the file: cam0, a ROS camera_name, DV's DAVIS346_SERIAL
    cameras: tuple[str, ...] = ()  # every camera the file holds, in its order
    source: str = ""  # the file's name
    format: str = ""  # "Kalibr camchain", "ROS camera_info", "VINS", "DV calibration XML"
    warnings: tuple[str, ...] = ()  # what was odd in the file, and how it was read

    def __post_init__(self) -> None:
        where = self.source or "calibration"
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | np.integer) or value <= 0:
                raise InputError(f"{where}: the image {name} must be a positive number of pixels")
        K = np.asarray(self.K, np.float64)
        if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise InputError(
                f"{where}: the camera matrix must be 3 x 3 and finite with positive focal "
                f"lengths, got {K.tolist()}"
            )
        if self.distortion_model not in COEFFICIENTS:
            raise InputError(
                f"{where}: unknown distortion model {self.distortion_model!r} "
                f"(evcap takes {', '.join(COEFFICIENTS)})"
            )
        dist = np.asarray(self.dist, np.float64).ravel()
        if len(dist) not in COEFFICIENTS[self.distortion_model] or not np.isfinite(dist).all():
            counts = " or ".join(map(str, COEFFICIENTS[self.distortion_model]))
            raise InputError(
                f"{where}: {self.distortion_model} distortion takes {counts} finite "
                f"coefficients, got {dist.tolist()}"
            )
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)
        if self.T_cam_imu is not None:
            object.__setattr__(
                self, "T_cam_imu", rigid_transform(self.T_cam_imu, "T_cam_imu", where)
            )
        if not np.isfinite(self.timeshift_cam_imu_s):
            raise InputError(f"{where}: the camera-IMU time shift must be a finite number")

    @property
    def skew(self) -> float:
        return float(self.K[0, 1])

    def describe(self) -> str:
        """The file and the camera, for a person: `camchain.yaml (Kalibr camchain, cam0 of
        cam0, cam1)`."""
        camera = self.camera
        if len(self.cameras) > 1:
            camera = f"{camera} of {', '.join(self.cameras)}"
        inside = ", ".join(part for part in (self.format, camera) if part)
        return f"{self.source} ({inside})" if inside else self.source


def number(value: object, what: str, where: str) -> float:
    """``value`` as a finite float (numbers written as strings too: YAML 1.1 reads `1e-5` so)."""
    if isinstance(value, bool) or value is None:
        raise InputError(f"{where}: {what} must be a number, got {value!r}")
    try:
        x = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise InputError(f"{where}: {what} must be a number, got {value!r}") from None
    if not np.isfinite(x):
        raise InputError(f"{where}: {what} must be finite, got {value!r}")
    return x


def pixels(value: object, what: str, where: str) -> int:
    """``value`` as a positive whole number of pixels."""
    x = number(value, what, where)
    if x != int(x) or x <= 0:
        raise InputError(
            f"{where}: {what} must be a positive whole number of pixels, got {value!r}"
        )
    return int(x)


def numbers(value: object, what: str, where: str) -> np.ndarray:
    """A flat list of finite numbers, from a list (nested or not) or a {rows, cols, data}
    mapping (ROS's matrices, OpenCV's opencv-matrix)."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, Mapping):
        if "data" not in value:
            raise InputError(f"{where}: {what} has no data (a matrix is rows, cols, data)")
        data = value["data"]
        flat = numbers(data, what, where)
        if "rows" in value and "cols" in value:
            rows, cols = (
                pixels(value["rows"], f"{what}'s rows", where),
                pixels(value["cols"], f"{what}'s cols", where),
            )
            if rows * cols != len(flat):
                raise InputError(
                    f"{where}: {what} says {rows} x {cols} but holds {len(flat)} numbers"
                )
        return flat
    if isinstance(value, list | tuple):
        out: list[float] = []
        for item in value:
            if isinstance(item, list | tuple):
                out += numbers(item, what, where).tolist()
            else:
                out.append(number(item, f"{what}'s entries", where))
        return np.array(out, np.float64)
    raise InputError(f"{where}: {what} must be a list of numbers, got {value!r}")


def matrix(value: object, shape: tuple[int, int], what: str, where: str) -> np.ndarray:
    """``value`` (see ``numbers``) as a ``shape`` matrix, row by row."""
    flat = numbers(value, what, where)
    if flat.size != shape[0] * shape[1]:
        raise InputError(
            f"{where}: {what} must be {shape[0]} x {shape[1]}, got {flat.size} numbers"
        )
    return flat.reshape(shape)


def camera_matrix(value: object, what: str, where: str) -> tuple[np.ndarray, list[str]]:
    """A 3 x 3 camera matrix and what was odd in it: a last row other than [0 0 1] (a file
    seen in the wild holds a rotation's) is read as [0 0 1], said so."""
    K = matrix(value, (3, 3), what, where)
    warnings = []
    if not np.allclose(K[2], [0, 0, 1], atol=1e-9, rtol=0):
        warnings.append(
            f"{what}'s last row is {K[2].tolist()} where a camera matrix has [0, 0, 1]: read "
            "fx, fy, cx, cy (and the skew) from its first two rows"
        )
        K[2] = [0, 0, 1]
    if K[1, 0] != 0:
        raise InputError(f"{where}: {what} is not a camera matrix (its [1][0] is {K[1, 0]}, not 0)")
    return K, warnings


def intrinsic_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def rigid_transform(value: object, what: str, where: str) -> np.ndarray:
    """A 4 x 4 rigid transform (a rotation and a translation), checked."""
    T = matrix(value, (4, 4), what, where)
    if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-9, rtol=0):
        raise InputError(f"{where}: {what}'s last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    check_rotation(T[:3, :3], what, where)
    return T


def check_rotation(R: np.ndarray, what: str, where: str) -> None:
    off = rotation_error(R)
    if off > ROTATION_TOLERANCE:
        raise InputError(
            f"{where}: {what}'s rotation is not a rotation (R^T R differs from the identity by "
            f"{off:.2g}, or it mirrors)"
        )


def transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, np.ravel(t)
    return T


def inverse(T: np.ndarray) -> np.ndarray:
    """The inverse of a transform (a general inverse: rotations printed to a few digits are
    not quite orthonormal, and written back they should read as they were)."""
    return np.linalg.inv(T)


def pick_camera(names: list[str], camera: str | None, where: str, what: str) -> str:
    """The camera asked for (default: the first, cam0), or an error naming the ones there."""
    if not names:
        raise InputError(f"{where}: a {what} with no camera in it")
    if camera is None:
        return names[0]
    if camera in names:
        return camera
    index = camera.removeprefix("cam")
    if camera.startswith("cam") and index.isdigit() and int(index) < len(names):
        return names[int(index)]  # cam1: the second camera of a file that names them otherwise
    held = ", ".join(names)
    raise InputError(
        f"{where} has no camera {camera!r}: it holds {len(names)} "
        f"({held}); give --camera one of them"
    )
