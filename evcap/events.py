"""The event container: validated x, y, t, p arrays with the sensor they come from.

Coordinates have their origin at the top-left pixel (x to the right, y down), as the DAVIS346
sends them. Timestamps are microseconds since the session's t = 0 (absolute time is
t + t_offset_us, see evcap.session). Polarity 1 is ON (brightness went up), 0 is OFF.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from evcap.errors import InputError

COLOR_FILTERS = ("MONO", "RGBG", "GRGB", "GBGR", "BGRG")
"""Color filter names as libcaer reports them (APS module, parameter 3): the 2x2 cell read
clockwise from the top-left pixel. The Color-DAVIS346 has RGBG: R at (even x, even y)."""


class Channel(IntEnum):
    """The color channel of a pixel."""

    RED = 0
    GREEN = 1
    BLUE = 2
    MONO = 3


_R, _G, _B = Channel.RED, Channel.GREEN, Channel.BLUE
# Channel at (x even, y even), (x odd, y even), (x even, y odd), (x odd, y odd).
_CELLS = {
    "MONO": (Channel.MONO,) * 4,
    "RGBG": (_R, _G, _G, _B),
    "GRGB": (_G, _R, _B, _G),
    "GBGR": (_G, _B, _R, _G),
    "BGRG": (_B, _G, _G, _R),
}


def check_color_filter(name: str) -> str:
    """Return ``name`` if it is a known color filter, else raise InputError."""
    if name not in _CELLS:
        raise InputError(
            f"unknown color filter {name!r}; expected one of {', '.join(COLOR_FILTERS)}"
        )
    return name


def pixel_channels(x: np.ndarray, y: np.ndarray, color_filter: str) -> np.ndarray:
    """The Channel (as uint8) of each pixel (x, y), from its parity and the color filter."""
    cells = np.asarray(_CELLS[check_color_filter(color_filter)], dtype=np.uint8)
    return cells[(np.asarray(x) & 1) | ((np.asarray(y) & 1) << 1)]


def _as_uint(values: np.ndarray, dtype: type, name: str, limit: int) -> np.ndarray:
    """``values`` as ``dtype`` if they are integers in [0, limit), else raise InputError."""
    a = np.asarray(values)
    if a.ndim != 1:
        raise InputError(f"events: {name} must be 1-D, got shape {a.shape}")
    if a.dtype == bool:
        a = a.astype(np.uint8)
    if a.dtype.kind not in "iu":
        raise InputError(f"events: {name} must hold integers, got {a.dtype}")
    if a.size:
        lo, hi = int(a.min()), int(a.max())
        if lo < 0 or hi >= limit:
            bad = int(np.flatnonzero((a < 0) | (a >= limit))[0])
            raise InputError(
                f"events: {name}={int(a[bad])} at event {bad} is outside 0..{limit - 1}"
            )
    return np.ascontiguousarray(a, dtype=dtype)


def first_unsorted(t: np.ndarray) -> int:
    """Index of the first timestamp smaller than the one before it, or -1 when sorted."""
    if t.size < 2:
        return -1
    bad = np.flatnonzero(t[1:] < t[:-1])
    return int(bad[0]) + 1 if bad.size else -1


@dataclass(frozen=True, eq=False)
class Events:
    """Events of one sensor, sorted by time. Arrays are converted to the dtypes below and checked.

    >>> ev = Events(x=[3, 4], y=[0, 1], t=[10, 12], p=[1, 0], width=346, height=260)
    >>> len(ev), ev.t.dtype.name
    (2, 'int64')
    """

    x: np.ndarray  # [N] uint16, column, 0 = left
    y: np.ndarray  # [N] uint16, row, 0 = top
    t: np.ndarray  # [N] int64, microseconds since the session's t = 0, non-decreasing
    p: np.ndarray  # [N] uint8, 1 = ON, 0 = OFF
    width: int  # sensor width in pixels
    height: int  # sensor height in pixels
    color_filter: str = "MONO"  # one of COLOR_FILTERS

    def __post_init__(self) -> None:
        if not (0 < self.width <= 65536 and 0 < self.height <= 65536):
            raise InputError(f"events: sensor size {self.width} x {self.height} is not valid")
        check_color_filter(self.color_filter)
        x = _as_uint(self.x, np.uint16, "x", self.width)
        y = _as_uint(self.y, np.uint16, "y", self.height)
        p = _as_uint(self.p, np.uint8, "p", 2)
        t = np.asarray(self.t)
        if t.ndim != 1 or t.dtype.kind not in "iu":
            raise InputError(
                f"events: t must be 1-D integers (microseconds), got {t.dtype} {t.shape}"
            )
        if t.dtype == np.uint64 and t.size and int(t.max()) > np.iinfo(np.int64).max:
            raise InputError("events: t does not fit in int64 microseconds")
        t = np.ascontiguousarray(t, dtype=np.int64)
        if not (x.size == y.size == t.size == p.size):
            raise InputError(
                "events: x, y, t, p have different lengths "
                f"({x.size}, {y.size}, {t.size}, {p.size})"
            )
        bad = first_unsorted(t)
        if bad >= 0:
            raise InputError(
                f"events: timestamps are not in time order at event {bad} "
                f"(t={int(t[bad])} after t={int(t[bad - 1])})"
            )
        for name, value in (("x", x), ("y", y), ("t", t), ("p", p)):
            object.__setattr__(self, name, value)

    def __len__(self) -> int:
        return int(self.t.size)

    def __repr__(self) -> str:
        span = f", t {self.t[0]}..{self.t[-1]} us" if len(self) else ""
        return f"Events({len(self)} events, {self.width} x {self.height} {self.color_filter}{span})"

    @classmethod
    def _unchecked(
        cls,
        x: np.ndarray,
        y: np.ndarray,
        t: np.ndarray,
        p: np.ndarray,
        width: int,
        height: int,
        color_filter: str = "MONO",
    ) -> Events:
        """Events from arrays that already have the dtypes above and are known to be valid
        (a producer that guarantees them, such as the stream decoder); skips the checks."""
        ev = object.__new__(cls)
        for name, value in (
            ("x", x),
            ("y", y),
            ("t", t),
            ("p", p),
            ("width", width),
            ("height", height),
            ("color_filter", color_filter),
        ):
            object.__setattr__(ev, name, value)
        return ev

    @classmethod
    def empty(cls, width: int, height: int, color_filter: str = "MONO") -> Events:
        z = np.zeros(0, np.uint16)
        return cls(z, z, np.zeros(0, np.int64), np.zeros(0, np.uint8), width, height, color_filter)

    def _take(self, index: slice | np.ndarray) -> Events:
        return Events(
            self.x[index],
            self.y[index],
            self.t[index],
            self.p[index],
            self.width,
            self.height,
            self.color_filter,
        )

    def time_slice(self, t0: int | None = None, t1: int | None = None) -> Events:
        """The events with t0 <= t < t1 (either bound may be None)."""
        lo = 0 if t0 is None else int(np.searchsorted(self.t, t0, "left"))
        hi = len(self) if t1 is None else int(np.searchsorted(self.t, t1, "left"))
        return self._take(slice(lo, max(lo, hi)))

    def select(self, mask: np.ndarray) -> Events:
        """The events where the boolean ``mask`` is true, in their order."""
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != self.t.shape:
            raise InputError(f"events: mask of shape {mask.shape} for {len(self)} events")
        return self._take(mask)

    def channels(self) -> np.ndarray:
        """The color channel (Channel, as uint8) of each event, from its pixel's filter."""
        return pixel_channels(self.x, self.y, self.color_filter)
