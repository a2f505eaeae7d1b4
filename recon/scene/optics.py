"""The sensor as the reconstruction sees it: intrinsics and distortion, the color channel and
thresholds of each pixel, and the pinhole image that the Gaussians are rendered into.

Rendering is pinhole; the sensor is not (lens distortion) and need not share the render's
resolution. Each sensor pixel's undistorted position is computed once; a render is then read at
those positions by bilinear interpolation (differentiably), so every loss and every metric is
taken on the sensor's own pixels, each with its own color channel.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from evcap.events import Channel, pixel_channels
from evcap.records import Calibration
from evcap.records.calibration import DistortionModel
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
    distortion_model: DistortionModel
    distortion: np.ndarray
    color_filter: str
    threshold_on: np.ndarray  # [H, W] float32
    threshold_off: np.ndarray
    hot_pixels: np.ndarray  # [H, W] bool
    # each pixel's noise events a second, ON and OFF (the calibration's background activity,
    # ON events, and shot noise, half of each polarity)
    noise_on_hz: float = 0.0
    noise_off_hz: float = 0.0
    refractory_us: float = 0.0  # the calibration's refractory period

    @classmethod
    def from_session(cls, session: Session) -> SensorOptics:
        """The session's sensor and calibration; InputError naming what to run when the
        calibration lacks the intrinsics or the per-pixel thresholds."""
        calibration = Calibration.read(session)
        K, model, dist = calibration.intrinsics(str(session.path))
        on, off = calibration.thresholds(str(session.path))
        s = session.sensor
        shot = calibration.shot_noise_hz / 2
        return cls(
            s.width,
            s.height,
            K,
            model,
            dist,
            s.color_filter,
            on,
            off,
            calibration.hot(),
            calibration.background_activity_hz + shot,
            shot,
            calibration.refractory_period_us,
        )

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
    rays: torch.Tensor | None = None  # [h, w, 3] unit directions through the pixel centres,
    # in the camera's frame (made from K when not given)
    _sampler: object = dataclasses.field(default=None, repr=False)  # sample()'s on the CPU

    def __post_init__(self) -> None:
        if self.rays is None:
            K = self.K
            ys, xs = torch.meshgrid(
                torch.arange(self.height, dtype=K.dtype, device=K.device),
                torch.arange(self.width, dtype=K.dtype, device=K.device),
                indexing="ij",
            )
            x, y = (xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1]
            self.rays = F.normalize(torch.stack([x, y, torch.ones_like(xs)], -1), dim=-1)

    def state(self) -> dict:
        """The grid as saved with a training's state (on the CPU)."""
        arrays = {"K": self.K, "grid": self.grid, "rays": self.rays}
        return {"width": self.width, "height": self.height} | {
            k: v.detach().cpu() for k, v in arrays.items()
        }

    @classmethod
    def from_state(cls, state: dict, device: torch.device | str = "cpu") -> RenderGrid:
        arrays = {k: state[k].to(device) for k in ("K", "grid", "rays")}
        return cls(width=int(state["width"]), height=int(state["height"]), **arrays)

    def directions(self, viewmat: torch.Tensor) -> torch.Tensor:
        """[h, w, 3] unit world directions of the rays through the render's pixel centres, for
        a camera at ``viewmat`` [4, 4] (world to camera)."""
        return self.rays @ viewmat[:3, :3]

    def sample(self, image: torch.Tensor) -> torch.Tensor:
        """Values [H_sensor * W_sensor, C] of a render [h, w, C] at the sensor's pixels (on the
        CPU one compiled sparse product, recon/scene/_sample_cpu.py; elsewhere grid_sample)."""
        if image.device.type == "cpu":
            if self._sampler is None:
                from evcap.recon.scene._sample_cpu import Sampler

                self._sampler = Sampler.of_grid(self.grid, self.width, self.height)
            return self._sampler(image)
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


__all__ = ["CHANNEL_WEIGHTS", "Channel", "RenderGrid", "SensorOptics", "render_grid"]
