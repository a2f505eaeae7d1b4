"""Per-pixel ON and OFF contrast thresholds, from the APS frames and the events between them.

The DVS pixel fires ON when its log intensity L has risen by C_on(x) above its reference
level, which then moves up by C_on (OFF likewise, with C_off). The APS value A is linear in the
intensity, so at the mid-exposure time of frame k

    log A_k = b + L_k = b + ref_k + e_k,    ref_k = ref_0 + C_on N_on(k) - C_off N_off(k)

with N_on(k), N_off(k) the pixel's events before frame k and e_k = L_k - ref_k, which stays
within (-C_off, C_on): the reference tracks L, so e does not random-walk and a fit of the
cumulative log change against the cumulative counts is far more precise than one of
frame-to-frame pairs. e is not centred either: right after an ON event it is 0 and grows
towards C_on, right after an OFF event it is 0 and falls towards -C_off. Taking its mean
after an ON event as C_on/2 (after an OFF event -C_off/2) is the ``hysteresis`` term below;
without it a pixel that alternates between dark and bright shows a larger log range than its
counts explain, and the thresholds come out about 10 % high (simulated ChArUco session). C/2
holds where the signal has plateaus between changes (edges passing, as over a board); a
smooth oscillation spends longer at its turning points, where e goes back below 0, and there
the thresholds come out up to 5 % low.

The fit, per pixel, vectorised over all pixels (no loop per pixel):

    log A_k = b_s + C_on (N_on(k) + h [last event ON]) - C_off (N_off(k) + h [last event OFF])

- Frames where the pixel is too dark (shot and read noise dominate) or saturated are left out.
- A pixel loses events when it is asked to fire faster than its refractory period allows
  (its reference still moves), and the lost counts would corrupt every later cumulative
  point. Intervals between frames that hold two events of the pixel closer than
  ``lossy_factor`` refractory periods are therefore cut out, as are invalid frames: the
  frames form segments, each with its own intercept b_s.
- Weighted least squares (APS shot and read noise plus the spread of e) made robust by
  iteratively reweighted Huber weights; then, per pixel, the posterior with a prior of the
  pixel's Bayer channel (its robust mean over the confidently fitted pixels and the spread
  of the thresholds around it), solved within the bounds. A pixel with too little data of a
  polarity takes the channel's mean for it.
- Confidence (per polarity) 1 / (1 + (se / se_half)^2) from the standard error se of the fit:
  at least 0.5 when se <= se_half. On the simulated ChArUco session (2 s, 50 frames) 20 % of
  the pixels have confidence >= 0.5 and their thresholds are within 0.008-0.009 (RMS) of the
  truth; frame-to-frame pairs fitted the same way give 9 % of the pixels at 0.010.

Times are microseconds; thresholds are in log units (natural log).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from evcap.calib.noise import refractory_period
from evcap.errors import CalibrationError, InputError
from evcap.events import Channel, Events, check_color_filter, pixel_channels
from evcap.streams import Frames

__all__ = ["DATASHEET_THRESHOLDS", "ThresholdConfig", "ThresholdFit", "fit_thresholds"]

DATASHEET_THRESHOLDS = (float(np.log(1.143)), float(np.log(1.225)))
"""(ON, OFF) of the Color-DAVIS346's datasheet (14.3 % and 22.5 % contrast at 50 % of pixels
responding): the channel means when not a single pixel can be fitted."""

_BLOCK = 1 << 20  # frames x pixels handled at a time (bounded memory for long recordings)


@dataclass(frozen=True)
class ThresholdConfig:
    """How the thresholds are fitted."""

    dark_dn: float = 20.0  # APS values (above black) below this: frame not used
    saturated_dn: float = 1000.0  # raw APS values from this up: frame not used
    black_dn: float = 0.0  # APS black level, subtracted before the log
    aps_gain_dn: float = 1.0  # DN per photo-electron (shot noise variance = gain * value)
    read_noise_dn: float = 2.0  # APS read noise, DN
    e_sigma: float = 0.06  # spread of L - reference about its mean, log units (~C / sqrt 12)
    hysteresis: float = 0.5  # mean of L - reference after an event, in thresholds
    lossy_factor: float = 1.5  # intervals with two events closer than this many refractory
    # periods may have lost events: cut out
    bounds: tuple[float, float] = (0.02, 1.5)  # log units, for both polarities
    min_events: int = 5  # events of a polarity inside the pixel's segments, at least
    min_dof: int = 3  # frames inside segments less segments less 2, at least
    min_decorrelation: float = 0.1  # 1 - corr^2 of ON and OFF counts: below, collinear
    huber_k: float = 1.345  # Huber's tuning constant, in robust standard deviations
    scale_floor: float = 0.7  # robust residual scale at least this (in noise-model units)
    iterations: int = 5  # reweighting passes
    se_half: float = 0.01  # standard error (log units) at which the confidence is 0.5
    min_channel_pixels: int = 10  # confident pixels a channel needs for its own mean
    spread_floor: float = 0.005  # smallest spread of the thresholds about the channel mean


@dataclass(frozen=True)
class ThresholdFit:
    """Per-pixel thresholds, how well each is known, and what the fit rests on."""

    on: np.ndarray  # [H, W] float32, log units
    off: np.ndarray  # [H, W] float32, log units
    confidence: np.ndarray  # [H, W] float32 in [0, 1]; >= 0.5: a good fit (both polarities)
    fallback: np.ndarray  # [H, W] bool: the channel mean is used for ON or OFF (or both)
    channel_means: dict[str, tuple[float, float]]  # channel name -> (ON, OFF), log units
    residual_std: float  # robust std of the fit's residuals (log units), median over pixels
    confidence_on: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.float32))
    confidence_off: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.float32))
    se_on: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.float32))  # [H, W]
    se_off: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.float32))
    channel_spread: dict[str, tuple[float, float]] = field(default_factory=dict)  # mismatch
    channel_pixels: dict[str, int] = field(default_factory=dict)  # confident fits per channel
    events_used: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 2), np.int32))
    # [H, W, 2]: ON and OFF events inside the pixel's segments
    frames_used: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.int16))
    confident_share: float = 0.0  # share of the pixels (not excluded) with confidence >= 0.5
    refractory_us: float = 0.0  # the refractory period the lossy intervals were found with
    lossy_share: float = 0.0  # share of pixel intervals with events that were cut out
    notes: tuple[str, ...] = ()  # what limited the fit, for a person


def fit_thresholds(
    events: Events,
    frames: Frames,
    color_filter: str,
    *,
    exclude: np.ndarray | None = None,
    refractory_us: float | None = None,
    config: ThresholdConfig = ThresholdConfig(),
    progress: Callable[[int, int], None] | None = None,
) -> ThresholdFit:
    """Fit each pixel's ON and OFF thresholds from the APS ``frames`` and the ``events``.

    ``exclude``: [H, W] bool pixels not to fit (hot pixels); they take their channel's mean.
    ``refractory_us``: the sensor's refractory period (default: measured from the events).
    ``progress(done, total)`` is called as the fit goes. Raises CalibrationError when there
    are fewer than 3 frames or no events.
    """
    check_color_filter(color_filter)
    w, h = events.width, events.height
    if len(frames) < 3:
        raise CalibrationError(
            f"thresholds: {len(frames)} APS frame(s); the fit needs at least 3 "
            "(record with APS frames on, the camera moving over a textured scene)"
        )
    if frames.data.shape[1:] != (h, w):
        raise CalibrationError(
            f"thresholds: frames of {frames.data.shape[2]} x {frames.data.shape[1]} for events "
            f"of a {w} x {h} sensor; use the frames and events of one recording"
        )
    skip = np.zeros((h, w), bool)
    if exclude is not None:
        skip = np.asarray(exclude)
        if skip.shape != (h, w):
            raise InputError(f"thresholds: exclude must be a {h} x {w} mask, got {skip.shape}")
        skip = skip.astype(bool)
    pix = events.y.astype(np.int64) * w + events.x
    kept = ~skip.ravel()[pix]
    if not kept.any():
        raise CalibrationError(
            "thresholds: no events (outside the excluded pixels); record with the DVS on, "
            "the camera moving over a textured scene"
        )
    c = config
    notes: list[str] = []
    if refractory_us is None:
        refractory_us = refractory_period(events, exclude=skip)
    lossy_us = c.lossy_factor * max(float(refractory_us), 0.0)

    # events sorted by pixel (and by time within a pixel), blocks of whole rows
    order = np.argsort(pix[kept], kind="stable")
    ev_pix = pix[kept][order]
    ev_t = events.t[kept][order]
    ev_p = events.p[kept][order]
    n = len(frames)
    # mid-exposure times (kept in order should exposures vary), and the exposure's share of
    # log A: the APS value is proportional to the exposure time
    mid = np.maximum.accumulate(frames.t + frames.exposure_us / 2.0)
    log_exposure = np.log(np.maximum(frames.exposure_us, 1).astype(np.float64))
    rows = max(1, _BLOCK // (n * w))
    starts = list(range(0, h, rows))
    stats = _empty_stats(h * w)
    lossy_cut = lossy_all = 0
    for i, r0 in enumerate(starts):
        r1 = min(h, r0 + rows)
        p0, p1 = r0 * w, r1 * w
        a, b = np.searchsorted(ev_pix, [p0, p1])
        block = _Block(
            frames.data[:, r0:r1].reshape(n, p1 - p0),
            frames.exposure_us > 0,
            log_exposure,
            mid,
            ev_pix[a:b] - p0,
            ev_t[a:b],
            ev_p[a:b],
            lossy_us,
            c,
        )
        lossy_cut += block.lossy_cut
        lossy_all += block.lossy_all
        for name, value in block.fit(c).items():
            stats[name][p0:p1] = value
        if progress is not None:
            progress(i + 1, len(starts) + 1)
    stats["skip"] = skip.ravel()

    yy, xx = np.divmod(np.arange(h * w), w)
    channels = pixel_channels(xx, yy, color_filter)
    result = _finish(stats, channels, c, notes)
    if progress is not None:
        progress(len(starts) + 1, len(starts) + 1)
    free = ~skip
    confident = result["confidence"] >= 0.5
    return ThresholdFit(
        on=result["on"].reshape(h, w).astype(np.float32),
        off=result["off"].reshape(h, w).astype(np.float32),
        confidence=result["confidence"].reshape(h, w).astype(np.float32),
        fallback=result["fallback"].reshape(h, w),
        channel_means=result["channel_means"],
        residual_std=result["residual_std"],
        confidence_on=result["confidence_on"].reshape(h, w).astype(np.float32),
        confidence_off=result["confidence_off"].reshape(h, w).astype(np.float32),
        se_on=result["se_on"].reshape(h, w).astype(np.float32),
        se_off=result["se_off"].reshape(h, w).astype(np.float32),
        channel_spread=result["channel_spread"],
        channel_pixels=result["channel_pixels"],
        events_used=np.stack([stats["n_on"], stats["n_off"]], -1).astype(np.int32).reshape(h, w, 2),
        frames_used=np.minimum(stats["frames"], np.iinfo(np.int16).max)
        .astype(np.int16)
        .reshape(h, w),
        confident_share=float(confident.reshape(h, w)[free].mean()) if free.any() else 0.0,
        refractory_us=float(refractory_us),
        lossy_share=lossy_cut / lossy_all if lossy_all else 0.0,
        notes=tuple(notes),
    )


# -- one block of pixels: the data and the robust fit ----------------------------------------


class _Block:
    """The design of the fit for a block of pixels: [frames, pixels] arrays."""

    def __init__(
        self, data, exposed, log_exposure, mid, lp, t, p, lossy_us, c: ThresholdConfig
    ) -> None:
        n, m = data.shape
        # interval k (k = 1..n-1) holds the events between the mid-exposures of frames k-1, k
        k = np.searchsorted(mid, t, "right")
        key = lp * (n + 1) + k  # non-decreasing: events are sorted by pixel, then time
        on, off = p == 1, p == 0
        size = (n + 1) * m
        per_bin_on = np.bincount(key[on], minlength=size).reshape(m, n + 1).T
        per_bin_off = np.bincount(key[off], minlength=size).reshape(m, n + 1).T
        n_on = np.cumsum(per_bin_on, 0)[:n].astype(np.float64)  # events before frame k
        n_off = np.cumsum(per_bin_off, 0)[:n].astype(np.float64)
        # the polarity of the last event before each frame (-1: none yet)
        last_of_run = np.r_[key[1:] != key[:-1], True] if key.size else np.zeros(0, bool)
        last_p = np.full((n + 1) * m, -1, np.int8)
        last_p[key[last_of_run]] = p[last_of_run]
        last_p = last_p.reshape(m, n + 1).T
        where = np.where(last_p >= 0, np.arange(n + 1)[:, None], -1)
        where = np.maximum.accumulate(where, axis=0)[:n]
        last = np.where(where >= 0, last_p[np.maximum(where, 0), np.arange(m)], -1)
        # intervals in which the pixel may have lost events to its refractory period
        lossy = np.zeros((n + 1) * m, bool)
        if lossy_us > 0 and key.size > 1:
            close = (lp[1:] == lp[:-1]) & (t[1:] - t[:-1] < lossy_us)
            lossy[key[1:][close]] = True
            lossy[key[:-1][close]] = True
        lossy = lossy.reshape(m, n + 1).T[:n]
        # usable frames, and segments: runs of usable frames not broken by a lossy interval
        a = data.astype(np.float64) - c.black_dn
        valid = (a >= c.dark_dn) & (data < c.saturated_dn) & exposed[:, None]
        start = valid.copy()
        start[1:] &= ~valid[:-1] | lossy[1:]
        inside = valid & ~start  # frame k continues the segment of frame k-1
        moved = (per_bin_on + per_bin_off)[1:n] > 0
        self.lossy_all = int((moved & valid[1:] & valid[:-1]).sum())
        self.lossy_cut = int((moved & valid[1:] & valid[:-1] & lossy[1:]).sum())
        seg = np.cumsum(start, 0) - 1
        self.key = (np.arange(m)[None, :] * n + np.maximum(seg, 0)).ravel()
        self.shape = (n, m)
        a = np.maximum(a, 1.0)
        self.y = np.log(a) - log_exposure[:, None]
        self.w0 = np.where(valid, 1.0 / (c.aps_gain_dn / a + (c.read_noise_dn / a) ** 2), 0.0)
        self.w0 = np.where(valid, 1.0 / (1.0 / np.maximum(self.w0, 1e-30) + c.e_sigma**2), 0.0)
        self.n_on, self.n_off = n_on, n_off
        self.s_on = (last == 1).astype(np.float64)
        self.s_off = (last == 0).astype(np.float64)
        self.set_hysteresis(c.hysteresis, c.hysteresis)
        # entries that inform the fit: frames in segments of two frames or more
        seg_len = np.bincount(self.key, valid.ravel(), n * m)
        self.used = valid & (seg_len[self.key].reshape(n, m) >= 2)
        self.n_segments = (seg_len.reshape(m, n) >= 2).sum(1)
        self.n_on_used = (np.diff(n_on, axis=0) * inside[1:]).sum(0)
        self.n_off_used = (np.diff(n_off, axis=0) * inside[1:]).sum(0)

    def set_hysteresis(self, h_on: float, h_off: float) -> None:
        """The regressors: counts plus the mean of L - reference after the last event."""
        self.x_on = self.n_on + h_on * self.s_on
        self.x_off = self.n_off + h_off * self.s_off

    def _demeaned(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """y, x_on, x_off less their weighted mean over each segment."""
        n, m = self.shape
        total = np.bincount(self.key, w.ravel(), n * m)
        total = np.maximum(total, 1e-300)
        out = []
        for v in (self.y, self.x_on, self.x_off):
            mean = np.bincount(self.key, (w * v).ravel(), n * m) / total
            out.append(v - mean[self.key].reshape(n, m))
        return out[0], out[1], out[2]

    def fit(self, c: ThresholdConfig) -> dict[str, np.ndarray]:
        """Robust (Huber) weighted least squares; returns the per-pixel normal equations
        (in noise-model units), the residual scale and the counts."""
        used = self.used
        w = np.where(used, self.w0, 0.0)
        lo, hi = c.bounds
        for it in range(c.iterations):
            yd, xo, xf = self._demeaned(w)
            q11 = (w * xo * xo).sum(0)
            q12 = -(w * xo * xf).sum(0)  # the unknowns are (C_on, C_off): x_off enters as -x
            q22 = (w * xf * xf).sum(0)
            g1 = (w * xo * yd).sum(0)
            g2 = -(w * xf * yd).sum(0)
            ridge = 1e-9 * (q11 + q22) + 1e-12
            c_on, c_off = _box_qp(q11 + ridge, q12, q22 + ridge, g1, g2, lo, hi)
            r = yd - xo * c_on + xf * c_off
            z = r * np.sqrt(self.w0)
            scale = np.maximum(1.4826 * _masked_median(np.abs(z), used), c.scale_floor)
            if it < c.iterations - 1:
                u = np.abs(z) / scale
                w = np.where(used, self.w0 * np.minimum(1.0, c.huber_k / np.maximum(u, 1e-12)), 0)
        return {
            "q11": q11,
            "q12": q12,
            "q22": q22,
            "g1": g1,
            "g2": g2,
            "scale2": scale**2,
            "dof": used.sum(0) - self.n_segments - 2,
            "n_on": self.n_on_used.astype(np.int32),
            "n_off": self.n_off_used.astype(np.int32),
            "frames": used.sum(0),
            "resid": 1.4826 * _masked_median(np.abs(r), used),
        }


def _masked_median(a: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Median over axis 0 of the entries where ``mask``; 0 where a column has none."""
    s = np.sort(np.where(mask, a, np.inf), axis=0)
    k = mask.sum(0)
    cols = np.arange(a.shape[1])
    lo = s[np.maximum((k - 1) // 2, 0), cols]
    hi = s[np.maximum(k // 2, 0), cols]
    return np.where(k > 0, 0.5 * (lo + hi), 0.0)


def _box_qp(q11, q12, q22, g1, g2, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
    """Minimise 1/2 x'Qx - g'x over lo <= x1, x2 <= hi, for positive definite 2 x 2 Q
    (vectorised): the interior optimum where it is inside, else the best edge optimum."""
    det = q11 * q22 - q12 * q12
    with np.errstate(divide="ignore", invalid="ignore"):
        x1 = (q22 * g1 - q12 * g2) / det
        x2 = (q11 * g2 - q12 * g1) / det
    inside = (det > 0) & (x1 >= lo) & (x1 <= hi) & (x2 >= lo) & (x2 <= hi)
    best1 = np.where(inside, x1, lo)
    best2 = np.where(inside, x2, lo)
    best = np.where(inside, _objective(q11, q12, q22, g1, g2, best1, best2), np.inf)
    for edge in (lo, hi):
        # x1 on an edge, x2 at its clipped 1-D optimum; then the other way round
        for a1, a2 in (
            (np.full_like(g1, edge), np.clip((g2 - q12 * edge) / q22, lo, hi)),
            (np.clip((g1 - q12 * edge) / q11, lo, hi), np.full_like(g2, edge)),
        ):
            f = _objective(q11, q12, q22, g1, g2, a1, a2)
            better = f < best
            best = np.where(better, f, best)
            best1 = np.where(better, a1, best1)
            best2 = np.where(better, a2, best2)
    return best1, best2


def _objective(q11, q12, q22, g1, g2, x1, x2) -> np.ndarray:
    return 0.5 * (q11 * x1 * x1 + 2 * q12 * x1 * x2 + q22 * x2 * x2) - g1 * x1 - g2 * x2


# -- all pixels: channel means, the posterior per pixel, confidence --------------------------


def _empty_stats(size: int) -> dict[str, np.ndarray]:
    names = ("q11", "q12", "q22", "g1", "g2", "scale2", "resid")
    stats = {name: np.zeros(size) for name in names}
    stats["scale2"][:] = 1.0
    for name in ("dof", "n_on", "n_off", "frames"):
        stats[name] = np.zeros(size, np.int64)
    return stats


def _finish(s: dict[str, np.ndarray], channels: np.ndarray, c: ThresholdConfig, notes) -> dict:
    """From every pixel's normal equations: which polarities have data, the channel priors,
    each pixel's posterior within the bounds, its standard error and confidence."""
    lo, hi = c.bounds
    usable = ~s["skip"] & (s["dof"] >= c.min_dof)
    info_on = usable & (s["n_on"] >= c.min_events)
    info_off = usable & (s["n_off"] >= c.min_events)
    # data alone (no prior): normal equations scaled by the residual variance
    scale2 = np.maximum(s["scale2"], 1e-12)
    q11, q12, q22 = s["q11"] / scale2, s["q12"] / scale2, s["q22"] / scale2
    g1, g2 = s["g1"] / scale2, s["g2"] / scale2
    det = q11 * q22 - q12 * q12
    with np.errstate(divide="ignore", invalid="ignore"):
        decorrelation = np.where((q11 > 0) & (q22 > 0), det / (q11 * q22), 0.0)
        se_on = np.sqrt(np.where(det > 0, q22 / det, np.inf))
        se_off = np.sqrt(np.where(det > 0, q11 / det, np.inf))
    ridge = 1e-9 * (q11 + q22) + 1e-12
    raw_on, raw_off = _box_qp(q11 + ridge, q12, q22 + ridge, g1, g2, lo, hi)
    # a fit that ends on a bound: events that do not match the frames' log change (a hot,
    # flickering or noisy pixel, a frame artefact): its data are not used
    at_on = info_on & ((raw_on <= lo * 1.0001) | (raw_on >= hi * 0.9999))
    at_off = info_off & ((raw_off <= lo * 1.0001) | (raw_off >= hi * 0.9999))
    if (at_on | at_off).any():
        notes.append(
            f"{int((at_on | at_off).sum())} pixels fit a threshold at the bounds {c.bounds} "
            "(their events do not match the log change of the frames: hot, flickering or "
            "noisy pixels); they take the channel mean"
        )
    info_on &= ~at_on
    info_off &= ~at_off
    good = (
        info_on
        & info_off
        & (decorrelation >= c.min_decorrelation)
        & (se_on <= c.se_half)
        & (se_off <= c.se_half)
    )

    # channel priors: robust mean and spread of the confident fits
    names, mean_on, mean_off, spread_on, spread_off, counts = {}, {}, {}, {}, {}, {}
    pooled = _robust_prior(raw_on[good], raw_off[good], se_on[good], se_off[good], c)
    if pooled is None:
        notes.append(
            "no pixel could be fitted with confidence: the datasheet thresholds are used "
            "(record the camera moving over a high-contrast scene, in good light)"
        )
        pooled = (*DATASHEET_THRESHOLDS, 0.05, 0.05)
    for ch in np.unique(channels):
        name = Channel(int(ch)).name
        sel = good & (channels == ch)
        prior = None
        if sel.sum() >= c.min_channel_pixels:
            prior = _robust_prior(raw_on[sel], raw_off[sel], se_on[sel], se_off[sel], c)
        elif (channels == ch).any() and good.any():
            notes.append(f"channel {name}: {int(sel.sum())} confident pixels; pooled mean used")
        mean_on[ch], mean_off[ch], spread_on[ch], spread_off[ch] = prior or pooled
        names[ch] = name
        counts[name] = int(sel.sum())
    m_on = np.zeros(channels.size)
    m_off = np.zeros(channels.size)
    v_on = np.ones(channels.size)
    v_off = np.ones(channels.size)
    for ch in names:
        at = channels == ch
        m_on[at], m_off[at] = mean_on[ch], mean_off[ch]
        v_on[at], v_off[at] = spread_on[ch] ** 2, spread_off[ch] ** 2

    # posterior: the data (where a polarity has data) and the channel prior
    d11 = np.where(info_on, q11, 0.0)
    d22 = np.where(info_off, q22, 0.0)
    d12 = np.where(info_on & info_off, q12, 0.0)
    e1 = np.where(info_on, g1 - np.where(info_off, 0.0, q12 * m_off), 0.0)
    e2 = np.where(info_off, g2 - np.where(info_on, 0.0, q12 * m_on), 0.0)
    p11, p22 = d11 + 1.0 / v_on, d22 + 1.0 / v_off
    on, off = _box_qp(p11, d12, p22, e1 + m_on / v_on, e2 + m_off / v_off, lo, hi)
    post_det = p11 * p22 - d12 * d12
    post_se_on = np.sqrt(p22 / post_det)
    post_se_off = np.sqrt(p11 / post_det)
    conf_on = np.where(info_on, 1.0 / (1.0 + (post_se_on / c.se_half) ** 2), 0.0)
    conf_off = np.where(info_off, 1.0 / (1.0 + (post_se_off / c.se_half) ** 2), 0.0)
    # a fit in which ON and OFF cannot be told apart is not trusted
    doubtful = info_on & info_off & (decorrelation < c.min_decorrelation)
    conf_on = np.where(doubtful, np.minimum(conf_on, 0.25), conf_on)
    conf_off = np.where(doubtful, np.minimum(conf_off, 0.25), conf_off)
    on = np.where(info_on, on, m_on)
    off = np.where(info_off, off, m_off)
    fitted = info_on | info_off
    residual = float(np.median(s["resid"][fitted])) if fitted.any() else 0.0
    return {
        "on": _finite(on, m_on),
        "off": _finite(off, m_off),
        "confidence": _finite(np.minimum(conf_on, conf_off), 0.0),
        "confidence_on": _finite(conf_on, 0.0),
        "confidence_off": _finite(conf_off, 0.0),
        "fallback": ~(info_on & info_off),
        "se_on": _finite(np.where(info_on, post_se_on, np.sqrt(v_on)), 1.0),
        "se_off": _finite(np.where(info_off, post_se_off, np.sqrt(v_off)), 1.0),
        "channel_means": {names[ch]: (float(mean_on[ch]), float(mean_off[ch])) for ch in names},
        "channel_spread": {
            names[ch]: (float(spread_on[ch]), float(spread_off[ch])) for ch in names
        },
        "channel_pixels": counts,
        "residual_std": residual if np.isfinite(residual) else 0.0,
    }


def _robust_prior(on, off, se_on, se_off, c: ThresholdConfig):
    """(mean ON, mean OFF, spread ON, spread OFF) of confident fits, or None if too few."""
    if on.size < 3:
        return None
    out = []
    for values, se in ((on, se_on), (off, se_off)):
        mean, sd = _huber_mean(values)
        spread = np.sqrt(max(sd**2 - float(np.mean(se**2)), c.spread_floor**2))
        out.append((mean, spread))
    return out[0][0], out[1][0], out[0][1], out[1][1]


def _huber_mean(values: np.ndarray, k: float = 1.5) -> tuple[float, float]:
    """(Huber M-estimate of the mean, robust standard deviation from the MAD)."""
    mean = float(np.median(values))
    sd = 1.4826 * float(np.median(np.abs(values - mean)))
    if sd <= 0:
        return mean, 0.0
    for _ in range(20):
        u = (values - mean) / sd
        w = np.minimum(1.0, k / np.maximum(np.abs(u), 1e-12))
        new = float(np.sum(w * values) / np.sum(w))
        if abs(new - mean) < 1e-7:
            break
        mean = new
    return mean, sd


def _finite(a: np.ndarray, fill) -> np.ndarray:
    return np.where(np.isfinite(a), a, fill)
