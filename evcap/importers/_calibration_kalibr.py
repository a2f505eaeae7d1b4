"""Kalibr's camchain YAML: one entry per camera (cam0, cam1, ...) with camera_model pinhole,
intrinsics [fu fv pu pv], distortion_model radtan | equidistant | none, distortion_coeffs,
resolution [w h], rostopic; kalibr_calibrate_imu_camera adds T_cam_imu (IMU-frame points into
the camera's) and timeshift_cam_imu (seconds: t_imu = t_cam + shift)."""

from __future__ import annotations

import re

import numpy as np
import yaml

from evcap.errors import InputError
from evcap.importers.camera_calibration import (
    CameraCalibration,
    intrinsic_matrix,
    number,
    numbers,
    pick_camera,
    pixels,
    rigid_transform,
)

FORMAT = "Kalibr camchain"
MODELS = ("radtan", "equidistant", "none")
KEYS = "camera_model, intrinsics, distortion_model, distortion_coeffs, resolution"
# the DAVIS346's frames under the ROS driver (rpg_dvs_ros); Kalibr's readers want a topic
ROSTOPIC = "/dvs/image_raw"


def camera_names(doc: dict) -> list[str]:
    """The cameras of a camchain, in Kalibr's order."""
    names = [k for k in doc if isinstance(k, str) and re.fullmatch(r"cam\d+", k)]
    return sorted(names, key=lambda k: int(k[3:]))


def imu_names(doc: dict) -> list[str]:
    """The IMUs of a Kalibr IMU file (imu0, ...): a file with no camera."""
    return [k for k in doc if isinstance(k, str) and re.fullmatch(r"imu\d+", k)]


def read(doc: dict, source: str, camera: str | None) -> CameraCalibration:
    names = camera_names(doc)
    name = pick_camera(names, camera, source, FORMAT)
    c = doc[name]
    place = f"{source}: {name}"
    if not isinstance(c, dict):
        raise InputError(f"{place} is not a camera's entry ({KEYS})")
    for key in ("intrinsics", "resolution"):
        if key not in c:
            raise InputError(f"{place} has no {key} (a camchain's camera has {KEYS})")
    camera_model = str(c.get("camera_model", "pinhole"))
    if camera_model != "pinhole":
        raise InputError(
            f"{place}: camera_model {camera_model!r}; evcap takes pinhole (Kalibr's omni, eucm "
            "and ds models have no counterpart)"
        )
    model = str(c.get("distortion_model", "none"))
    if model not in MODELS:
        raise InputError(
            f"{place}: distortion_model {model!r} is not one evcap takes ({', '.join(MODELS)})"
        )
    intrinsics = numbers(c["intrinsics"], "intrinsics", place)
    resolution = c["resolution"]
    if intrinsics.size != 4:
        raise InputError(f"{place}: intrinsics must be [fu, fv, pu, pv], got {c['intrinsics']}")
    if not isinstance(resolution, list | tuple) or len(resolution) != 2:
        raise InputError(f"{place}: resolution must be [width, height], got {resolution!r}")
    dist = numbers(c.get("distortion_coeffs", []), "distortion_coeffs", place)
    T = c.get("T_cam_imu")
    return CameraCalibration(
        width=pixels(resolution[0], "resolution's width", place),
        height=pixels(resolution[1], "resolution's height", place),
        K=intrinsic_matrix(*intrinsics),
        distortion_model=model,
        dist=np.zeros(0) if model == "none" else dist,
        T_cam_imu=None if T is None else rigid_transform(T, "T_cam_imu", place),
        timeshift_cam_imu_s=number(c.get("timeshift_cam_imu", 0.0), "timeshift_cam_imu", place),
        camera=name,
        cameras=tuple(names),
        source=source,
        format=FORMAT,
    )


def write(cal: CameraCalibration) -> str:
    """``cal`` as cam0 of a camchain (with T_cam_imu and timeshift_cam_imu when it has them)."""
    K, dist = cal.K, cal.dist
    if cal.distortion_model == "radtan" and len(dist) == 5:
        if dist[4] != 0:
            raise InputError(
                f"the calibration's k3 is {dist[4]:g}: Kalibr's radtan holds k1 k2 p1 p2 only; "
                "export it as ROS camera_info (--format ros) or DV's XML (.xml), which keep k3"
            )
        dist = dist[:4]
    cam: dict = {
        "camera_model": "pinhole",
        "intrinsics": [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])],
        "distortion_model": cal.distortion_model,
        "distortion_coeffs": [float(d) for d in dist],
        "resolution": [int(cal.width), int(cal.height)],
        "rostopic": ROSTOPIC,
        "cam_overlaps": [],
    }
    if cal.T_cam_imu is not None:
        cam["T_cam_imu"] = [[float(v) for v in row] for row in cal.T_cam_imu]
        cam["timeshift_cam_imu"] = float(cal.timeshift_cam_imu_s)
    return yaml.safe_dump({"cam0": cam}, default_flow_style=None)
