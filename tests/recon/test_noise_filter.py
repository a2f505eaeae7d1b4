"""The background-activity filter: a moving edge's events kept, lone noise events dropped."""

from types import SimpleNamespace

import numpy as np
import pytest

from evcap.events import Events
from evcap.recon.events import windows as event_windows
from evcap.recon.events.noise_filter import supported
from evcap.recon.events.windows import EventWindows
from evcap.session import SensorInfo, Session, SessionWriter

W = H = 20
NONE_YET = np.iinfo(np.int64).min // 2


def edge_and_noise(noise_hz: float, seed: int = 0) -> tuple[Events, np.ndarray]:
    """A vertical edge sweeping right at 100 px/s (each column fires at once, every 10 ms),
    and noise at ``noise_hz`` a pixel over the same 0.2 s; (events in time order, which are
    the edge's)."""
    rng = np.random.default_rng(seed)
    cols, rows = np.meshgrid(np.arange(W), np.arange(H))
    edge = (cols.ravel(), rows.ravel(), cols.ravel() * 10_000 + 1_000)
    n = rng.poisson(noise_hz * 0.2 * W * H)
    noise = (rng.integers(0, W, n), rng.integers(0, H, n), rng.integers(0, 200_000, n))
    x, y, t = (np.concatenate(a) for a in zip(edge, noise, strict=True))
    is_edge = np.arange(len(t)) < W * H
    order = np.argsort(t, kind="stable")
    p = np.ones(len(t), np.int8)
    return Events(x[order], y[order], t[order], p, width=W, height=H), is_edge[order]


def test_a_moving_edge_is_kept_and_lone_noise_dropped():
    events, is_edge = edge_and_noise(5.0)
    last = np.full((H, W), NONE_YET, np.int64)
    kept = supported(events.x, events.y, events.t, last, 5_000)
    # each column's pixels fire together: all kept but the first of each (none before it)
    assert kept[is_edge].sum() >= W * H - W
    # a noise event has 8 neighbours firing at 5 Hz: 1 - exp(-8 x 5 x 0.005) = 18 % of them
    # meet one, and some more meet the edge (it crosses a neighbour every 10 ms)
    assert 0.1 < kept[~is_edge].mean() < 0.5
    assert last.max() == events.t.max()  # the map holds each pixel's last event


def test_blocks_sharing_the_map_filter_as_the_whole():
    events, _ = edge_and_noise(20.0, seed=1)
    whole = supported(events.x, events.y, events.t, np.full((H, W), NONE_YET), 2_000)
    last = np.full((H, W), NONE_YET, np.int64)
    first = np.arange(len(events)) < len(events) // 2
    parts = [supported(e.x, e.y, e.t, last, 2_000) for e in map(events.select, (first, ~first))]
    np.testing.assert_array_equal(np.concatenate(parts), whole)


def test_the_filter_needs_a_positive_time():
    events, _ = edge_and_noise(1.0)
    with pytest.raises(ValueError, match="positive"):
        supported(events.x, events.y, events.t, np.full((H, W), NONE_YET), 0)


def test_the_windows_count_the_filtered_events(tmp_path, monkeypatch):
    events, _ = edge_and_noise(5.0)
    path = tmp_path / "s.h5"
    with SessionWriter(path, SensorInfo("simulated", W, H)) as w:
        w.append_events(events)
    monkeypatch.setattr(event_windows, "MIN_EVENTS", 0)
    c = np.full((H, W), 0.2)
    optics = SimpleNamespace(threshold_on=c, threshold_off=c)
    with Session.open(path) as s:
        every = EventWindows.from_session(s, optics, 0, 200_000, 10_000, 30)
        some = EventWindows.from_session(s, optics, 0, 200_000, 10_000, 30, noise_filter_us=5e3)
    last = np.full((H, W), NONE_YET, np.int64)
    assert every.events == len(events)
    assert some.events == supported(events.x, events.y, events.t, last, 5_000).sum()
