"""ROS camera_info YAML as camera_calibration writes it (image_width, image_height,
camera_name, camera_matrix, distortion_model, distortion_coefficients, rectification_matrix,
projection_matrix), and OpenCV's own calibration YAML, which names its matrices the same."""

from __future__ import annotations

import numpy as np
import yaml

from evcap.errors import InputError
from evcap.importers.camera_calibration import (
    CameraCalibration,
    camera_matrix,
    numbers,
    pick_camera,
    pixels,
)

FORMAT = "ROS camera_info"
OPENCV_FORMAT = "OpenCV calibration YAML"
# ROS's distortion model names -> evcap's
MODELS = {
    "plumb_bob": "radtan",
    "radtan": "radtan",
    "equidistant": "equidistant",
    "fisheye": "equidistant",
}
KEYS = "image_width, image_height, camera_matrix, distortion_model, distortion_coefficients"


def read(doc: dict, source: str, camera: str | None) -> CameraCalibration:
    """The camera of a camera_info file (``camera``: its camera_name, cam0 or None)."""
    opencv = isinstance(doc["camera_matrix"], dict) and "dt" in doc["camera_matrix"]
    fmt = OPENCV_FORMAT if opencv else FORMAT
    name = str(doc.get("camera_name") or "cam0")
    pick_camera([name], camera, source, fmt)
    for key in ("image_width", "image_height"):
        if key not in doc:
            raise InputError(f"{source}: no {key} (a {fmt} file has {KEYS})")
    K, warnings = camera_matrix(doc["camera_matrix"], "camera_matrix", source)
    dist = np.zeros(0)
    if doc.get("distortion_coefficients") is not None:
        dist = numbers(doc["distortion_coefficients"], "distortion_coefficients", source)
    given = doc.get("distortion_model")
    if given is None and not opencv and dist.any():
        raise InputError(f"{source}: distortion_coefficients without a distortion_model")
    given = "plumb_bob" if given is None else str(given)
    if given not in MODELS:
        raise InputError(
            f"{source}: distortion_model {given!r} is not one evcap takes (plumb_bob, "
            "equidistant); rational_polynomial's k4..k6 and other models have no counterpart"
        )
    model = MODELS[given]
    if model == "radtan" and len(dist) > 5:
        if dist[5:].any():
            raise InputError(
                f"{source}: {len(dist)} distortion coefficients: the rational model's k4..k6 "
                "have no counterpart in evcap (plumb_bob takes k1 k2 p1 p2 k3)"
            )
        dist = dist[:5]  # OpenCV's 8 with the rational part zero
    if model == "radtan" and len(dist) == 0:
        model = "none"
    return CameraCalibration(
        width=pixels(doc["image_width"], "image_width", source),
        height=pixels(doc["image_height"], "image_height", source),
        K=K,
        distortion_model=model,
        dist=dist,
        camera=name,
        cameras=(name,),
        source=source,
        format=fmt,
        warnings=tuple(warnings),
    )


def write(cal: CameraCalibration, name: str) -> str:
    """The camera_info YAML of ``cal``: plumb_bob (k1 k2 p1 p2 k3) or equidistant, the
    rectification the identity and the projection the undistorted camera camera_calibration
    gives a monocular camera (OpenCV's optimal new camera matrix, alpha 0)."""
    import cv2

    K, dist = cal.K, cal.dist
    if cal.distortion_model == "equidistant":
        model, coeffs = "equidistant", dist
        P = cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(
            K, dist, (cal.width, cal.height), np.eye(3), balance=0.0
        )
    else:
        model, coeffs = "plumb_bob", np.concatenate([dist, np.zeros(5 - len(dist))])
        P, _ = cv2.getOptimalNewCameraMatrix(K, coeffs, (cal.width, cal.height), 0.0)
    projection = np.hstack([np.asarray(P, np.float64), np.zeros((3, 1))])

    def block(rows: int, cols: int, values: np.ndarray) -> dict:
        return {"rows": rows, "cols": cols, "data": [float(v) for v in np.ravel(values)]}

    doc = {
        "image_width": int(cal.width),
        "image_height": int(cal.height),
        "camera_name": name,
        "camera_matrix": block(3, 3, K),
        "distortion_model": model,
        "distortion_coefficients": block(1, len(coeffs), coeffs),
        "rectification_matrix": block(3, 3, np.eye(3)),
        "projection_matrix": block(3, 4, projection),
    }
    return yaml.safe_dump(doc, default_flow_style=None, sort_keys=False)
