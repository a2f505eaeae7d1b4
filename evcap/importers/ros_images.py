"""sensor_msgs/Image messages as the session's raw frames: each pixel the value its color
filter passes, on the 10-bit scale (8-bit images stored as value << 2, as AEDAT 4 frames are;
16-bit images, which ROS scales to the full 16 bits, as value >> 6)."""

from __future__ import annotations

import numpy as np

from evcap.errors import InputError
from evcap.events import pixel_channels

_BAYER = {"rggb": "RGBG", "grbg": "GRGB", "gbrg": "GBGR", "bggr": "BGRG"}
"""ROS Bayer patterns (rows top to bottom) as evcap's filters (clockwise from top-left)."""
_RAW = {"mono8", "mono16"} | {f"bayer_{b}{d}" for b in _BAYER for d in (8, 16)}
_RGB = {"rgb8", "bgr8", "rgb16", "bgr16"}
ENCODINGS = tuple(sorted(_RAW | _RGB))
"""Image encodings evcap imports."""


def bayer_filter(encoding: str) -> str | None:
    """The color filter a Bayer encoding states ("bayer_rggb8" -> "RGBG"), else None."""
    if encoding in _RAW and encoding.startswith("bayer_"):
        return _BAYER[encoding[6:10]]
    return None


def is_raw(encoding: str) -> bool:
    """True for encodings that hold the sensor's values (mono, Bayer), not demosaiced ones."""
    return encoding in _RAW


def precision_bits(encoding: str) -> int:
    """Significant bits of the frames made from images in ``encoding``."""
    return 8 if encoding.endswith("8") else 10


def image_values(msg: object, color_filter: str) -> np.ndarray:
    """The raw values (uint16, height x width, 0..1023) of a sensor_msgs/Image."""
    encoding = msg.encoding
    if encoding not in _RAW and encoding not in _RGB:
        raise InputError(
            f"images in encoding {encoding!r} are not supported ({', '.join(ENCODINGS)} are)"
        )
    depth = 8 if encoding.endswith("8") else 16
    dtype = np.dtype(np.uint8) if depth == 8 else np.dtype(">u2" if msg.is_bigendian else "<u2")
    channels = 3 if encoding in _RGB else 1
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    row = w * channels * dtype.itemsize
    data = np.asarray(msg.data, np.uint8)
    if step < row or data.size < h * step:
        raise InputError(f"a {w} x {h} {encoding} image of {data.size} bytes (step {step})")
    rows = np.ascontiguousarray(data[: h * step].reshape(h, step)[:, :row])
    pixels = rows.view(dtype).reshape(h, w, channels)
    if channels == 3:
        if color_filter == "MONO":
            raise InputError(f"{encoding} images on a MONO sensor")
        # demosaiced: keep at each pixel the channel its filter passes (R, G, B = 0, 1, 2)
        yy, xx = np.mgrid[0:h, 0:w]
        channel = pixel_channels(xx, yy, color_filter).astype(np.intp)
        if encoding.startswith("bgr"):
            channel = 2 - channel
        values = np.take_along_axis(pixels, channel[..., None], axis=2)[..., 0]
    else:
        values = pixels[..., 0]
    values = values.astype(np.uint16)
    return values << 2 if depth == 8 else values >> 6
