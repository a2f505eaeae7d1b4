"""What the monitor shows, computed from the decoded stream in the capture thread.

``LiveView`` takes every decoded batch and, when asked, gives a ``LiveSnapshot``: event rates
per 100 ms of device time (ON, OFF, and per color channel), an image of the events of the
last few milliseconds, the latest APS frame demosaiced for display, the latest IMU sample,
and the share of events the hottest pixels make. Everything is in device time, so what is
shown does not depend on how fast the host draws (and tests are deterministic).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from evcap.acquire.decoder import Decoded
from evcap.events import Channel, pixel_channels

SERIES = ("on", "off", "red", "green", "blue")
ON_COLOR = np.array([90, 230, 110])
OFF_COLOR = np.array([240, 70, 70])
CHANNEL_COLORS = np.array([[255, 60, 60], [60, 230, 60], [80, 120, 255], [230, 230, 230]])
HOT_PIXEL_FRACTION = 0.001  # the hottest 0.1 % of pixels...
HOT_PIXEL_WARNING = 0.5  # ...making half of the events: hot pixels dominate the rate


@dataclass
class LiveSnapshot:
    """One update of the monitor's view."""

    t_us: int  # device time of the latest data
    bin_us: int  # width of a rate bin
    rates: dict[str, np.ndarray]  # events per second in each recent bin, per SERIES name
    image: np.ndarray  # [H, W, 3] uint8: the events of the last window, colored
    window_us: int
    frame: np.ndarray | None = None  # [h, w, 3] uint8: the latest APS frame, for display
    frame_t_us: int | None = None
    accel: np.ndarray | None = None  # [3] m/s^2, latest IMU sample
    gyro: np.ndarray | None = None  # [3] rad/s
    temperature: float | None = None  # degC
    totals: dict[str, int] = field(default_factory=dict)  # since the start
    hot_pixel_share: float = 0.0  # share of the last second's events from the hottest 0.1 %

    @property
    def rate_hz(self) -> float:
        """The event rate in the last complete bin."""
        total = self.rates["on"] + self.rates["off"]
        return float(total[-2]) if total.size >= 2 else float(total.sum())

    @property
    def hot_pixels_dominate(self) -> bool:
        return self.hot_pixel_share >= HOT_PIXEL_WARNING


def frame_for_display(raw: np.ndarray, color_filter: str) -> np.ndarray:
    """An APS frame (10-bit raw mosaic) as 8-bit RGB, contrast-stretched for the eye.

    A color frame is demosaiced by its 2 x 2 cells (R, mean of the Gs, B): half the
    resolution, which a terminal cannot show anyway."""
    raw = raw.astype(np.float32)
    if color_filter == "MONO":
        rgb = np.repeat(raw[..., None], 3, axis=2)
    else:
        h, w = raw.shape[0] // 2 * 2, raw.shape[1] // 2 * 2
        yy, xx = np.mgrid[0:2, 0:2]
        cells = pixel_channels(xx.ravel(), yy.ravel(), color_filter).reshape(2, 2)
        rgb = np.zeros((h // 2, w // 2, 3), np.float32)
        count = np.zeros(3, np.float32)
        for dy in range(2):
            for dx in range(2):
                c = int(cells[dy, dx])
                rgb[..., c] += raw[dy:h:2, dx:w:2]
                count[c] += 1
        rgb /= np.maximum(count, 1)
    lo, hi = np.percentile(rgb, [1, 99])
    return (np.clip((rgb - lo) / max(hi - lo, 1.0), 0, 1) * 255).astype(np.uint8)


class LiveView:
    """Accumulates decoded batches for display."""

    def __init__(
        self,
        width: int,
        height: int,
        color_filter: str = "MONO",
        *,
        window_us: int = 33_000,
        bin_us: int = 100_000,
        history: int = 120,
    ) -> None:
        self.width, self.height, self.color_filter = width, height, color_filter
        self.window_us, self.bin_us, self.history = window_us, bin_us, history
        self.by_channel = False  # color the image by Bayer channel instead of polarity
        self._recent: deque[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = deque()
        self._bins: dict[int, np.ndarray] = {}  # bin index -> counts per SERIES
        self._pixel_bins: deque[tuple[int, np.ndarray]] = deque()  # per-pixel counts per bin
        self._t = 0
        self._frame: np.ndarray | None = None  # latest, raw
        self._frame_shown: np.ndarray | None = None  # latest, for display (made once)
        self._frame_t: int | None = None
        self._imu: tuple | None = None
        self.totals = {"events": 0, "on": 0, "off": 0, "frames": 0, "imu": 0, "triggers": 0}

    def add(self, d: Decoded) -> None:
        ev = d.events
        n = len(ev)
        t = self.totals
        t["events"] += n
        on = int(ev.p.sum())
        t["on"] += on
        t["off"] += n - on
        t["frames"] += len(d.frames)
        t["imu"] += len(d.imu)
        t["triggers"] += len(d.triggers)
        if n:
            self._t = max(self._t, int(ev.t[-1]))
            self._add_rates(ev)
            self._add_pixels(ev)
            self._recent.append(
                (int(ev.t[-1]), ev.t, ev.y.astype(np.int64) * self.width + ev.x, ev.p)
            )
        if len(d.frames):
            self._frame, self._frame_shown = d.frames.data[-1], None
            self._frame_t = int(d.frames.t[-1])
            self._t = max(self._t, self._frame_t)
        if len(d.imu):
            self._imu = (d.imu.accel[-1], d.imu.gyro[-1], float(d.imu.temperature[-1]))
            self._t = max(self._t, int(d.imu.t[-1]))
        while self._recent and self._recent[0][0] < self._t - self.window_us:
            self._recent.popleft()

    def _add_rates(self, ev) -> None:
        b = ev.t // self.bin_us
        first = int(b[0])
        span = int(b[-1]) - first + 1
        channels = ev.channels()
        series = [
            ev.p == 1,
            ev.p == 0,
            channels == Channel.RED,
            channels == Channel.GREEN,
            channels == Channel.BLUE,
        ]
        counts = np.stack([np.bincount(b[m] - first, minlength=span) for m in series], axis=1)
        for k in range(span):
            bins = self._bins.setdefault(first + k, np.zeros(len(SERIES), np.int64))
            bins += counts[k]
        newest = max(self._bins)
        for old in [i for i in self._bins if i <= newest - self.history]:
            del self._bins[old]

    def _add_pixels(self, ev) -> None:
        b = int(ev.t[-1]) // self.bin_us
        counts = np.bincount(
            ev.y.astype(np.int64) * self.width + ev.x, minlength=self.width * self.height
        )
        if self._pixel_bins and self._pixel_bins[-1][0] == b:
            self._pixel_bins[-1][1][:] += counts
        else:
            self._pixel_bins.append((b, counts))
        second = 1_000_000 // self.bin_us
        while self._pixel_bins and self._pixel_bins[0][0] <= b - second:
            self._pixel_bins.popleft()

    def hot_pixel_share(self) -> float:
        if not self._pixel_bins:
            return 0.0
        counts = np.sum([c for _, c in self._pixel_bins], axis=0)
        total = int(counts.sum())
        if total < 1000:
            return 0.0  # too few events to tell
        k = max(1, int(counts.size * HOT_PIXEL_FRACTION))
        return float(np.partition(counts, -k)[-k:].sum() / total)

    def image(self) -> np.ndarray:
        """The events of the last window: by polarity, or by Bayer channel."""
        n_pix = self.width * self.height
        out = np.zeros((n_pix, 3), np.float32)
        start = self._t - self.window_us
        for _, t, pixel, p in self._recent:
            keep = t >= start
            pixel, p = pixel[keep], p[keep]
            if self.by_channel and self.color_filter != "MONO":
                channel = pixel_channels(pixel % self.width, pixel // self.width, self.color_filter)
                for c in range(3):
                    count = np.bincount(pixel[channel == c], minlength=n_pix)
                    out += count[:, None] * CHANNEL_COLORS[c] * 0.6
            else:
                out += np.bincount(pixel[p == 1], minlength=n_pix)[:, None] * ON_COLOR * 0.6
                out += np.bincount(pixel[p == 0], minlength=n_pix)[:, None] * OFF_COLOR * 0.6
        return np.clip(out, 0, 255).astype(np.uint8).reshape(self.height, self.width, 3)

    def snapshot(self) -> LiveSnapshot:
        newest = self._t // self.bin_us
        bins = range(newest - self.history + 1, newest + 1)
        counts = np.array([self._bins.get(b, np.zeros(len(SERIES), np.int64)) for b in bins])
        rates = {name: counts[:, k] * (1e6 / self.bin_us) for k, name in enumerate(SERIES)}
        s = LiveSnapshot(
            self._t,
            self.bin_us,
            rates,
            self.image(),
            self.window_us,
            totals=dict(self.totals),
            hot_pixel_share=self.hot_pixel_share(),
        )
        if self._frame is not None:
            if self._frame_shown is None:
                self._frame_shown = frame_for_display(self._frame, self.color_filter)
            s.frame, s.frame_t_us = self._frame_shown, self._frame_t
        if self._imu is not None:
            s.accel, s.gyro, s.temperature = self._imu
        return s
