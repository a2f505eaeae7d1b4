"""Intensity frames from events with no network (Scheerlinck et al., ACCV 2018): each pixel's
log intensity integrated from its events (each adds its polarity's contrast threshold) and
pulled, at rate 2 pi cutoff, towards a reference: 0 (a high-pass filter: what a pixel saw long
ago fades instead of drifting) or, with APS frames, the log of the latest frame (the
complementary filter: the frames give the low frequencies, the events the high ones).
Frames are made on the raw mosaic: one value per pixel, in that pixel's own color channel."""

from __future__ import annotations

import numba
import numpy as np

from evcap.errors import InputError
from evcap.events import Events
from evcap.streams import Frames


@numba.njit(cache=True, nogil=True)
def _filter(x, y, t, p, c_on, c_off, ref_t, ref, times, alpha, width, height):  # pragma: no cover
    n_px = width * height
    value = ref[0].copy() if len(ref_t) else np.zeros(n_px)
    target = value.copy()
    last = np.zeros(n_px)
    if len(t):
        last[:] = t[0]
    out = np.zeros((len(times), height, width), np.float32)
    i = k = 0
    r = 1  # the next reference frame (the first is in force from the start)
    while k < len(times):
        # the next thing to happen: an event, a new reference frame, or an output frame
        t_event = t[i] if i < len(t) else np.iinfo(np.int64).max
        t_ref = ref_t[r] if r < len(ref_t) else np.iinfo(np.int64).max
        if times[k] < t_event and times[k] < t_ref:
            for j in range(n_px):
                decay = np.exp(-alpha * (times[k] - last[j]))
                out[k, j // width, j % width] = target[j] + (value[j] - target[j]) * decay
            k += 1
        elif t_ref <= t_event:
            for j in range(n_px):
                value[j] = target[j] + (value[j] - target[j]) * np.exp(-alpha * (t_ref - last[j]))
                last[j] = t_ref
                target[j] = ref[r, j]
            r += 1
        else:
            j = int(y[i]) * width + int(x[i])
            decay = np.exp(-alpha * (t[i] - last[j]))
            value[j] = target[j] + (value[j] - target[j]) * decay
            value[j] += c_on[j] if p[i] else -c_off[j]
            last[j] = t[i]
            i += 1
    return out


def high_pass_frames(
    events: Events,
    times_us: np.ndarray,
    *,
    cutoff_hz: float = 2.0,
    threshold_on: np.ndarray | float = 0.2,
    threshold_off: np.ndarray | float = 0.2,
    exclude: np.ndarray | None = None,
    aps: Frames | None = None,
) -> np.ndarray:
    """[K, H, W] float32 log intensity (log units) of each pixel at ``times_us``, from
    ``events`` through the filter with corner ``cutoff_hz``. Without ``aps`` frames it is the
    change from what the pixel saw lately (a still scene fades to 0 in about
    1 / (2 pi cutoff) seconds); with them, the log of each frame (per millisecond of
    exposure) corrected by the events since. ``exclude`` ([H, W] bool): pixels whose events
    are left out (hot pixels)."""
    times = np.asarray(times_us, np.int64)
    if times.ndim != 1 or (np.diff(times) < 0).any():
        raise InputError("frame times must be a 1-D increasing sequence of microseconds")
    if cutoff_hz <= 0:
        raise InputError(f"cutoff_hz must be positive, got {cutoff_hz}")
    w, h = events.width, events.height
    c_on = np.broadcast_to(np.asarray(threshold_on, np.float64), (h, w)).ravel().copy()
    c_off = np.broadcast_to(np.asarray(threshold_off, np.float64), (h, w)).ravel().copy()
    ev = events if exclude is None else events.select(~exclude[events.y, events.x])
    if aps is not None and len(aps):
        if aps.data.shape[1:] != (h, w):
            raise InputError(f"APS frames are {aps.data.shape[1:]}, the events {h} x {w}")
        per_ms = aps.data.reshape(len(aps), -1) / np.maximum(aps.exposure_us, 1)[:, None] * 1e3
        ref = np.log(per_ms + 1.0)  # + 1 count per ms keeps black pixels finite
        ref_t = aps.t + aps.exposure_us // 2
    else:
        ref, ref_t = np.zeros((0, w * h)), np.zeros(0, np.int64)
    alpha = 2 * np.pi * cutoff_hz * 1e-6  # per microsecond
    return _filter(ev.x, ev.y, ev.t, ev.p, c_on, c_off, ref_t, ref, times, alpha, w, h)


@numba.njit(cache=True, nogil=True)
def _time_surface(x, y, t, times, tau_us, width, height):  # pragma: no cover
    last = np.full(width * height, np.iinfo(np.int64).min)
    out = np.zeros((len(times), height, width), np.float32)
    i = 0
    for k in range(len(times)):
        while i < len(t) and t[i] <= times[k]:
            last[int(y[i]) * width + int(x[i])] = t[i]
            i += 1
        for j in range(width * height):
            if last[j] != np.iinfo(np.int64).min:
                out[k, j // width, j % width] = np.exp(-(times[k] - last[j]) / tau_us)
    return out


def time_surface_frames(
    events: Events,
    times_us: np.ndarray,
    *,
    tau_us: float,
    exclude: np.ndarray | None = None,
) -> np.ndarray:
    """[K, H, W] float32 exponentially decayed time surface at ``times_us``: each pixel
    exp(-(t - t_last) / tau) of its latest event at or before t, whatever its polarity (0 for a
    pixel with no event yet). An edge shows as a bright ridge fading behind it, the same
    whichever way it moves and whether it turns brighter or darker, where a filter's frame
    changes sign. ``exclude`` ([H, W] bool): pixels whose events are left out (hot pixels)."""
    times = np.asarray(times_us, np.int64)
    if times.ndim != 1 or (np.diff(times) < 0).any():
        raise InputError("frame times must be a 1-D increasing sequence of microseconds")
    if not tau_us > 0:
        raise InputError(f"tau_us must be positive, got {tau_us}")
    ev = events if exclude is None else events.select(~exclude[events.y, events.x])
    return _time_surface(ev.x, ev.y, ev.t, times, float(tau_us), events.width, events.height)
