"""A dense, realistic DAVIS346 stream for the throughput benchmarks."""

from __future__ import annotations

import numpy as np

from evcap.acquire.encoder import StreamEncoder
from evcap.events import Events
from evcap.streams import Frames

W, H = 346, 260


def dense_events(seconds: float, rate_hz: float = 12e6, seed: int = 0) -> Events:
    """Edges sweeping the sensor at the DAVIS346's peak rate. The readout sends a row address,
    then the columns of that row that fired: here each microsecond carries 12 events, in rows
    of 4 (about 1.4 words per event, as libcaer's own benchmark stream)."""
    rng = np.random.default_rng(seed)
    per_us = max(1, round(rate_hz / 1e6))
    n_us = int(seconds * 1e6)
    n = n_us * per_us
    t = np.repeat(np.arange(n_us, dtype=np.int64), per_us)
    sweep = (t / 1e6 * 400).astype(np.int64)  # the edges move 400 rows per second
    y = (sweep + np.arange(n) % per_us // 4 * 7) % H
    x = rng.integers(0, W, n)
    return Events(x, y, t, (rng.random(n) < 0.5).astype(np.uint8), W, H, "RGBG")


def dense_stream(seconds: float, rate_hz: float = 12e6) -> tuple[bytes, int]:
    """(bytes, number of events): events at ``rate_hz``, frames at 25 fps, IMU at 1 kHz."""
    events = dense_events(seconds, rate_hz)
    rng = np.random.default_rng(1)
    starts = np.arange(10_000, int(seconds * 1e6) - 10_000, 40_000)
    frames = Frames(rng.integers(0, 1024, (len(starts), H, W)), starts, [4000] * len(starts))
    imu_t = np.arange(500, int(seconds * 1e6), 1000)
    imu_raw = (imu_t, rng.integers(-3000, 3000, (imu_t.size, 7)).astype(np.int16))
    return StreamEncoder().encode(events, frames, imu_raw=imu_raw), len(events)
