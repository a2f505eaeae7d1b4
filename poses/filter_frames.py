"""Intensity frames from events with no network: each pixel's log intensity integrated from its
events (each adds its polarity's contrast threshold) through a first-order high-pass filter
(Scheerlinck et al., ACCV 2018), so what a pixel saw long ago fades instead of drifting.
Frames are made on the raw mosaic: one value per pixel, in that pixel's own color channel."""

from __future__ import annotations

import numba
import numpy as np

from evcap.errors import InputError
from evcap.events import Events


@numba.njit(cache=True, nogil=True)
def _high_pass(x, y, t, p, c_on, c_off, times, alpha, width, height):  # pragma: no cover - numba
    n_px = width * height
    value = np.zeros(n_px)
    last = np.zeros(n_px)
    out = np.zeros((len(times), height, width), np.float32)
    k = 0
    for i in range(len(t)):
        while k < len(times) and t[i] > times[k]:
            for j in range(n_px):
                out[k, j // width, j % width] = value[j] * np.exp(-alpha * (times[k] - last[j]))
            k += 1
        if k == len(times):
            break
        j = int(y[i]) * width + int(x[i])
        value[j] = value[j] * np.exp(-alpha * (t[i] - last[j])) + (c_on[j] if p[i] else -c_off[j])
        last[j] = t[i]
    while k < len(times):
        for j in range(n_px):
            out[k, j // width, j % width] = value[j] * np.exp(-alpha * (times[k] - last[j]))
        k += 1
    return out


def high_pass_frames(
    events: Events,
    times_us: np.ndarray,
    *,
    cutoff_hz: float = 2.0,
    threshold_on: np.ndarray | float = 0.2,
    threshold_off: np.ndarray | float = 0.2,
    exclude: np.ndarray | None = None,
) -> np.ndarray:
    """[K, H, W] float32 log-intensity change (log units) of each pixel at ``times_us``, from
    ``events`` through a high-pass filter with corner ``cutoff_hz``: a still scene fades to 0
    in about 1 / (2 pi cutoff) seconds. ``exclude`` ([H, W] bool) marks pixels to leave at 0
    (hot pixels)."""
    times = np.asarray(times_us, np.int64)
    if times.ndim != 1 or (np.diff(times) < 0).any():
        raise InputError("frame times must be a 1-D increasing sequence of microseconds")
    if cutoff_hz <= 0:
        raise InputError(f"cutoff_hz must be positive, got {cutoff_hz}")
    w, h = events.width, events.height
    c_on = np.broadcast_to(np.asarray(threshold_on, np.float64), (h, w)).ravel().copy()
    c_off = np.broadcast_to(np.asarray(threshold_off, np.float64), (h, w)).ravel().copy()
    ev = events if exclude is None else events.select(~exclude[events.y, events.x])
    alpha = 2 * np.pi * cutoff_hz * 1e-6  # per microsecond
    return _high_pass(ev.x, ev.y, ev.t, ev.p, c_on, c_off, times, alpha, w, h)
