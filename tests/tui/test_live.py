"""What the monitor computes from the stream (evcap.tui.live), without the UI."""

import numpy as np

from evcap.acquire.decoder import Decoded
from evcap.events import Events
from evcap.streams import Frames, ImuSamples, Triggers
from evcap.tui.live import LiveView, frame_for_display

W, H = 346, 260


def batch(x, y, t, p, frames=None, imu=None, color_filter="RGBG"):
    return Decoded(
        Events(np.asarray(x), np.asarray(y), np.asarray(t), np.asarray(p), W, H, color_filter),
        frames or Frames(np.zeros((0, H, W), np.uint16), [], []),
        imu or ImuSamples([], np.zeros((0, 3)), np.zeros((0, 3)), []),
        Triggers([], []),
    )


def test_rates_per_bin_and_series():
    live = LiveView(W, H, "RGBG", bin_us=100_000)
    # 100 ms bins: 3 events in bin 0 (R ON, G OFF, B ON), 1 in bin 2 (G ON)
    live.add(batch([0, 1, 1, 3], [0, 0, 1, 2], [10, 20, 99_999, 250_000], [1, 0, 1, 1]))
    s = live.snapshot()
    assert s.rates["on"][-3:].tolist() == [20.0, 0.0, 10.0]  # events per second
    assert s.rates["off"][-3:].tolist() == [10.0, 0.0, 0.0]
    assert s.rates["red"][-3:].tolist() == [10.0, 0.0, 0.0]
    assert s.rates["green"][-3:].tolist() == [10.0, 0.0, 10.0]
    assert s.rates["blue"][-3:].tolist() == [10.0, 0.0, 0.0]
    assert s.totals["events"] == 4 and s.totals["on"] == 3


def test_image_holds_only_the_last_window():
    live = LiveView(W, H, "MONO", window_us=10_000)
    live.add(batch([5], [5], [0], [1], color_filter="MONO"))
    live.add(batch([6], [6], [20_000], [0], color_filter="MONO"))
    img = live.snapshot().image
    assert img[5, 5].sum() == 0  # 20 ms old: out of the 10 ms window
    assert img[6, 6, 0] > img[6, 6, 1]  # OFF is red


def test_image_by_bayer_channel():
    live = LiveView(W, H, "RGBG")
    live.by_channel = True
    live.add(batch([0, 1, 1], [0, 0, 1], [0, 1, 2], [0, 0, 0]))
    img = live.snapshot().image
    assert np.argmax(img[0, 0]) == 0 and np.argmax(img[0, 1]) == 1 and np.argmax(img[1, 1]) == 2


def test_hot_pixels_are_found():
    rng = np.random.default_rng(0)
    live = LiveView(W, H, "MONO")
    n = 20_000
    x, y = rng.integers(0, W, n), rng.integers(0, H, n)
    x[: n // 2], y[: n // 2] = 7, 9  # one pixel makes half the events
    order = np.arange(n)
    rng.shuffle(order)
    live.add(batch(x[order], y[order], np.arange(n) * 20, np.ones(n, int), color_filter="MONO"))
    s = live.snapshot()
    assert s.hot_pixels_dominate and s.hot_pixel_share > 0.5
    calm = LiveView(W, H, "MONO")
    calm.add(
        batch(
            rng.integers(0, W, n),
            rng.integers(0, H, n),
            np.arange(n) * 20,
            np.ones(n, int),
            color_filter="MONO",
        )
    )
    assert not calm.snapshot().hot_pixels_dominate


def test_frame_imu_and_display():
    raw = np.zeros((H, W), np.uint16)
    raw[0::2, 0::2] = 1000  # red pixels of an RGBG mosaic lit
    frames = Frames(raw[None], [100], [50])
    imu = ImuSamples([5], [[0, -9.8, 0]], [[0.1, 0, 0]], [31.5])
    live = LiveView(W, H, "RGBG")
    live.add(batch([1], [1], [200], [1], frames=frames, imu=imu))
    s = live.snapshot()
    assert s.frame.shape == (H // 2, W // 2, 3)
    assert (s.frame[..., 0] > 200).all() and (s.frame[..., 1:] < 50).all()  # red
    assert s.frame_t_us == 100 and s.temperature == 31.5
    np.testing.assert_allclose(s.accel, [0, -9.8, 0], rtol=1e-6)
    gray = frame_for_display(np.tile(np.arange(W, dtype=np.uint16), (H, 1)), "MONO")
    assert gray.shape == (H, W, 3) and gray[0, 0, 0] == 0 and gray[0, -1, 0] == 255
