"""The DVS pixel model on hand-made signals (no rendering)."""

import numpy as np
import pytest

from evcap.sim.events import PixelArray


def run(times, values, effects=None, c=0.2, seed=0, px_per_us=None):
    """One pixel's samples -> its events (t, polarity); ``px_per_us``: how fast the pixel's
    image moves (what a footprint reads)."""
    pa = PixelArray(1, c, c, effects or {}, np.random.default_rng(seed))
    pa.start(np.array([values[0]]), times[0])
    if px_per_us is not None:
        pa.set_image_speed(np.array([px_per_us]))
    t, px, p = pa.events(
        np.asarray(times, float),
        np.asarray(values, float),
        np.array([0, len(times)]),
        np.array([0]),
    )
    return t, p


def test_crossings_at_the_interpolated_times():
    t, p = run([0.0, 1000.0], [0.0, 1.1])  # log rises by 1.1 over 1 ms: 5 ON events
    np.testing.assert_allclose(t, np.arange(1, 6) * 0.2 / 1.1 * 1000, atol=1e-6)
    assert p.tolist() == [1] * 5
    t, p = run([0.0, 100.0, 200.0], [0.0, -0.5, 0.0])
    # down by 0.5: OFF at -0.2, -0.4; back up from the reference -0.4: ON at -0.2 and 0.0
    assert p.tolist() == [0, 0, 1, 1]
    np.testing.assert_allclose(t, [40, 80, 160, 200])


def test_long_recordings_keep_microseconds():
    start = 1e10  # about 2.8 hours of microseconds
    t, _ = run([start, start + 1000.0], [0.0, 1.1])
    np.testing.assert_allclose(t - start, np.arange(1, 6) * 0.2 / 1.1 * 1000, atol=1e-4)


def test_refractory_period_drops_but_moves_the_reference():
    t, p = run([0.0, 1000.0], [0.0, 2.0], {"refractory": {"period_us": 250}})
    # crossings every 100 us: only those 250 us or more after the last kept one remain
    np.testing.assert_allclose(t, [100, 400, 700, 1000])
    t2, _ = run([0.0, 1000.0, 2000.0], [0.0, 2.0, 2.0], {"refractory": {"period_us": 250}})
    assert len(t2) == 4  # the reference moved with the dropped events: no catch-up burst


def test_bandwidth_delays_a_step():
    cutoff = 100.0
    tau = 1e6 / (2 * np.pi * cutoff)
    t, p = run([0.0, 1.0, 50_000.0], [0.0, 1.0, 1.0], {"bandwidth": {"cutoff_hz": cutoff}})
    # the filtered signal 1 - exp(-t / tau) crosses 0.2, 0.4, ... later than the step
    expected = -tau * np.log(1 - 0.2 * np.arange(1, 5))
    np.testing.assert_allclose(t[:4], expected, rtol=0.01)
    assert len(t) == 4  # the 5th level (1.0) is only reached asymptotically


@pytest.mark.parametrize("contrast", [1.0, -1.0, 2.0])
def test_the_footprint_spreads_an_edge_as_a_pixel_of_that_size_sees_it(contrast):
    from scipy.special import ndtr

    sigma, speed = 0.3, 100e-6  # px, px per us: the edge takes 3 ms to cross sigma
    spread = sigma / speed
    # a point pixel's signal: the edge's step at 20 ms, resolved to 1 us
    step = [0.0, 20_000.0, 20_001.0, 60_000.0], [0.0, 0.0, contrast, contrast]
    t, p = run(*step, {"footprint": {"sigma_px": sigma}}, px_per_us=speed)
    # the signal of a Gaussian footprint crossed by the edge, linear radiance
    fine = np.linspace(0.0, 60_000.0, 60_001)
    seen = 1 + (np.exp(contrast) - 1) * ndtr((fine - 20_000.0) / spread)
    t_exact, p_exact = run(fine, np.log(seen))
    assert p.tolist() == p_exact.tolist()
    assert np.abs(t - t_exact).max() < 0.5 * spread
    assert abs(np.mean(t - t_exact)) < 0.25 * spread
    t_point, _ = run(*step)  # a point: all at once
    assert np.ptp(t_point) < 2 and np.ptp(t) > spread


def test_a_footprint_keeps_events_a_point_pixel_loses_to_the_refractory_period():
    step = [0.0, 20_000.0, 20_001.0, 60_000.0], [0.0, 0.0, 2.0, 2.0]
    refractory = {"refractory": {"period_us": 500}}
    point, _ = run(*step, refractory)
    seen, _ = run(*step, {**refractory, "footprint": {"sigma_px": 0.3}}, px_per_us=100e-6)
    assert len(point) == 1 and len(seen) >= 6  # of 10


def test_background_activity_rate_of_a_still_pixel():
    n = 2000
    pa = PixelArray(
        n, 0.2, 0.2, {"background_activity": {"rate_hz": 5.0}}, np.random.default_rng(1)
    )
    pa.start(np.zeros(n), 0.0)
    times = np.tile([0.0, 2e6], n)  # 2 s of a constant signal
    t, px, p = pa.events(times, np.zeros(2 * n), np.arange(n + 1) * 2, np.arange(n))
    assert (p == 1).all()
    rate = len(t) / n / 2.0
    assert rate == pytest.approx(5.0 * 1.027, rel=0.05)  # 0.1-decade spread: mean factor 1.027


def test_threshold_spread_statistics():
    pa = PixelArray(
        20_000, 0.2, 0.3, {"threshold_spread": {"sigma": 0.03}}, np.random.default_rng(2)
    )
    assert pa.con.mean() == pytest.approx(0.2, abs=0.002)
    assert pa.coff.mean() == pytest.approx(0.3, abs=0.002)
    assert pa.con.std() == pytest.approx(0.03, rel=0.05)
    assert not np.allclose(pa.con, pa.coff - 0.1)  # ON and OFF drawn apart
    t, p = run([0.0, 1000.0], [0.0, 1.0], {"threshold_spread": {"sigma": 0.05}}, seed=3)
    pa = PixelArray(1, 0.2, 0.2, {"threshold_spread": {"sigma": 0.05}}, np.random.default_rng(3))
    assert len(t) == int(1.0 / pa.con[0])  # the pixel's own threshold counts the steps


def test_shot_noise_and_hot_pixels():
    n = 5000
    pa = PixelArray(
        n,
        0.2,
        0.2,
        {"shot_noise": {"rate_hz": 2.0}, "hot_pixels": {"count": 7, "rate_hz": 300.0}},
        np.random.default_rng(4),
    )
    t, px, p = pa.noise(0.0, 1e6)
    hot = np.isin(px, pa.hot)
    assert len(pa.hot) == 7 and np.unique(px[hot]).size == 7
    assert hot.sum() == pytest.approx(7 * 300, rel=0.15)
    assert (~hot).sum() == pytest.approx(2.0 * n, rel=0.1)
    assert 0.45 < p[~hot].mean() < 0.55 and p[hot].mean() > 0.95  # hot pixels fire ON
    assert t.min() >= 0 and t.max() < 1e6


def test_jitter_and_drops():
    pa = PixelArray(
        1,
        0.2,
        0.2,
        {"timestamp_jitter": {"sigma_us": 10.0}, "dropped": {"probability": 0.25}},
        np.random.default_rng(5),
    )
    t = np.arange(40_000, dtype=float) * 100
    jt, px, p = pa.degrade(t, np.zeros(40_000, np.int64), np.ones(40_000, np.uint8))
    assert len(jt) == pytest.approx(30_000, rel=0.03)
    pa2 = PixelArray(
        1, 0.2, 0.2, {"timestamp_jitter": {"sigma_us": 10.0}}, np.random.default_rng(5)
    )
    jt, _, _ = pa2.degrade(t, np.zeros(40_000, np.int64), np.ones(40_000, np.uint8))
    assert (jt - t).std() == pytest.approx(10.0, rel=0.05)


def test_black_and_extreme_values_stay_finite():
    dark = 1e-3
    values = np.log(np.array([0.0, 1e6, 0.0, 0.0]) + dark)  # black to blinding and back
    t, p = run([0.0, 100.0, 200.0, 300.0], values)
    expected_each_way = int((values[1] - values[0]) / 0.2)
    assert (p == 1).sum() == expected_each_way and (p == 0).sum() == expected_each_way
    assert np.isfinite(t).all() and (np.diff(t) >= 0).all()
