"""The sensor as the reconstruction sees it: intrinsics and distortion, the color channel and
thresholds of each pixel, and the pinhole image that the Gaussians are rendered into.

Rendering is pinhole; the sensor is not (lens distortion) and need not share the render's
resolution. Each sensor pixel's undistorted position is computed once; a render is then read at
those positions by bilinear interpolation (differentiably), so every loss and every metric is
taken on the sensor's own pixels, each with its own color channel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from evcap.errors import InputError
from evcap.events import Channel, pixel_channels
from evcap.records import read_intrinsics
from evcap.session import Session

# what each channel sees of the rendered (R, G, B): a Bayer pixel one of them, MONO luminance
CHANNEL_WEIGHTS = torch.tensor(
    [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [0.2126, 0.7152, 0.0722]], dtype=torch.float32
)


@dataclass
class SensorOptics:
    width: int
    height: int
    K: np.ndarray  # [3, 3]
    distortion_model: str  # none, radtan, equidistant
    distortion: np.ndarray
    color_filter: str
    threshold_on: np.ndarray  # [H, W] float32
    threshold_off: np.ndarray
    hot_pixels: np.ndarray  # [H, W] bool

    @classmethod
    def from_session(cls, session: Session) -> SensorOptics:
        if "calibration" not in session.groups:
            raise InputError(
                f"{session.path} has no calibration (/calibration); "
                "run `evcap calibrate` on it first"
            )
        g = session.group("calibration")
        s = session.sensor
        w, h = int(g.attrs.get("width", s.width)), int(g.attrs.get("height", s.height))
        if (w, h) != (s.width, s.height):
            raise InputError(
                f"{session.path}: the calibration is for {w} x {h}, the sensor is "
                f"{s.width} x {s.height}"
            )
        K, model, dist = read_intrinsics(session)
        on = _map(g, "threshold_on", h, w, session)
        off = _map(g, "threshold_off", h, w, session)
        hot = g["hot_pixels"][:].astype(bool) if "hot_pixels" in g else np.zeros((h, w), bool)
        return cls(w, h, K, model, dist, s.color_filter, on, off, hot)

    def undistorted(self) -> np.ndarray:
        """[H * W, 2] normalized pinhole coordinates (x/z, y/z) of each sensor pixel's centre."""
        yy, xx = np.mgrid[0 : self.height, 0 : self.width]
        pts = np.stack([xx.ravel(), yy.ravel()], 1).astype(np.float64)[:, None, :]
        if self.distortion_model == "none" or not np.any(self.distortion):
            Kinv = np.linalg.inv(self.K)
            return pts[:, 0] @ Kinv[:2, :2].T + Kinv[:2, 2]
        import cv2

        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
        if self.distortion_model == "radtan":
            out = cv2.undistortPoints(pts, self.K, self.distortion, criteria=crit)
        else:
            out = cv2.fisheye.undistortPoints(pts, self.K, self.distortion[:4], criteria=crit)
        return out[:, 0]

    def channels(self) -> np.ndarray:
        """[H * W] Channel of each pixel."""
        yy, xx = np.mgrid[0 : self.height, 0 : self.width]
        return pixel_channels(xx.ravel(), yy.ravel(), self.color_filter)

    def is_mono(self) -> bool:
        return self.color_filter == "MONO"


@dataclass
class RenderGrid:
    """A pinhole render covering the sensor, and where each sensor pixel falls in it."""

    K: torch.Tensor  # [3, 3]
    width: int
    height: int
    grid: torch.Tensor  # [1, 1, H * W, 2] for grid_sample (align_corners=True)

    def sample(self, image: torch.Tensor) -> torch.Tensor:
        """Values [H_sensor * W_sensor, C] of a render [h, w, C] at the sensor's pixels."""
        x = image.permute(2, 0, 1)[None]
        out = F.grid_sample(
            x, self.grid, mode="bilinear", padding_mode="border", align_corners=True
        )
        return out[0, :, 0].T


def render_grid(
    optics: SensorOptics, scale: float, device: torch.device | str = "cpu"
) -> RenderGrid:
    """The pinhole image at ``scale`` times the sensor's focal length that holds every sensor
    pixel's undistorted position."""
    xy = optics.undistorted()
    fx, fy = optics.K[0, 0] * scale, optics.K[1, 1] * scale
    # render coordinates: scale * (sensor pixel), shifted by whole pixels where distortion
    # reaches further, so that without distortion at scale 1 the two grids coincide
    u = xy[:, 0] * fx + optics.K[0, 2] * scale
    v = xy[:, 1] * fy + optics.K[1, 2] * scale
    u = u + max(0, int(np.ceil(-u.min() - 1e-6)))
    v = v + max(0, int(np.ceil(-v.min() - 1e-6)))
    cx, cy = (u - xy[:, 0] * fx)[0], (v - xy[:, 1] * fy)[0]
    width = int(np.ceil(u.max() - 1e-6)) + 1
    height = int(np.ceil(v.max() - 1e-6)) + 1
    K = torch.tensor([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=torch.float32)
    gx = 2 * u / max(width - 1, 1) - 1
    gy = 2 * v / max(height - 1, 1) - 1
    grid = torch.tensor(np.stack([gx, gy], 1), dtype=torch.float32).reshape(1, 1, -1, 2)
    return RenderGrid(K.to(device), width, height, grid.to(device))


def _map(g, name: str, h: int, w: int, session: Session) -> np.ndarray:
    if name not in g:
        raise InputError(f"{session.path}: /calibration has no {name}; run `evcap calibrate`")
    m = np.asarray(g[name][:], np.float32)
    if m.shape != (h, w) or not np.isfinite(m).all() or (m <= 0).any():
        raise InputError(f"{session.path}: /calibration/{name} must be {h} x {w} positive numbers")
    return m


__all__ = ["CHANNEL_WEIGHTS", "Channel", "RenderGrid", "SensorOptics", "render_grid"]
