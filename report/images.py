"""Arrays as images for the page: PNG data URIs, a color map, and the renderings of
normals, depth and linear radiance that the recovered maps and the truth share."""

from __future__ import annotations

import base64
from pathlib import Path

import cv2
import numpy as np

from evcap.images import srgb

INVALID_RGB = (255, 0, 255)  # NaN or infinity, in every kind of map
EMPTY_RGB = (24, 24, 24)  # no surface in a depth or normal map


def png_data_uri(image: np.ndarray) -> str:
    """A data URI of ``image`` as PNG: uint8 (or uint16) [H, W] gray or [H, W, 3] RGB."""
    image = np.ascontiguousarray(image)
    if image.ndim == 3:
        image = image[..., ::-1]  # OpenCV writes BGR
    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise ValueError(f"cannot encode an image of shape {image.shape} as PNG")
    return "data:image/png;base64," + base64.b64encode(data.tobytes()).decode("ascii")


def file_data_uri(path: str | Path) -> str:
    """A data URI of a PNG file, its bytes as they are."""
    data = Path(path).read_bytes()
    return "data:image/png;base64," + base64.b64encode(data).decode("ascii")


def value_range(
    values: np.ndarray, percentiles: tuple[float, float] = (1, 99)
) -> tuple[float, float]:
    """(low, high) of the finite values at these percentiles, so that a few outliers do not
    wash the map out; (0, 1) when there are none, and never an empty range."""
    v = np.asarray(values, np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return 0.0, 1.0
    lo, hi = (float(x) for x in np.percentile(v, percentiles))
    if not hi > lo:
        hi = lo + max(abs(lo) * 1e-3, 1e-9)
    return lo, hi


def colormap(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """[H, W] values -> [H, W, 3] uint8 RGB on OpenCV's viridis from ``lo`` to ``hi`` (clipped);
    NaN and infinity magenta."""
    v = np.asarray(values, np.float64)
    finite = np.isfinite(v)
    s = np.clip((np.where(finite, v, lo) - lo) / max(hi - lo, 1e-300), 0.0, 1.0)
    out = cv2.applyColorMap((s * 255 + 0.5).astype(np.uint8), cv2.COLORMAP_VIRIDIS)[..., ::-1]
    out = np.ascontiguousarray(out)
    out[~finite] = INVALID_RGB
    return out


def ramp_image(width: int = 160, height: int = 10) -> np.ndarray:
    """The color map's ramp, low to high from left to right (a color bar)."""
    return colormap(np.tile(np.linspace(0.0, 1.0, width), (height, 1)), 0.0, 1.0)


def srgb8(linear: np.ndarray) -> np.ndarray:
    """Linear RGB [H, W, 3], 0..1 -> uint8 sRGB RGB; a pixel with NaN or infinity magenta."""
    x = np.asarray(linear, np.float64)
    out = (srgb(np.nan_to_num(x, nan=0.0)) * 255 + 0.5).astype(np.uint8)
    out[~np.isfinite(x).all(-1)] = INVALID_RGB
    return out


def gray_image(values: np.ndarray) -> np.ndarray:
    """[H, W] values in [0, 1] (roughness, an edge map) -> RGB gray, as they are; NaN and
    infinity magenta."""
    x = np.asarray(values, np.float64)
    g = (np.clip(np.nan_to_num(x, nan=0.0), 0.0, 1.0) * 255 + 0.5).astype(np.uint8)
    out = np.repeat(g[..., None], 3, -1)
    out[~np.isfinite(x)] = INVALID_RGB
    return out


def normal_image(normal: np.ndarray) -> np.ndarray:
    """Unit normals [H, W, 3] (camera frame) -> RGB (n + 1) / 2; no surface (a zero normal)
    dark, NaN or infinity magenta."""
    n = np.asarray(normal, np.float64)
    finite = np.isfinite(n).all(-1)
    n = np.where(finite[..., None], n, 0.0)
    out = (np.clip((n + 1) / 2, 0, 1) * 255 + 0.5).astype(np.uint8)
    out[np.linalg.norm(n, axis=-1) <= 0.5] = EMPTY_RGB
    out[~finite] = INVALID_RGB
    return out


def depth_image(depth: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Depth [H, W] (camera z) -> RGB on the ramp from ``lo`` (near) to ``hi``; no surface
    (0) dark, NaN or infinity magenta."""
    d = np.asarray(depth, np.float64)
    out = colormap(d, lo, hi)
    out[np.isfinite(d) & (d <= 0)] = EMPTY_RGB
    return out


def depth_range(*depths: np.ndarray) -> tuple[float, float]:
    """One (low, high) for depth maps shown side by side: their surfaces' 1..99 percentiles."""
    values = [np.asarray(d, np.float64).ravel() for d in depths]
    v = np.concatenate(values) if values else np.zeros(0)
    return value_range(v[np.isfinite(v) & (v > 0)])


def event_image(x: np.ndarray, y: np.ndarray, p: np.ndarray, width: int, height: int) -> np.ndarray:
    """Events accumulated into RGB: ON red, OFF blue, on white; each pixel's color saturates
    at a few events."""
    on = np.bincount((y * width + x)[p > 0], minlength=width * height).reshape(height, width)
    off = np.bincount((y * width + x)[p == 0], minlength=width * height).reshape(height, width)
    busy = np.maximum(on, off)
    busy = busy[busy > 0]
    scale = max(float(np.percentile(busy, 99)), 1.0) if busy.size else 1.0
    a_on, a_off = np.clip(on / scale, 0, 1), np.clip(off / scale, 0, 1)
    rgb = np.ones((height, width, 3))
    rgb -= a_on[..., None] * [0.0, 0.85, 0.85]  # toward red
    rgb -= a_off[..., None] * [0.85, 0.6, 0.0]  # toward blue
    return (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)


def mark_pixels(image: np.ndarray, mask: np.ndarray, scale: int = 2) -> np.ndarray:
    """``image`` [H, W, 3] enlarged ``scale`` times (nearest), with a red circle around each
    pixel of ``mask`` (hot pixels are single pixels: too small to see unmarked)."""
    big = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    big = np.ascontiguousarray(big)
    for y, x in zip(*np.nonzero(mask), strict=True):
        centre = (int(x * scale + scale // 2), int(y * scale + scale // 2))
        cv2.circle(big, centre, 4 * scale, (230, 20, 20), 1, cv2.LINE_AA)
    return big
