"""Hot pixels, background activity, shot noise and the refractory period, from the events
(and the APS frames where the recording has them).

- Hot pixels. A pixel is a candidate when its rate is high: log10 of its rate above the
  median + ``rate_k`` MADs of all pixels' (loose: where the camera moves fast, most pixels
  are busy and a hot pixel is only a little above the median), with at least
  ``min_hot_events`` events of one polarity. A busy pixel on a moving edge is as fast; what
  tells a hot pixel apart is that it fires one polarity at a steady rate whatever the scene
  does. A candidate is hot when most of its events have one polarity
  (``dominance``), those events occupy most time bins (``occupancy``: with bins of three of
  its own mean intervals, a steady Poisson pixel fills 95 % of them, an edge pixel that fires
  when edges pass fills about a third) and do not come in bursts (``burst_share``: a Poisson
  pixel has 10 % of its intervals under a tenth of its mean interval, a pixel that edges
  cross, even regularly as a moving grating does, 75 % or more). Where APS frames exist, a
  candidate whose occupancy is only borderline is hot if it keeps firing while its APS value
  does not change (its events are not explained by the frames).
- Background activity (the leak: ON events) and shot noise (ON and OFF alike) are counted on
  pixels that see no change over the whole recording: the APS frames show no log change
  beyond their noise at the pixel and its 3 x 3 neighbours, and the pixel's neighbours within
  ``quiet_radius`` fire no more than noise would (a Poisson quantile of the noise rate). The
  selection looks at the neighbours' events only, never at the pixel's own, so that the
  pixel's own count is an unbiased sample of its noise. Without frames (or with no usable
  frame) the neighbour test alone selects the pixels. Shot noise is 2 x the OFF rate (it is
  symmetric), background activity the ON rate less the shot noise's ON half.
  Whole-recording spans, not shorter ones: after a scene change a pixel's leak restarts from
  a random point of its cycle (its reference sits anywhere within a threshold), so a pixel
  that has just seen an edge fires fewer leak events for a while, and counting it in short
  quiet spans would bias the leak rate low.
- Refractory period: a low percentile (not the minimum, which timestamp jitter moves) of the
  intervals between successive same-polarity events of a pixel, over the busiest pixels. A
  scene that never drives a pixel to its limit gives an upper bound.

Times are microseconds, rates Hz per pixel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from statistics import NormalDist

import numpy as np

from evcap.errors import CalibrationError, InputError
from evcap.events import Events
from evcap.streams import Frames

__all__ = [
    "NoiseConfig",
    "NoiseStats",
    "hot_pixel_mask",
    "measure_noise",
    "poisson_quantile",
    "refractory_period",
]


@dataclass(frozen=True)
class NoiseConfig:
    """How hot pixels, noise rates and the refractory period are measured."""

    rate_k: float = 1.0  # hot candidates: log10 rate above the median + rate_k MADs
    mad_floor: float = 0.1  # decades; a still scene's rates are discrete, their MAD can be 0
    min_hot_events: int = 30  # in the main polarity (10 time bins): fewer cannot show a
    # steady rate
    dominance: float = 0.65  # share of a hot pixel's events in its main polarity, at least
    occupancy: float = 0.7  # share of time bins (3 mean intervals long) a hot pixel fires in
    occupancy_maybe: float = 0.5  # ...or at least this much where the frames confirm it
    burst_share: float = 0.5  # a hot pixel's intervals under a tenth of its mean, at most
    unexplained: float = 0.8  # the frames confirm: the rate while the APS is still / overall
    static_false_alarm: float = 0.05  # chance that a still pixel is taken for a changing one
    # (the APS test's threshold in noise sigmas grows with the frames and neighbours it sees)
    quiet_radius: int = 3  # neighbours (a (2r+1)^2 square) whose events make a pixel busy
    quiet_quantile: float = 0.75  # neighbour events allowed: this Poisson quantile of noise
    min_static_pixels: int = 100  # fewer static pixels from the frames: use the events alone
    dark_dn: float = 20.0  # APS values below this are too dark to show a change
    saturated_dn: float = 1000.0  # APS values from this up are saturated
    black_dn: float = 0.0  # APS black level, subtracted before the log
    aps_gain_dn: float = 1.0  # DN per photo-electron (shot noise variance = gain * value)
    read_noise_dn: float = 2.0  # APS read noise, DN
    refractory_percentile: float = 0.5  # percentile of the intervals taken as the period
    busy_share: float = 0.1  # the busiest share of the pixels gives the intervals


@dataclass(frozen=True)
class NoiseStats:
    """What the recording says about the sensor's noise."""

    hot_pixels: np.ndarray  # [H, W] bool
    rate_hz: np.ndarray  # [H, W] float32, every event of the pixel over the duration
    background_activity_hz: float  # leak, per pixel (ON events), on still pixels
    shot_noise_hz: float  # per pixel, ON and OFF together, on still pixels
    refractory_period_us: float  # 0 when no pixel fired twice
    background_activity_err_hz: float = 0.0  # its standard error (Poisson counts)
    shot_noise_err_hz: float = 0.0  # its standard error (Poisson counts)
    on_rate_hz: float = 0.0  # still pixels' ON rate (leak + half the shot noise)
    off_rate_hz: float = 0.0  # still pixels' OFF rate (half the shot noise)
    static_pixels: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), bool))  # [H, W]
    static_pixel_seconds: float = 0.0  # what the noise rates were counted over
    noise_method: str = "none"  # "frames and events", "events" or "none" (no still pixel)
    duration_us: int = 0  # the span the rates are over
    candidates: int = 0  # rate outliers looked at as possible hot pixels
    notes: tuple[str, ...] = ()  # what limited the measurement, for a person


def measure_noise(
    events: Events,
    frames: Frames | None,
    *,
    duration_us: int | None = None,
    config: NoiseConfig = NoiseConfig(),
) -> NoiseStats:
    """Hot pixels, noise rates, refractory period and the per-pixel event rate.

    ``duration_us``: the recording's length (default: from the first to the last time of the
    events and frames). Raises CalibrationError when there are no events.
    """
    if len(events) == 0:
        raise CalibrationError(
            "noise: the recording has no events; record with the DVS on (a still scene is enough)"
        )
    w, h = events.width, events.height
    frames = _usable_frames(frames, w, h)
    t0, t1 = _span(events, frames, duration_us)
    events = events.time_slice(t0, t1)  # the events past a given duration are not counted
    if len(events) == 0:
        raise CalibrationError(f"noise: no events in the first {duration_us} us")
    span_s = (t1 - t0) * 1e-6
    pix = events.y.astype(np.int64) * w + events.x
    n_on = np.bincount(pix[events.p == 1], minlength=w * h)
    n_off = np.bincount(pix[events.p == 0], minlength=w * h)
    rate = (n_on + n_off) / span_s
    notes = []

    hot, candidates = _hot(events, pix, n_on, n_off, t0, t1, frames, config)
    hot = hot.reshape(h, w)
    static, method = _still_pixels(n_on + n_off, hot, frames, span_s, config)
    if method == "events" and frames is not None:
        notes.append("the APS frames show too few still pixels; noise from the events alone")
    pixel_s = float(static.sum()) * span_s
    still_on = int(n_on[static.ravel()].sum())
    still_off = int(n_off[static.ravel()].sum())
    if pixel_s > 0:
        on_rate, off_rate = still_on / pixel_s, still_off / pixel_s
        # Poisson errors: BA = (on - off) / S, shot = 2 off / S
        ba_err = math.sqrt(still_on + still_off) / pixel_s
        shot_err = 2.0 * math.sqrt(still_off) / pixel_s
        if still_on + still_off < 100:
            notes.append(
                f"noise rates from {still_on + still_off} events on {int(static.sum())} still "
                f"pixels ({pixel_s:.0f} pixel-seconds): record a still scene for longer"
            )
    else:
        on_rate = off_rate = ba_err = shot_err = 0.0
        method = "none"
        notes.append("no pixel is still over the recording: noise rates not measured (0)")
    refractory = refractory_period(
        events,
        exclude=hot,
        percentile=config.refractory_percentile,
        busy_share=config.busy_share,
    )
    if refractory == 0.0:
        notes.append("no pixel fired twice in a polarity: refractory period not measured (0)")
    return NoiseStats(
        hot_pixels=hot,
        rate_hz=rate.reshape(h, w).astype(np.float32),
        background_activity_hz=max(on_rate - off_rate, 0.0),
        shot_noise_hz=2.0 * off_rate,
        refractory_period_us=refractory,
        background_activity_err_hz=ba_err,
        shot_noise_err_hz=shot_err,
        on_rate_hz=on_rate,
        off_rate_hz=off_rate,
        static_pixels=static,
        static_pixel_seconds=pixel_s,
        noise_method=method,
        duration_us=int(t1 - t0),
        candidates=candidates,
        notes=tuple(notes),
    )


def hot_pixel_mask(
    events: Events,
    frames: Frames | None = None,
    *,
    duration_us: int | None = None,
    config: NoiseConfig = NoiseConfig(),
) -> np.ndarray:
    """[H, W] bool: the hot pixels alone (see the module's doc for the rule)."""
    if len(events) == 0:
        return np.zeros((events.height, events.width), bool)
    w, h = events.width, events.height
    frames = _usable_frames(frames, w, h)
    t0, t1 = _span(events, frames, duration_us)
    pix = events.y.astype(np.int64) * w + events.x
    n_on = np.bincount(pix[events.p == 1], minlength=w * h)
    n_off = np.bincount(pix[events.p == 0], minlength=w * h)
    return _hot(events, pix, n_on, n_off, t0, t1, frames, config)[0].reshape(h, w)


def refractory_period(
    events: Events,
    *,
    exclude: np.ndarray | None = None,
    percentile: float = 0.5,
    busy_share: float = 0.1,
) -> float:
    """The refractory period (us): the ``percentile`` of the intervals between successive
    same-polarity events of a pixel, over the busiest ``busy_share`` of the pixels that fire
    (``exclude``: [H, W] bool pixels left out, such as hot pixels). 0 when no pixel fired
    twice in one polarity."""
    w, h = events.width, events.height
    if len(events) < 2:
        return 0.0
    pix = events.y.astype(np.int64) * w + events.x
    counts = np.bincount(pix, minlength=w * h)
    if exclude is not None:
        counts[_mask(exclude, w, h, "exclude").ravel()] = 0
    firing = counts[counts >= 2]
    if firing.size == 0:
        return 0.0
    # the busiest pixels: at least this many events (ties keep the share a little larger)
    least = max(2, int(np.quantile(firing, 1.0 - busy_share, method="lower")))
    keep = counts[pix] >= least
    key = pix[keep] * 2 + events.p[keep]
    t = events.t[keep]
    order = np.argsort(key, kind="stable")  # events are in time order: stays so within a key
    key, t = key[order], t[order]
    same = key[1:] == key[:-1]
    intervals = (t[1:] - t[:-1])[same]
    if intervals.size == 0:
        return 0.0
    return float(np.percentile(intervals, percentile))


def poisson_quantile(q: float, mean: float) -> int:
    """The smallest k with P(X <= k) >= q for X ~ Poisson(mean)."""
    if mean <= 0.0:
        return 0
    if mean > 500.0:  # the normal approximation is close enough, and the sum below slow
        z = NormalDist().inv_cdf(min(max(q, 1e-12), 1.0 - 1e-12))
        return max(0, int(math.ceil(mean + z * math.sqrt(mean) - 0.5)))
    k, term = 0, math.exp(-mean)
    total = term
    while total < q:
        k += 1
        term *= mean / k
        total += term
    return k


# -- hot pixels ------------------------------------------------------------------------------


def _hot(events, pix, n_on, n_off, t0, t1, frames, c: NoiseConfig) -> tuple[np.ndarray, int]:
    """(flat bool mask of hot pixels, number of candidates)."""
    n = n_on + n_off
    span_s = (t1 - t0) * 1e-6
    log_rate = np.log10((n + 0.5) / span_s)
    median = float(np.median(log_rate))
    mad = max(1.4826 * float(np.median(np.abs(log_rate - median))), c.mad_floor)
    main = np.maximum(n_on, n_off)
    cand = (log_rate > median + c.rate_k * mad) & (main >= c.min_hot_events)
    cand &= main >= c.dominance * np.maximum(n, 1)
    hot = np.zeros(n.size, bool)
    ids = np.flatnonzero(cand)
    if ids.size == 0:
        return hot, 0
    # occupancy of the main polarity's events, in bins of three of the pixel's own intervals
    main_p = (n_on >= n_off).astype(np.uint8)
    take = cand[pix] & (events.p == main_p[pix])
    p_c, t_c = pix[take], events.t[take]
    bin_us = 3.0 * (t1 - t0) / np.maximum(main, 1)
    n_bins = np.maximum(np.ceil((t1 - t0) / bin_us), 1).astype(np.int64)
    bins = np.minimum(((t_c - t0) / bin_us[p_c]).astype(np.int64), n_bins[p_c] - 1)
    slot = np.full(n.size, -1, np.int64)
    slot[ids] = np.arange(ids.size)
    s_c = slot[p_c]
    stride = int(n_bins[ids].max())
    filled = np.unique(s_c * stride + bins) // stride
    occupancy = np.bincount(filled, minlength=ids.size) / n_bins[ids]
    # bursts: the share of intervals under a tenth of the pixel's mean interval (Poisson: 10 %)
    order = np.argsort(s_c, kind="stable")  # the events stay in time order within a pixel
    s_c, t_c = s_c[order], t_c[order]
    same = s_c[1:] == s_c[:-1]
    gaps, owner = (t_c[1:] - t_c[:-1])[same], s_c[1:][same]
    mean_gap = (t1 - t0) / main[ids]
    short = np.bincount(owner[gaps < 0.1 * mean_gap[owner]], minlength=ids.size)
    bursty = short > c.burst_share * np.maximum(main[ids] - 1, 1)
    steady = (occupancy >= c.occupancy) & ~bursty
    maybe = ~steady & ~bursty & (occupancy >= c.occupancy_maybe)
    if frames is not None and maybe.any():
        ratio = _unexplained(events, pix, frames, ids[maybe], c)
        steady[np.flatnonzero(maybe)] = ratio >= c.unexplained
    hot[ids[steady]] = True
    return hot, int(ids.size)


def _unexplained(events, pix, frames: Frames, ids: np.ndarray, c: NoiseConfig) -> np.ndarray:
    """For pixels ``ids``: their event rate while their own APS value is still (between
    frames whose log values agree within the noise), over their rate between all frames."""
    h, w = frames.data.shape[1:]
    mid = np.maximum.accumulate(frames.t + frames.exposure_us / 2.0)
    if len(frames) < 2:
        return np.zeros(ids.size)
    a = frames.data.reshape(len(frames), h * w)[:, ids].astype(np.float64) - c.black_dn
    exposed, log_exposure = _exposures(frames)
    valid = (a >= c.dark_dn) & (a + c.black_dn < c.saturated_dn) & exposed[:, None]
    y, var = _log_and_var(a, c)
    y -= log_exposure[:, None]
    z = np.abs(np.diff(y, axis=0)) / np.sqrt(var[1:] + var[:-1])
    still = (z < _two_sided_z(c.static_false_alarm)) & valid[1:] & valid[:-1]  # [N - 1, ids]
    slot = np.full(h * w, -1, np.int64)
    slot[ids] = np.arange(ids.size)
    sel = slot[pix] >= 0
    k = np.searchsorted(mid, events.t[sel], "right") - 1
    inside = (k >= 0) & (k < len(frames) - 1)
    s, k = slot[pix[sel]][inside], k[inside]
    all_n = np.bincount(s, minlength=ids.size)
    still_n = np.bincount(s[still[k, s]], minlength=ids.size)
    gaps = np.diff(mid)[:, None]
    still_s = (still * gaps).sum(0)
    all_s = float(mid[-1] - mid[0])
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = (still_n / np.maximum(still_s, 1e-9)) / (all_n / max(all_s, 1e-9))
    return np.where((still_s > 0) & (all_n > 0), ratio, 0.0)


# -- still pixels ----------------------------------------------------------------------------


def _still_pixels(
    counts: np.ndarray, hot: np.ndarray, frames: Frames | None, span_s: float, c: NoiseConfig
) -> tuple[np.ndarray, str]:
    """([H, W] bool pixels that see no change over the recording, how they were found)."""
    h, w = hot.shape
    candidates = ~hot
    method = "events"
    if frames is not None:
        still = _aps_still(frames, c) & ~hot
        if int(still.sum()) >= c.min_static_pixels:
            candidates, method = still, "frames and events"
    counts = np.where(hot.ravel(), 0, counts).reshape(h, w)
    r = c.quiet_radius
    ring = _box_sum(counts.astype(np.float64), r) - counts
    neighbours = _box_sum((~hot).astype(np.float64), r) - (~hot)
    if not candidates.any():
        return candidates, method
    # the noise rate: start from the median pixel (the mean where most pixels have no event),
    # then take the quiet pixels' own rate until it settles
    start = float(np.median(counts[candidates]))
    rate = (start if start > 0 else float(counts[candidates].mean())) / span_s
    quiet = np.zeros_like(candidates)
    for _ in range(8):
        limit = _quantile_table(c.quiet_quantile, rate * span_s, (2 * r + 1) ** 2)
        now = candidates & (ring <= limit[neighbours.astype(np.int64)])
        if not now.any():
            break
        quiet = now
        new = float(counts[quiet].sum()) / (float(quiet.sum()) * span_s)
        if abs(new - rate) <= 1e-3 * max(rate, 1e-12):
            break
        rate = new
    return quiet, method


def _aps_still(frames: Frames, c: NoiseConfig) -> np.ndarray:
    """[H, W] bool: every frame's log value (per unit of exposure) within the noise of the
    pixel's median, at the pixel and its 3 x 3 neighbours (all frames usable: exposed, neither
    dark nor saturated). The
    threshold, in noise sigmas, makes the chance of a false alarm among the 9 N values
    static_false_alarm (Bonferroni): 3.9 sigmas for 50 frames, 4.4 for 500."""
    n, h, w = frames.data.shape
    if n < 2:
        return np.zeros((h, w), bool)
    z_max = np.zeros((h, w))
    exposed, log_exposure = _exposures(frames)
    step = max(1, (1 << 22) // max(n * w, 1))  # rows at a time: bounded memory
    for r0 in range(0, h, step):
        a = frames.data[:, r0 : r0 + step].astype(np.float64) - c.black_dn
        valid = (a >= c.dark_dn) & (a + c.black_dn < c.saturated_dn)
        valid = (valid & exposed[:, None, None]).all(0)
        y, var = _log_and_var(a, c)
        y -= log_exposure[:, None, None]  # the APS value is proportional to the exposure
        z = (np.abs(y - np.median(y, axis=0)) / np.sqrt(var)).max(0)
        z_max[r0 : r0 + step] = np.where(valid, z, np.inf)
    return _max3(z_max) < _two_sided_z(c.static_false_alarm / (9 * n))


def _exposures(frames: Frames) -> tuple[np.ndarray, np.ndarray]:
    """([N] bool frames with an exposure, [N] log of their exposure time)."""
    return frames.exposure_us > 0, np.log(np.maximum(frames.exposure_us, 1).astype(np.float64))


def _log_and_var(a: np.ndarray, c: NoiseConfig) -> tuple[np.ndarray, np.ndarray]:
    """(log of APS values above the black level, the variance of that log from shot and
    read noise); values below 1 DN are taken as 1."""
    a = np.maximum(a, 1.0)
    return np.log(a), c.aps_gain_dn / a + (c.read_noise_dn / a) ** 2


def _two_sided_z(alpha: float) -> float:
    """z with P(|N(0, 1)| > z) = alpha."""
    return NormalDist().inv_cdf(1.0 - min(max(alpha, 1e-15), 1.0) / 2.0)


def _box_sum(a: np.ndarray, r: int) -> np.ndarray:
    """Sum over the (2r+1)^2 square around each pixel (zeros outside the image)."""
    s = np.pad(a, ((r + 1, r), (r + 1, r))).cumsum(0).cumsum(1)
    k = 2 * r + 1
    return s[k:, k:] - s[:-k, k:] - s[k:, :-k] + s[:-k, :-k]


def _max3(a: np.ndarray) -> np.ndarray:
    """Maximum over the 3 x 3 square around each pixel (the image edge repeated)."""
    p = np.pad(a, 1, mode="edge")
    h, w = a.shape
    return np.max([p[dy : dy + h, dx : dx + w] for dy in range(3) for dx in range(3)], axis=0)


def _quantile_table(q: float, mean_per_pixel: float, size: int) -> np.ndarray:
    """[size] the Poisson q-quantile of the events of k pixels, for k = 0..size-1."""
    return np.array([poisson_quantile(q, k * mean_per_pixel) for k in range(size)])


# -- helpers ---------------------------------------------------------------------------------


def _usable_frames(frames: Frames | None, w: int, h: int) -> Frames | None:
    if frames is None or len(frames) == 0:
        return None
    if frames.data.shape[1:] != (h, w):
        raise InputError(
            f"noise: frames of {frames.data.shape[2]} x {frames.data.shape[1]} for events of "
            f"a {w} x {h} sensor"
        )
    return frames


def _span(events: Events, frames: Frames | None, duration_us: int | None) -> tuple[int, int]:
    """[t0, t1) in us: the recording's span."""
    t0 = int(events.t[0])
    t1 = int(events.t[-1]) + 1
    if frames is not None:
        t0 = min(t0, int(frames.t[0]))
        t1 = max(t1, int(frames.t[-1] + frames.exposure_us[-1]))
    if duration_us is not None:
        if duration_us <= 0:
            raise InputError(f"noise: duration_us must be positive, got {duration_us}")
        t1 = t0 + int(duration_us)
    return t0, max(t1, t0 + 1)


def _mask(a: np.ndarray, w: int, h: int, name: str) -> np.ndarray:
    a = np.asarray(a)
    if a.shape != (h, w):
        raise InputError(f"{name} must be a {h} x {w} mask, got shape {a.shape}")
    return a.astype(bool)
