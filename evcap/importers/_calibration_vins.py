"""VINS-Mono and VINS-Fusion YAML (OpenCV FileStorage's YAML, `%YAML:1.0`): the camera as
camodocal writes it (model_type PINHOLE: distortion_parameters k1 k2 p1 p2, projection_parameters
fx fy cx cy; KANNALA_BRANDT: projection_parameters k2 k3 k4 k5 mu mv u0 v0, the equidistant
model), and the camera-IMU transform as the IMU's pose of the camera: VINS-Mono's
extrinsicRotation and extrinsicTranslation, VINS-Fusion's body_T_cam0 (4 x 4), with td, the
time offset in seconds (t_imu = t_cam + td, Kalibr's sign). A VINS-Fusion configuration names
its cameras' files (cam0_calib); evcap.importers.calibration_files follows it."""

from __future__ import annotations

import numpy as np

from evcap.errors import InputError
from evcap.importers.camera_calibration import (
    CameraCalibration,
    intrinsic_matrix,
    inverse,
    matrix,
    number,
    pick_camera,
    pixels,
    rigid_transform,
    transform,
)

FORMAT = "VINS"
PINHOLE_KEYS = "model_type, image_width, image_height, distortion_parameters, projection_parameters"
NO_PRIOR = 2  # VINS-Mono's estimate_extrinsic: 2 = the extrinsics given are not known


def is_camera(doc: dict) -> bool:
    return "projection_parameters" in doc or "model_type" in doc


def calibration_files(doc: dict) -> list[str]:
    """The keys of a VINS-Fusion configuration that name its cameras' files (cam0_calib, ...)."""
    names = [k for k in doc if isinstance(k, str) and k.startswith("cam") and k.endswith("_calib")]
    return sorted(names, key=lambda k: (len(k), k))


def read(
    doc: dict, source: str, camera: str | None, extrinsics_doc: dict | None = None, index: int = 0
) -> CameraCalibration:
    """The camera of a camodocal file ``doc``; the camera-IMU transform from ``extrinsics_doc``
    (a VINS-Fusion configuration, camera ``index``) or from ``doc`` itself (VINS-Mono)."""
    name = str(doc.get("camera_name") or "cam0")
    if extrinsics_doc is None:
        pick_camera([name], camera, source, f"{FORMAT} file")
    kind = str(doc.get("model_type", "PINHOLE")).upper()
    for key in ("image_width", "image_height", "projection_parameters"):
        if key not in doc:
            raise InputError(f"{source}: no {key} (a VINS camera file has {PINHOLE_KEYS})")
    p = _section(doc, "projection_parameters", source)
    if kind == "PINHOLE":
        q = _section(doc, "distortion_parameters", source) if "distortion_parameters" in doc else {}
        fx, fy, cx, cy = (
            _value(p, k, "projection_parameters", source) for k in ("fx", "fy", "cx", "cy")
        )
        dist = [
            number(q.get(k, 0.0), f"distortion_parameters {k}", source)
            for k in ("k1", "k2", "p1", "p2")
        ]
        model = "radtan"
    elif kind == "KANNALA_BRANDT":
        fx, fy, cx, cy = (
            _value(p, k, "projection_parameters", source) for k in ("mu", "mv", "u0", "v0")
        )
        dist = [_value(p, k, "projection_parameters", source) for k in ("k2", "k3", "k4", "k5")]
        model = "equidistant"
    else:
        raise InputError(
            f"{source}: model_type {kind}; evcap takes PINHOLE (radtan) and KANNALA_BRANDT "
            "(equidistant): MEI's and SCARAMUZZA's omnidirectional models have no counterpart"
        )
    T, shift, warnings = extrinsics(
        doc if extrinsics_doc is None else extrinsics_doc, source, index
    )
    return CameraCalibration(
        width=pixels(doc["image_width"], "image_width", source),
        height=pixels(doc["image_height"], "image_height", source),
        K=intrinsic_matrix(fx, fy, cx, cy),
        distortion_model=model,
        dist=np.array(dist),
        T_cam_imu=T,
        timeshift_cam_imu_s=shift,
        camera=name,
        cameras=(name,),
        source=source,
        format=FORMAT,
        warnings=tuple(warnings),
    )


def extrinsics(
    doc: dict, source: str, index: int = 0
) -> tuple[np.ndarray | None, float, list[str]]:
    """(T_cam_imu or None, the time shift in seconds, warnings) of a VINS file."""
    key = f"body_T_cam{index}"
    T_imu_cam = None
    if key in doc:
        T_imu_cam = rigid_transform(doc[key], key, source)
    elif "extrinsicRotation" in doc or "extrinsicTranslation" in doc:
        for part in ("extrinsicRotation", "extrinsicTranslation"):
            if part not in doc:
                raise InputError(
                    f"{source}: extrinsicRotation and extrinsicTranslation go together"
                )
        R = matrix(doc["extrinsicRotation"], (3, 3), "extrinsicRotation", source)
        t = matrix(doc["extrinsicTranslation"], (3, 1), "extrinsicTranslation", source)
        T_imu_cam = rigid_transform(transform(R, t), "extrinsicRotation", source)
    if T_imu_cam is None:
        return None, 0.0, []
    if doc.get("estimate_extrinsic") == NO_PRIOR:
        return None, 0.0, ["estimate_extrinsic is 2 (the camera-IMU transform not known): left out"]
    return inverse(T_imu_cam), number(doc.get("td", 0.0), "td", source), []


def write(cal: CameraCalibration, name: str) -> str:
    """``cal`` as a VINS-Mono configuration's camera part (PINHOLE or KANNALA_BRANDT), with the
    camera-IMU transform both as VINS-Mono's extrinsicRotation/Translation and VINS-Fusion's
    body_T_cam0, and td, when it has one."""
    K, dist = cal.K, cal.dist
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    lines = ["%YAML:1.0", "", f"camera_name: {name}", f"image_width: {int(cal.width)}"]
    lines.append(f"image_height: {int(cal.height)}")
    if cal.distortion_model == "equidistant":
        lines.insert(2, "model_type: KANNALA_BRANDT")
        projection = dict(zip(("k2", "k3", "k4", "k5"), dist, strict=True))
        projection.update(mu=fx, mv=fy, u0=cx, v0=cy)
        lines += ["projection_parameters:", *_fields(projection)]
    else:
        if len(dist) == 5 and dist[4] != 0:
            raise InputError(
                f"the calibration's k3 is {dist[4]:g}: VINS's PINHOLE model holds k1 k2 p1 p2 "
                "only; export it as ROS camera_info (--format ros) or DV's XML (.xml)"
            )
        k = np.concatenate([dist, np.zeros(4)])[:4]
        lines.insert(2, "model_type: PINHOLE")
        lines += [
            "distortion_parameters:",
            *_fields(dict(zip(("k1", "k2", "p1", "p2"), k, strict=True))),
        ]
        lines += ["projection_parameters:", *_fields({"fx": fx, "fy": fy, "cx": cx, "cy": cy})]
    if cal.T_cam_imu is not None:
        T = inverse(cal.T_cam_imu)
        lines += [
            "",
            "# the camera's pose in the IMU's frame (imu_T_cam), fixed",
            "estimate_extrinsic: 0",
            *_opencv_matrix("extrinsicRotation", T[:3, :3]),
            *_opencv_matrix("extrinsicTranslation", T[:3, 3:]),
            *_opencv_matrix("body_T_cam0", T),
            "# t_imu = t_cam + td (seconds), fixed",
            "estimate_td: 0",
            f"td: {_real(cal.timeshift_cam_imu_s)}",
        ]
    return "\n".join(lines) + "\n"


def _section(doc: dict, key: str, source: str) -> dict:
    value = doc[key]
    if not isinstance(value, dict):
        raise InputError(f"{source}: {key} must be a mapping of named values, got {value!r}")
    return value


def _value(section: dict, key: str, name: str, source: str) -> float:
    if key not in section:
        raise InputError(f"{source}: {name} has no {key}")
    return number(section[key], f"{name} {key}", source)


def _real(x: float) -> str:
    """A float as YAML 1.1 and OpenCV both read it back exactly (a dot in the mantissa)."""
    text = repr(float(x))
    return text.replace("e", ".0e") if "e" in text and "." not in text else text


def _fields(values: dict) -> list[str]:
    return [f"   {k}: {_real(v)}" for k, v in values.items()]


def _opencv_matrix(key: str, m: np.ndarray) -> list[str]:
    data = ", ".join(_real(v) for v in np.ravel(m))
    rows, cols = m.shape
    return [
        f"{key}: !!opencv-matrix",
        f"   rows: {rows}",
        f"   cols: {cols}",
        "   dt: d",
        f"   data: [{data}]",
    ]
