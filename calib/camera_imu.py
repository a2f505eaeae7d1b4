"""The camera-IMU transform and time shift a calibration carries: from the file `evcap
calibrate --intrinsics` reads (Kalibr's T_cam_imu and timeshift_cam_imu, VINS's extrinsics and
td), else kept from the session's /calibration, for `evcap poses`' gyroscope step."""

from __future__ import annotations

from evcap.importers.calibration_files import CameraCalibration
from evcap.records import Calibration


def camera_imu(file: CameraCalibration | None, stored: Calibration | None) -> dict:
    """CalibrationRun's T_cam_imu, timeshift_cam_imu_us and camera_imu_source: the file's when
    it has them, else those the session held (the same camera and IMU, still from the file
    they came from), else none."""
    if file is not None and file.T_cam_imu is not None:
        return {
            "T_cam_imu": file.T_cam_imu,
            "timeshift_cam_imu_us": file.timeshift_cam_imu_s * 1e6,
            "camera_imu_source": file.describe(),
        }
    if stored is not None and stored.T_cam_imu is not None:
        return {
            "T_cam_imu": stored.T_cam_imu,
            "timeshift_cam_imu_us": stored.timeshift_cam_imu_us,
            "camera_imu_source": str(stored.notes.get("camera_imu_source", stored.source)),
        }
    return {}
