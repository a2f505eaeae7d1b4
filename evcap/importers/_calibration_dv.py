"""iniVation DV's camera calibration file: OpenCV FileStorage XML with one element per camera
(named MODEL_SERIAL, e.g. DAVIS346_00000499) holding camera_matrix and distortion_coefficients
(opencv-matrix), image_width and image_height, beside type (camera) and use_fisheye_model
(1: the equidistant model). Both are looked for in the camera's element and at the top, as
DV's versions place them; a plain OpenCV calibration (camera_matrix at the top) reads too.
Read and written with OpenCV's own cv2.FileStorage."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from evcap.errors import InputError
from evcap.importers.camera_calibration import (
    CameraCalibration,
    camera_matrix,
    numbers,
    pick_camera,
    pixels,
)

FORMAT = "DV calibration XML"
KEYS = "camera_matrix, distortion_coefficients, image_width, image_height"


def read(path: Path, source: str, camera: str | None) -> CameraCalibration:
    import cv2

    if b"<opencv_storage>" not in path.read_bytes()[:4096]:  # before OpenCV's own messages
        raise InputError(
            f"{source} is not DV's calibration XML (an <opencv_storage> document, as OpenCV "
            "writes it, with an element per camera)"
        )
    try:
        return _read(path, source, camera)
    except (cv2.error, SystemError) as e:  # OpenCV's errors come wrapped in SystemError too
        cause = e.__cause__ or e.__context__ or e
        raise InputError(
            f"{source}: its elements are not as DV writes them (OpenCV: {_reason(cause)})"
        ) from None


def _read(path: Path, source: str, camera: str | None) -> CameraCalibration:
    import cv2

    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_FORMAT_XML)
    except (cv2.error, SystemError) as e:  # OpenCV's parse errors come wrapped in SystemError
        cause = e.__cause__ or e.__context__ or e
        raise InputError(
            f"{source} is not an XML calibration OpenCV reads: {_reason(cause)}"
        ) from None
    try:
        if not fs.isOpened():
            raise InputError(f"{source} could not be opened as OpenCV FileStorage XML")
        root = fs.root()
        keys = list(root.keys())
        names = [
            k for k in keys if root.getNode(k).isMap() and _has(root.getNode(k), "camera_matrix")
        ]
        top = _has(root, "camera_matrix")
        if not names and not top:
            raise InputError(
                f"{source}: no camera in it (DV's calibration holds an element per camera with "
                f"{KEYS}); its elements: {', '.join(keys) or 'none'}"
            )
        if names:
            name = pick_camera(names, camera, source, FORMAT)
            node = root.getNode(name)
        else:
            name = "cam0"
            pick_camera([name], camera, source, FORMAT)
            node, names = root, [name]
        kind = _text(node, "type") or _text(root, "type")
        if kind not in ("", "camera", "stereo"):
            raise InputError(f"{source}: type {kind!r}, not a camera calibration")
        fisheye = _integer(node, "use_fisheye_model")
        if fisheye is None:
            fisheye = _integer(root, "use_fisheye_model") or 0
        K, warnings = camera_matrix(_matrix(node, "camera_matrix", source), "camera_matrix", source)
        dist = np.zeros(0)
        if _has(node, "distortion_coefficients"):
            dist = numbers(
                _matrix(node, "distortion_coefficients", source).ravel().tolist(),
                "distortion_coefficients",
                source,
            )
        width, height = (
            _integer(node, key) or _integer(root, key) for key in ("image_width", "image_height")
        )
    finally:
        fs.release()
    if width is None or height is None:
        raise InputError(f"{source}: {name} has no image_width or image_height ({KEYS})")
    model = "equidistant" if fisheye else "radtan"
    if model == "radtan" and len(dist) > 5:
        if dist[5:].any():
            raise InputError(
                f"{source}: {len(dist)} distortion coefficients: OpenCV's rational and thin-prism "
                "terms have no counterpart in evcap (k1 k2 p1 p2 k3)"
            )
        dist = dist[:5]
    if model == "radtan" and len(dist) == 0:
        model = "none"
    return CameraCalibration(
        width=pixels(width, "image_width", source),
        height=pixels(height, "image_height", source),
        K=K,
        distortion_model=model,
        dist=dist,
        camera=name,
        cameras=tuple(names),
        source=source,
        format=FORMAT,
        warnings=tuple(warnings),
    )


def write(cal: CameraCalibration, name: str) -> str:
    """``cal`` as DV's calibration XML, the camera's element named ``name`` (made a valid XML
    name: MODEL_SERIAL)."""
    import cv2

    element = re.sub(r"[^A-Za-z0-9_]", "_", name) or "camera"
    if not re.match(r"[A-Za-z_]", element):
        element = f"camera_{element}"
    flags = cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY | cv2.FILE_STORAGE_FORMAT_XML
    fs = cv2.FileStorage(".xml", flags)
    fs.startWriteStruct(element, cv2.FileNode_MAP)
    fs.write("camera_matrix", np.asarray(cal.K, np.float64))
    coefficients = cal.dist if cal.distortion_model != "none" else np.zeros(5)
    fs.write("distortion_coefficients", np.asarray(coefficients, np.float64).reshape(-1, 1))
    fs.write("image_width", int(cal.width))
    fs.write("image_height", int(cal.height))
    fs.endWriteStruct()
    fs.write("type", "camera")
    fs.write("use_fisheye_model", int(cal.distortion_model == "equidistant"))
    return fs.releaseAndGetString()


def _has(node, key: str) -> bool:
    return not node.getNode(key).empty()


def _matrix(node, key: str, source: str) -> np.ndarray:
    import cv2

    try:
        m = node.getNode(key).mat()
    except (cv2.error, SystemError):
        raise InputError(
            f"{source}: {key} is not a valid opencv-matrix (its rows x cols must match its data)"
        ) from None
    if m is None:
        raise InputError(f"{source}: {key} is not an opencv-matrix (rows, cols, dt, data)")
    return np.asarray(m, np.float64)


def _text(node, key: str) -> str:
    n = node.getNode(key)
    return n.string() if not n.empty() and n.isString() else ""


def _integer(node, key: str) -> float | None:
    n = node.getNode(key)
    return None if n.empty() or not (n.isInt() or n.isReal()) else n.real()


def _reason(e: Exception) -> str:
    """OpenCV's message without its version, source file and line."""
    text = _first_line(e)
    return re.sub(r"^OpenCV\([^)]*\) \S+: error: \([^)]*\) ", "", text)


def _first_line(e: Exception) -> str:
    lines = [line for line in str(e).splitlines() if line.strip()]
    return lines[-1] if lines else type(e).__name__
