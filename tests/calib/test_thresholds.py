"""Per-pixel contrast thresholds from APS frames vs events, on a small pixel model of this
file's own: per-pixel log signals, thresholds with spread, events from threshold crossings
(with a refractory period that loses events), APS frames from the same signals."""

from dataclasses import dataclass

import numpy as np
import pytest

from evcap.calib.thresholds import (
    DATASHEET_THRESHOLDS,
    ThresholdConfig,
    _box_qp,
    fit_thresholds,
)
from evcap.errors import CalibrationError, InputError
from evcap.events import Events
from evcap.streams import Frames

H, W = 24, 32
FPS, EXPOSURE_US = 25, 4000
GAIN = 200.0  # DN per unit of intensity per millisecond of exposure


@dataclass
class Recording:
    events: Events
    frames: Frames
    on: np.ndarray  # [H, W] true thresholds
    off: np.ndarray


def _signal(t_s, base, amp, freq, phase, sharp):
    """[T, P] log intensity: a slow wave sharpened into edges with plateaus between them (as
    a pixel sees when the camera moves over a board); smaller ``sharp``: smoother."""
    wave = np.sin(2 * np.pi * freq * t_s[:, None] + phase)
    wave = np.tanh(sharp * wave) / np.tanh(sharp)
    return base + amp * wave


def _crossings(t_us, log_i, on, off):
    """Events of every pixel for log intensity sampled at ``t_us`` ([T] floats, [T, P]):
    a reference per pixel, moved by one threshold at each crossing, crossing times by linear
    interpolation. Returns (t, pixel, polarity) sorted by time."""
    ref = log_i[0].copy()
    out_t, out_px, out_p = [], [], []
    for i in range(1, len(t_us)):
        a, b = log_i[i - 1], log_i[i]
        rising = b > a
        k_on = np.where(rising, np.floor((b - ref) / on), 0).clip(0).astype(np.int64)
        k_off = np.where(~rising, np.floor((ref - b) / off), 0).clip(0).astype(np.int64)
        for k, step, pol in ((k_on, on, 1), (k_off, -off, 0)):
            px = np.repeat(np.arange(ref.size), k)
            if px.size == 0:
                continue
            j = np.arange(px.size) - np.repeat(np.cumsum(k) - k, k) + 1  # 1..k per pixel
            level = ref[px] + j * step[px]
            frac = (level - a[px]) / (b[px] - a[px])
            out_t.append(t_us[i - 1] + frac * (t_us[i] - t_us[i - 1]))
            out_px.append(px)
            out_p.append(np.full(px.size, pol, np.uint8))
            ref = ref + k * step
    t = np.concatenate(out_t)
    order = np.argsort(t, kind="stable")
    return t[order], np.concatenate(out_px)[order], np.concatenate(out_p)[order]


def _refractory(t, px, period_us):
    """Drop each event within ``period_us`` of the pixel's last kept event (the reference
    has moved all the same, as in a DVS pixel)."""
    keep = np.ones(t.size, bool)
    last = {}
    for i in range(t.size):
        p = px[i]
        if p in last and t[i] - last[p] < period_us:
            keep[i] = False
        else:
            last[p] = t[i]
    return keep


def make_recording(
    seed=0,
    duration_s=2.0,
    sharp=4.0,
    refractory_us=0.0,
    flat=(),
    flicker=(),
    spread=0.03,
    auto_exposure=False,
) -> Recording:
    """A recording of the pixel model. ``flat``: pixels (flat indices) with a constant signal;
    ``flicker``: pixels that oscillate much faster than the frames (ON and OFF counts then
    grow together: collinear)."""
    rng = np.random.default_rng(seed)
    n_px = H * W
    on = np.maximum(rng.normal(0.2, spread, n_px), 0.05)
    off = np.maximum(rng.normal(0.2, spread, n_px), 0.05)
    base = rng.uniform(np.log(0.15), np.log(0.6), n_px)  # APS between about 60 and 1000 DN
    amp = rng.uniform(0.6, 1.2, n_px)
    freq = rng.uniform(0.7, 2.5, n_px)
    phase = rng.uniform(0, 2 * np.pi, n_px)
    step_us = 100.0
    t_us = np.arange(0.0, duration_s * 1e6 + step_us, step_us)
    log_i = _signal(t_us * 1e-6, base, amp, freq, phase, sharp)
    flat, flicker = np.asarray(flat, np.int64), np.asarray(flicker, np.int64)
    log_i[:, flat] = base[flat]
    if flicker.size:
        log_i[:, flicker] = base[flicker] + 0.5 * np.sin(
            2 * np.pi * 137.0 * t_us[:, None] * 1e-6 + phase[flicker]
        )
    t, px, p = _crossings(t_us, log_i, on, off)
    if refractory_us > 0:
        keep = _refractory(t, px, refractory_us)
        t, px, p = t[keep], px[keep], p[keep]
    events = Events(px % W, px // W, np.floor(t).astype(np.int64), p, W, H, "RGBG")
    # APS: the intensity averaged over the exposure, shot and read noise, 10 bits
    starts = np.arange(0, duration_s * 1e6 - EXPOSURE_US, 1e6 / FPS)
    exposure = np.full(len(starts), EXPOSURE_US)
    if auto_exposure:  # the exposure changes from frame to frame (an auto-exposure)
        exposure = np.round(EXPOSURE_US * rng.uniform(0.4, 1.0, len(starts))).astype(np.int64)
    data = []
    for s, e in zip(starts, exposure, strict=True):
        ts = (s + (np.arange(8) + 0.5) * e / 8) * 1e-6
        li = _signal(ts, base, amp, freq, phase, sharp)
        li[:, flat] = base[flat]
        if flicker.size:
            li[:, flicker] = base[flicker] + 0.5 * np.sin(
                2 * np.pi * 137.0 * ts[:, None] + phase[flicker]
            )
        mean = np.exp(li).mean(0)
        value = rng.poisson(GAIN * mean * e / 1000) + rng.normal(0, 2.0, n_px)
        data.append(np.clip(np.round(value), 0, 1023).reshape(H, W))
    frames = Frames(
        np.array(data, np.uint16),
        starts.astype(np.int64),
        exposure,
    )
    return Recording(events, frames, on.reshape(H, W), off.reshape(H, W))


@pytest.fixture(scope="module")
def smooth():
    return make_recording(seed=1)


@pytest.fixture(scope="module")
def lossy():
    # sharp edges: pixels are asked to fire faster than every 2 ms and lose events
    return make_recording(seed=2, sharp=12.0, refractory_us=2000.0)


def _rmse(fit, rec, mask):
    return (
        float(np.sqrt(np.mean((fit.on - rec.on)[mask] ** 2))),
        float(np.sqrt(np.mean((fit.off - rec.off)[mask] ** 2))),
    )


def _all_finite(fit):
    arrays = (fit.on, fit.off, fit.confidence, fit.confidence_on, fit.confidence_off)
    assert all(np.isfinite(a).all() for a in arrays + (fit.se_on, fit.se_off))
    assert np.isfinite(fit.residual_std)
    assert all(np.isfinite(v).all() for v in fit.channel_means.values())
    assert ((fit.confidence >= 0) & (fit.confidence <= 1)).all()


def test_recovers_per_pixel_thresholds(smooth):
    fit = fit_thresholds(smooth.events, smooth.frames, "RGBG", refractory_us=0.0)
    _all_finite(fit)
    good = fit.confidence >= 0.5
    assert good.mean() > 0.5
    rmse_on, rmse_off = _rmse(fit, smooth, good)
    assert rmse_on < 0.02 and rmse_off < 0.02
    # the per-pixel maps know more than the channel means: the spread (0.03) is resolved
    assert rmse_on < 0.6 * smooth.on[good].std()
    for name in ("RED", "GREEN", "BLUE"):
        on, off = fit.channel_means[name]
        assert abs(on - 0.2) < 0.01 and abs(off - 0.2) < 0.01
        assert 0.015 < fit.channel_spread[name][0] < 0.05
    assert abs(fit.confident_share - good.mean()) < 1e-9
    assert 0.01 < fit.residual_std < 0.3


def test_the_hysteresis_term_removes_a_bias(smooth):
    # without it the log range a pixel shows exceeds what its counts explain
    fit = fit_thresholds(smooth.events, smooth.frames, "RGBG", refractory_us=0.0)
    plain = fit_thresholds(
        smooth.events,
        smooth.frames,
        "RGBG",
        refractory_us=0.0,
        config=ThresholdConfig(hysteresis=0),
    )
    good = (fit.confidence >= 0.5) & (plain.confidence >= 0.5)
    bias = float(np.mean((fit.on - smooth.on)[good]))
    plain_bias = float(np.mean((plain.on - smooth.on)[good]))
    assert abs(bias) < 0.005
    assert plain_bias > 0.01


def test_frames_of_varying_exposure():
    rec = make_recording(seed=5, auto_exposure=True)
    fit = fit_thresholds(rec.events, rec.frames, "RGBG", refractory_us=0.0)
    good = fit.confidence >= 0.5
    assert good.mean() > 0.5
    assert max(_rmse(fit, rec, good)) < 0.02


def test_events_lost_to_the_refractory_period_are_cut_out(lossy):
    rec = lossy
    fit = fit_thresholds(rec.events, rec.frames, "RGBG", refractory_us=2000.0)
    _all_finite(fit)
    assert fit.lossy_share > 0.1
    good = fit.confidence >= 0.5
    assert good.mean() > 0.1
    assert max(_rmse(fit, rec, good)) < 0.02
    # the same fit keeping the lossy intervals overestimates the thresholds
    naive = fit_thresholds(rec.events, rec.frames, "RGBG", refractory_us=0.0)
    keep = naive.confidence >= 0.5
    assert float(np.mean((naive.on - rec.on)[keep])) > 0.01


def test_refractory_period_measured_when_not_given(lossy):
    rec = lossy
    fit = fit_thresholds(rec.events, rec.frames, "RGBG")
    assert 1900 <= fit.refractory_us <= 2300
    good = fit.confidence >= 0.5
    assert max(_rmse(fit, rec, good)) < 0.02


def test_pixels_without_data_take_the_channel_mean():
    flat = np.arange(0, H * W, 7)
    flicker = np.arange(3, H * W, 11)
    flicker = flicker[~np.isin(flicker, flat)]
    rec = make_recording(seed=3, flat=flat, flicker=flicker)
    exclude = np.zeros((H, W), bool)
    exclude[5, 6] = exclude[10, 11] = True
    fit = fit_thresholds(rec.events, rec.frames, "RGBG", exclude=exclude, refractory_us=0.0)
    _all_finite(fit)
    channels = {0: "RED", 1: "GREEN", 2: "GREEN", 3: "BLUE"}
    for i in flat:
        y, x = divmod(int(i), W)
        name = channels[(x & 1) | ((y & 1) << 1)]
        assert fit.fallback[y, x]
        assert fit.confidence[y, x] == 0
        assert fit.on[y, x] == pytest.approx(fit.channel_means[name][0], abs=1e-6)
        assert fit.off[y, x] == pytest.approx(fit.channel_means[name][1], abs=1e-6)
    # ON and OFF counts that grow together cannot be told apart: not confident
    ys, xs = np.divmod(flicker, W)
    assert (fit.confidence[ys, xs] < 0.5).all()
    assert ((fit.on[ys, xs] >= 0.02) & (fit.on[ys, xs] <= 1.5)).all()
    # excluded pixels are not fitted
    assert fit.fallback[exclude].all() and (fit.confidence[exclude] == 0).all()
    # the others are still fitted well
    good = fit.confidence >= 0.5
    assert good.mean() > 0.3
    assert max(_rmse(fit, rec, good)) < 0.02


@pytest.mark.parametrize("value", [0, 5, 1023])
def test_black_or_saturated_frames_give_the_datasheet_values(smooth, value):
    frames = Frames(
        np.full_like(smooth.frames.data, value), smooth.frames.t, smooth.frames.exposure_us
    )
    fit = fit_thresholds(smooth.events, frames, "RGBG")
    _all_finite(fit)
    assert fit.fallback.all() and (fit.confidence == 0).all()
    assert np.allclose(fit.on, DATASHEET_THRESHOLDS[0])
    assert np.allclose(fit.off, DATASHEET_THRESHOLDS[1])
    assert fit.notes


def test_half_the_frames_saturated(smooth):
    data = smooth.frames.data.copy()
    data[::2, : H // 2] = 1023  # every other frame clipped in the top half
    frames = Frames(data, smooth.frames.t, smooth.frames.exposure_us)
    fit = fit_thresholds(smooth.events, frames, "RGBG", refractory_us=0.0)
    _all_finite(fit)
    good = fit.confidence >= 0.5
    assert good.any()
    assert max(_rmse(fit, smooth, good)) < 0.02


def test_a_single_event_is_finite(smooth):
    one = Events([3], [4], [100_000], [1], W, H, "RGBG")
    fit = fit_thresholds(one, smooth.frames, "RGBG")
    _all_finite(fit)
    assert fit.fallback.all() and (fit.confidence == 0).all()


def test_too_little_data_is_an_error(smooth):
    f = smooth.frames
    two = Frames(f.data[:2], f.t[:2], f.exposure_us[:2])
    with pytest.raises(CalibrationError, match="at least 3"):
        fit_thresholds(smooth.events, two, "RGBG")
    with pytest.raises(CalibrationError, match="no events"):
        fit_thresholds(Events.empty(W, H, "RGBG"), f, "RGBG")
    with pytest.raises(CalibrationError, match="no events"):
        fit_thresholds(smooth.events, f, "RGBG", exclude=np.ones((H, W), bool))
    with pytest.raises(CalibrationError, match="frames of"):
        small = Frames(f.data[:, :10], f.t, f.exposure_us)
        fit_thresholds(smooth.events, small, "RGBG")
    with pytest.raises(InputError, match="exclude"):
        fit_thresholds(smooth.events, f, "RGBG", exclude=np.zeros((3, 3), bool))
    with pytest.raises(InputError, match="color filter"):
        fit_thresholds(smooth.events, f, "XYZW")


def test_deterministic_and_reports_progress(smooth):
    seen = []
    a = fit_thresholds(smooth.events, smooth.frames, "RGBG", progress=lambda d, n: seen.append(d))
    b = fit_thresholds(smooth.events, smooth.frames, "RGBG")
    assert np.array_equal(a.on, b.on) and np.array_equal(a.confidence, b.confidence)
    assert seen and seen == sorted(seen)


def test_box_qp_matches_a_grid_search():
    rng = np.random.default_rng(4)
    m = 200
    root = rng.normal(size=(m, 2, 2))
    q = root @ root.transpose(0, 2, 1) + 0.05 * np.eye(2)
    g = rng.normal(size=(m, 2)) * 3
    lo, hi = 0.02, 1.5
    x1, x2 = _box_qp(q[:, 0, 0], q[:, 0, 1], q[:, 1, 1], g[:, 0], g[:, 1], lo, hi)
    grid = np.linspace(lo, hi, 301)
    a, b = np.meshgrid(grid, grid, indexing="ij")
    for i in range(m):
        f = 0.5 * (q[i, 0, 0] * a * a + 2 * q[i, 0, 1] * a * b + q[i, 1, 1] * b * b)
        f -= g[i, 0] * a + g[i, 1] * b
        fit = 0.5 * (q[i, 0, 0] * x1[i] ** 2 + 2 * q[i, 0, 1] * x1[i] * x2[i])
        fit += 0.5 * q[i, 1, 1] * x2[i] ** 2 - g[i, 0] * x1[i] - g[i, 1] * x2[i]
        assert lo <= x1[i] <= hi and lo <= x2[i] <= hi
        assert fit <= f.min() + 1e-9
