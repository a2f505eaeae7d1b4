"""Hot pixels, noise rates and the refractory period, on synthetic events of this file's own:
a still part of the sensor (leak and shot noise only), a part that sees a grating move to and
fro (bursts of events limited by the refractory period, as busy as the hot pixels), hot pixels
in both, and APS frames of the same."""

from dataclasses import dataclass

import numpy as np
import pytest

from evcap.calib.noise import (
    NoiseConfig,
    hot_pixel_mask,
    measure_noise,
    poisson_quantile,
    refractory_period,
)
from evcap.errors import CalibrationError, InputError
from evcap.events import Events
from evcap.streams import Frames

H, W = 80, 140
SWEPT = 40  # columns 0..39 see a grating of stripes moving to and fro
STRIPE = 3  # pixels
LEAK_HZ, SHOT_HZ, HOT_HZ, REFRACTORY_US = 0.1, 0.05, 100.0, 200.0
STEPS = 10  # events per edge crossing (a log change of 2 at thresholds of 0.2)


@dataclass
class Recording:
    events: Events
    frames: Frames
    hot: np.ndarray  # [H, W] bool
    leak_hz: float  # the mean leak rate of the still pixels
    duration_us: int


def _phase(x, t_s):
    """Which stripe of the grating pixel column x sees at times t_s (even: bright)."""
    shift = 20.0 * np.sin(2 * np.pi * 0.5 * t_s)
    return np.floor((np.asarray(x) + 0.5 - shift) / STRIPE)


def make_recording(seed=0, duration_s=10.0, flicker=None, ramp=None) -> Recording:
    rng = np.random.default_rng(seed)
    n_px = H * W
    T = duration_s * 1e6
    ts, pxs, ps = [], [], []

    def add(t, px, p):
        ts.append(np.asarray(t, np.float64))
        pxs.append(np.asarray(px, np.int64))
        ps.append(np.asarray(p, np.uint8))

    # leak (ON, steady state: Poisson) on every pixel, each at its own rate; shot noise
    leak = LEAK_HZ * 10 ** rng.normal(0, 0.1, n_px)
    counts = rng.poisson(leak * duration_s)
    add(rng.uniform(0, T, counts.sum()), np.repeat(np.arange(n_px), counts), np.ones(counts.sum()))
    n = rng.poisson(SHOT_HZ * duration_s * n_px)
    add(rng.uniform(0, T, n), rng.integers(0, n_px, n), rng.integers(0, 2, n))
    # the swept part: a burst of STEPS events each time an edge crosses a pixel, closer than
    # the refractory period allows: the pixel keeps every m-th (m = ceil(period / spacing)).
    # Going dark is faster, and loses more: the busy pixels fire mostly ON, as hot ones do.
    grid = np.arange(0, T, 500.0)
    for x in range(SWEPT):
        stripe = _phase(x, grid * 1e-6)
        for i in np.flatnonzero(stripe[1:] != stripe[:-1]):
            bright = stripe[i + 1] % 2 == 0
            spacing = rng.uniform(60.0, 150.0, H) if bright else rng.uniform(10.0, 40.0, H)
            m = np.ceil(REFRACTORY_US / spacing)
            kept = np.ceil(STEPS / m).astype(np.int64)  # events 0, m, 2m, ... of each burst
            j = np.arange(kept.sum()) - np.repeat(np.cumsum(kept) - kept, kept)
            t = grid[i] + j * np.repeat(m * spacing, kept)
            add(t, np.repeat(np.arange(H) * W + x, kept), np.full(t.size, bright))
    # hot pixels: steady ON at HOT_HZ, some in the still half, some in the swept half
    hot = np.zeros(n_px, bool)
    ys = rng.integers(2, H - 2, 10)
    xs = np.r_[rng.integers(2, SWEPT - 2, 4), rng.integers(SWEPT + 5, W - 2, 6)]
    hot[ys * W + xs] = True
    for p in np.flatnonzero(hot):
        k = rng.poisson(HOT_HZ * duration_s)
        add(rng.uniform(0, T, k), np.full(k, p), np.ones(k))
    if flicker is not None:  # a pixel that alternates ON and OFF at 200 Hz: busy, not hot
        t = np.arange(0, T, 2500.0)
        add(t, np.full(t.size, flicker), np.arange(t.size) % 2)
    if ramp is not None:  # a pixel brightening steadily for a quarter of the recording
        t = np.arange(T / 4, T / 2, 20_000.0) + rng.uniform(0, 2000.0)
        add(t, np.full(t.size, ramp), np.ones(t.size))
    t = np.concatenate(ts)
    order = np.argsort(t, kind="stable")
    px = np.concatenate(pxs)[order]
    events = Events(
        px % W, px // W, np.floor(t[order]).astype(np.int64), np.concatenate(ps)[order], W, H
    )
    # APS frames at 25 fps: the grating's stripes bright and dark, the rest still
    starts = np.arange(0, T - 4000, 40_000.0)
    level = np.full((starts.size, H, W), 400.0)
    lit = _phase(np.arange(SWEPT)[None, :], (starts[:, None] + 2000) * 1e-6) % 2 == 0
    level[:, :, :SWEPT] = np.where(lit, 739.0, 100.0)[:, None, :]
    data = rng.poisson(level) + rng.normal(0, 2.0, level.shape)
    frames = Frames(
        np.clip(np.round(data), 0, 1023).astype(np.uint16),
        starts.astype(np.int64),
        np.full(starts.size, 4000),
    )
    still_leak = leak.reshape(H, W)[:, SWEPT:]
    return Recording(events, frames, hot.reshape(H, W), float(still_leak.mean()), int(T))


@pytest.fixture(scope="module")
def rec():
    return make_recording()


def _precision_recall(found, truth):
    tp = int((found & truth).sum())
    return tp / max(int(found.sum()), 1), tp / max(int(truth.sum()), 1)


@pytest.mark.parametrize("with_frames", [True, False])
def test_measures_hot_pixels_noise_and_refractory(rec, with_frames):
    stats = measure_noise(
        rec.events, rec.frames if with_frames else None, duration_us=rec.duration_us
    )
    precision, recall = _precision_recall(stats.hot_pixels, rec.hot)
    assert precision >= 0.95 and recall >= 0.95
    assert stats.background_activity_hz == pytest.approx(rec.leak_hz, rel=0.1)
    assert stats.shot_noise_hz == pytest.approx(SHOT_HZ, rel=0.1)
    assert stats.refractory_period_us == pytest.approx(REFRACTORY_US, rel=0.1)
    assert 0 < stats.background_activity_err_hz < 0.03 * stats.background_activity_hz
    assert 0 < stats.shot_noise_err_hz < 0.05 * stats.shot_noise_hz
    assert stats.noise_method == ("frames and events" if with_frames else "events")
    # the noise is counted away from the grating: no still pixel within 3 columns of it
    assert not stats.static_pixels[:, : SWEPT + 3].any()
    assert stats.static_pixels.sum() > 0.5 * H * (W - SWEPT)
    assert stats.rate_hz.shape == (H, W) and stats.rate_hz.dtype == np.float32
    hot_rate = stats.rate_hz[rec.hot & (np.arange(W) >= SWEPT)[None, :]]
    assert np.all(np.abs(hot_rate - HOT_HZ) < 0.3 * HOT_HZ)
    assert stats.duration_us == rec.duration_us


def test_the_rate_alone_would_flag_the_grating():
    # the grating's pixels fire about as often as the hot ones: the rate rule alone cannot
    # tell them apart, the polarity and steadiness rules do
    rec = make_recording(seed=1, duration_s=5.0)
    stats = measure_noise(rec.events, None)
    assert stats.candidates >= stats.hot_pixels.sum()
    loose = NoiseConfig(occupancy=0.0, occupancy_maybe=0.0, dominance=0.0, burst_share=1.0)
    flagged = hot_pixel_mask(rec.events, config=loose)
    assert flagged[:, :SWEPT].sum() > 10 * rec.hot[:, :SWEPT].sum()
    # the grating sweeps by regularly: its pixels' ON events are steady at the scale of
    # their rate; what gives them away is that they come in bursts
    no_bursts = hot_pixel_mask(rec.events, config=NoiseConfig(burst_share=1.0))
    assert no_bursts[:, :SWEPT].sum() > 10 * rec.hot[:, :SWEPT].sum()
    assert _precision_recall(stats.hot_pixels, rec.hot) == (1.0, 1.0)
    assert np.array_equal(hot_pixel_mask(rec.events), stats.hot_pixels)


def test_pixels_of_one_steady_trait_only_are_not_hot():
    rec = make_recording(seed=2, duration_s=5.0, flicker=40 * W + 70, ramp=20 * W + 90)
    stats = measure_noise(rec.events, rec.frames)
    # steady, not in bursts, but both polarities alike
    assert not stats.hot_pixels[40, 70]
    assert stats.rate_hz[40, 70] > 300
    # one polarity, not in bursts, but for a while only
    assert not stats.hot_pixels[20, 90]
    assert stats.rate_hz[20, 90] > 10
    assert _precision_recall(stats.hot_pixels, rec.hot) == (1.0, 1.0)


def test_frames_of_varying_exposure(rec):
    # the APS value follows the exposure time: a still pixel stays still per unit of exposure
    f = rec.frames
    scale = np.where(np.arange(len(f)) % 2 == 0, 1.0, 0.5)
    data = np.round(f.data * scale[:, None, None]).astype(np.uint16)
    halved = Frames(data, f.t, np.round(f.exposure_us * scale).astype(np.int64))
    stats = measure_noise(rec.events, halved, duration_us=rec.duration_us)
    assert stats.noise_method == "frames and events"
    assert stats.static_pixels.sum() > 0.5 * H * (W - SWEPT)


def test_black_frames_fall_back_to_the_events(rec):
    black = Frames(np.zeros_like(rec.frames.data), rec.frames.t, rec.frames.exposure_us)
    stats = measure_noise(rec.events, black, duration_us=rec.duration_us)
    assert stats.noise_method == "events" and stats.notes
    assert stats.shot_noise_hz == pytest.approx(SHOT_HZ, rel=0.1)


def test_refractory_period_is_a_low_percentile_not_the_minimum(rec):
    # a few timestamps glitch (two events 1 us apart) and noise events fall inside bursts:
    # the minimum follows them, the estimate does not
    ev = rec.events
    busy = np.flatnonzero(ev.x < 5)[:40]
    t = np.sort(np.concatenate([ev.t, ev.t[busy] + 1]))
    extra = np.argsort(np.concatenate([ev.t, ev.t[busy] + 1]), kind="stable")
    glitchy = Events(
        np.concatenate([ev.x, ev.x[busy]])[extra],
        np.concatenate([ev.y, ev.y[busy]])[extra],
        t,
        np.concatenate([ev.p, ev.p[busy]])[extra],
        W,
        H,
    )
    assert refractory_period(glitchy, exclude=rec.hot) == pytest.approx(REFRACTORY_US, rel=0.1)
    assert refractory_period(glitchy, exclude=rec.hot, percentile=0.0) < 20


@pytest.mark.parametrize(
    "events",
    [
        Events([3], [4], [10], [1], W, H),
        Events([3, 3], [4, 4], [10, 10], [1, 1], W, H),
        Events(
            np.full(500, 7), np.full(500, 9), np.arange(500) * 1000, np.ones(500, np.uint8), W, H
        ),
    ],
    ids=["one event", "two at one time", "one pixel only"],
)
def test_little_data_stays_finite(events):
    stats = measure_noise(events, None)
    for value in (
        stats.background_activity_hz,
        stats.shot_noise_hz,
        stats.refractory_period_us,
        stats.on_rate_hz,
        stats.off_rate_hz,
    ):
        assert np.isfinite(value) and value >= 0
    assert np.isfinite(stats.rate_hz).all()


def test_bad_input_is_an_error(rec):
    with pytest.raises(CalibrationError, match="no events"):
        measure_noise(Events.empty(W, H), rec.frames)
    small = Frames(rec.frames.data[:, :10], rec.frames.t, rec.frames.exposure_us)
    with pytest.raises(InputError, match="frames of"):
        measure_noise(rec.events, small)
    with pytest.raises(InputError, match="duration_us"):
        measure_noise(rec.events, None, duration_us=0)


def test_poisson_quantile_against_the_sum_of_its_terms():
    from math import exp, factorial

    for mean in (0.0, 0.3, 2.5, 17.0, 120.0):
        for q in (0.5, 0.75, 0.99):
            k = poisson_quantile(q, mean)
            cdf = [
                sum(exp(-mean) * mean**i / factorial(i) for i in range(j + 1)) for j in (k - 1, k)
            ]
            assert cdf[1] >= q - 1e-12
            assert k == 0 or cdf[0] < q
    # the normal approximation, for large means
    assert abs(poisson_quantile(0.75, 10_000.0) - (10_000 + 0.6745 * 100)) <= 2
