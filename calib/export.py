"""`evcap calibrate --export`: a session's calibration written as another tool's file (a Kalibr
camchain, ROS camera_info or VINS YAML, or DV's calibration XML), for the tools a DAVIS346's
owner runs beside evcap."""

from __future__ import annotations

from pathlib import Path

from evcap.errors import OutputExistsError
from evcap.importers.calibration_files import (
    CameraCalibration,
    export_format,
    read_calibration_file,
    render_calibration,
    write_calibration_file,
)
from evcap.records import Calibration
from evcap.session import SensorInfo, Session


def check_export(
    path: str | Path,
    fmt: str | None,
    overwrite: bool,
    intrinsics: str | Path | None = None,
    camera: str | None = None,
) -> str:
    """The format ``path`` will be written in; InputError before any work when it cannot be
    (with ``intrinsics``, the file to be imported first: when the format cannot hold it)."""
    chosen = export_format(path, fmt)
    if Path(path).exists() and not overwrite:
        raise OutputExistsError(f"{path} exists: give --force to replace it")
    if intrinsics is not None:
        render_calibration(read_calibration_file(intrinsics, camera), chosen, "camera")
    return chosen


def export_calibration(
    session: str | Path, path: str | Path, fmt: str | None = None, *, overwrite: bool = False
) -> tuple[str, list[str]]:
    """Write the intrinsics (and the camera-IMU transform and time shift, where the format
    holds them) of ``session``'s /calibration to ``path``. Returns the format and what the
    format has no place for."""
    check_export(path, fmt, overwrite)
    with Session.open(session) as s:
        cal = Calibration.read(s)
        sensor = s.sensor
    K, model, dist = cal.intrinsics(str(session))
    camera = CameraCalibration(
        width=cal.width,
        height=cal.height,
        K=K,
        distortion_model=model,
        dist=dist,
        T_cam_imu=cal.T_cam_imu,
        timeshift_cam_imu_s=cal.timeshift_cam_imu_us / 1e6,
        source=Path(session).name,
    )
    return write_calibration_file(camera, path, fmt, name=camera_name(sensor), overwrite=overwrite)


def camera_name(sensor: SensorInfo) -> str:
    """The camera's name in the files that hold one: MODEL_SERIAL, as DV names it."""
    return f"{sensor.sensor}_{sensor.serial}" if sensor.serial else sensor.sensor
