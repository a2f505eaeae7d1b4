"""The simulated camera: intrinsics with lens distortion, rays through pixels, projection.

Axes are OpenCV's: x right, y down, z forward. Distortion models: "radtan" (plumb_bob:
k1, k2, p1, p2[, k3]) and "equidistant" (fisheye: k1..k4), as real DAVIS346 calibrations
give them (ROS camera_info, Kalibr, VINS and DV files).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from evcap.errors import InputError
from evcap.importers.calibration_files import read_calibration_file
from evcap.sim.scene import CameraSpec


def load_calibration(path: str | Path, camera: str | None = None) -> CameraSpec:
    """Intrinsics and distortion from another tool's calibration file (ROS camera_info, Kalibr
    camchain, VINS, DV's XML: evcap.importers.calibration_files; ``camera`` the one to take of
    a file holding several) or from an evcap session's /calibration."""
    path = Path(path)
    if path.suffix in (".h5", ".hdf5"):
        return _session_calibration(path)
    cal = read_calibration_file(path, camera)
    if cal.skew != 0:
        raise InputError(f"{cal.describe()}: a camera matrix with skew; the simulator has none")
    K = cal.K
    return CameraSpec(
        cal.width,
        cal.height,
        float(K[0, 0]),
        float(K[1, 1]),
        float(K[0, 2]),
        float(K[1, 2]),
        cal.distortion_model,
        tuple(float(v) for v in cal.dist),
        source=path.name,
    )


def _session_calibration(path: Path) -> CameraSpec:
    """The intrinsics of an evcap session's /calibration (measured by `evcap calibrate`)."""
    from evcap.records import read_intrinsics
    from evcap.session import Session

    with Session.open(path, validate=False) as s:
        K, model, dist = read_intrinsics(s)
        w, h = s.sensor.width, s.sensor.height
    return CameraSpec(
        w,
        h,
        float(K[0, 0]),
        float(K[1, 1]),
        float(K[0, 2]),
        float(K[1, 2]),
        model,
        tuple(float(v) for v in dist),
        path.name,
    )


class Camera:
    """A pinhole camera with distortion."""

    def __init__(self, spec: CameraSpec) -> None:
        self.spec = spec
        self.width, self.height = spec.width, spec.height
        self.K = np.array([[spec.fx, 0, spec.cx], [0, spec.fy, spec.cy], [0, 0, 1]], np.float64)
        self._rays: np.ndarray | None = None

    def distort(self, xn: np.ndarray, yn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normalized undistorted coordinates -> normalized distorted ones."""
        s = self.spec
        k = list(s.distortion) + [0.0] * 5
        if s.distortion_model == "radtan":
            k1, k2, p1, p2, k3 = k[:5]
            r2 = xn * xn + yn * yn
            radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2**3
            xd = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
            yd = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
            return xd, yd
        if s.distortion_model == "equidistant":
            k1, k2, k3, k4 = k[:4]
            r = np.sqrt(xn * xn + yn * yn)
            theta = np.arctan(r)
            theta_d = theta * (1 + k1 * theta**2 + k2 * theta**4 + k3 * theta**6 + k4 * theta**8)
            scale = np.where(r > 1e-12, theta_d / np.maximum(r, 1e-12), 1.0)
            return xn * scale, yn * scale
        return xn, yn

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """[N, 3] points in the camera frame -> [N, 2] pixel coordinates (z must be > 0)."""
        z = points_cam[:, 2]
        xd, yd = self.distort(points_cam[:, 0] / z, points_cam[:, 1] / z)
        return np.stack([self.K[0, 0] * xd + self.K[0, 2], self.K[1, 1] * yd + self.K[1, 2]], 1)

    def undistort(self, u: np.ndarray, v: np.ndarray, iterations: int = 30) -> np.ndarray:
        """Pixel coordinates -> normalized undistorted coordinates [N, 2] (fixed-point
        iteration on the distortion, then Newton polish)."""
        xd = (u - self.K[0, 2]) / self.K[0, 0]
        yd = (v - self.K[1, 2]) / self.K[1, 1]
        x, y = xd.copy(), yd.copy()
        if self.spec.distortion_model == "none":
            return np.stack([x, y], 1)
        if self.spec.distortion_model == "equidistant":  # Newton on the angle theta
            k1, k2, k3, k4 = (list(self.spec.distortion) + [0.0] * 4)[:4]
            theta_d = np.sqrt(xd * xd + yd * yd)
            theta = theta_d.copy()
            for _ in range(iterations):
                t2 = theta * theta
                f = theta * (1 + k1 * t2 + k2 * t2**2 + k3 * t2**3 + k4 * t2**4) - theta_d
                df = 1 + 3 * k1 * t2 + 5 * k2 * t2**2 + 7 * k3 * t2**3 + 9 * k4 * t2**4
                theta = theta - f / df
            scale = np.where(theta_d > 1e-12, np.tan(theta) / np.maximum(theta_d, 1e-12), 1.0)
            return np.stack([xd * scale, yd * scale], 1)
        for _ in range(iterations):
            fx, fy = self.distort(x, y)
            x, y = x - (fx - xd), y - (fy - yd)
        return np.stack([x, y], 1)

    def rays(self) -> np.ndarray:
        """[H * W, 3] unit ray directions in the camera frame through the pixel centers
        (pixel (x, y) covers [x - 0.5, x + 0.5]), row-major."""
        if self._rays is None:
            v, u = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
            xy = self.undistort(u.ravel(), v.ravel())
            d = np.concatenate([xy, np.ones((xy.shape[0], 1))], 1)
            self._rays = d / np.linalg.norm(d, axis=1, keepdims=True)
        return self._rays
