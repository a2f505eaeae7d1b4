"""The event filters: a moving edge's events kept and lone noise events dropped, crowded events
marked, hot pixels dropped; each against a plain-Python reference, and the same on a stream
read in blocks as on the stream whole."""

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evcap.errors import InputError
from evcap.event_filters import (
    CROWDED_PERIODS,
    BackgroundActivityFilter,
    Compose,
    EventFilter,
    HotPixelMask,
    RefractoryMarking,
)
from evcap.events import Events

W = H = 20


def edge_and_noise(noise_hz: float, seed: int = 0) -> tuple[Events, np.ndarray]:
    """A vertical edge sweeping right at 100 px/s (each column fires at once, every 10 ms),
    and noise at ``noise_hz`` a pixel over the same 0.2 s; (events in time order, which are
    the edge's). The edge's events are ON, the noise's OFF: what a filter keeps tells them
    apart (none of them looks at polarity)."""
    rng = np.random.default_rng(seed)
    cols, rows = np.meshgrid(np.arange(W), np.arange(H))
    edge = (cols.ravel(), rows.ravel(), cols.ravel() * 10_000 + 1_000)
    n = rng.poisson(noise_hz * 0.2 * W * H)
    noise = (rng.integers(0, W, n), rng.integers(0, H, n), rng.integers(0, 200_000, n))
    x, y, t = (np.concatenate(a) for a in zip(edge, noise, strict=True))
    is_edge = np.arange(len(t)) < W * H
    order = np.argsort(t, kind="stable")
    return Events(x[order], y[order], t[order], is_edge[order], W, H), is_edge[order]


def supported_reference(events: Events, within_us: float) -> np.ndarray:
    """The background-activity filter's kept events, as plain Python."""
    last: dict[tuple[int, int], int] = {}
    out = []
    for x, y, t in zip(events.x.tolist(), events.y.tolist(), events.t.tolist(), strict=True):
        near = [(x + dx, y + dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1) if dx or dy]
        out.append(any(q in last and t - last[q] <= int(within_us) for q in near))
        last[x, y] = t
    return np.array(out, bool)


def crowded_reference(events: Events, within_us: float) -> np.ndarray:
    """Whether each event comes at most ``within_us`` after its pixel's previous one."""
    last: dict[tuple[int, int], int] = {}
    out = []
    for x, y, t in zip(events.x.tolist(), events.y.tolist(), events.t.tolist(), strict=True):
        out.append((x, y) in last and t - last[x, y] <= within_us)
        last[x, y] = t
    return np.array(out, bool)


def in_blocks(stream, events: Events, cuts: list[int]) -> list:
    bounds = [0, *sorted(cuts), len(events)]
    index = np.arange(len(events))
    pairs = zip(bounds[:-1], bounds[1:], strict=True)
    return [stream(events.select((index >= a) & (index < b))) for a, b in pairs]


def same_events(a: Events, b: Events) -> None:
    for name in ("x", "y", "t", "p"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def concatenated(parts: list[Events]) -> Events:
    fields = (np.concatenate([getattr(e, n) for e in parts]) for n in ("x", "y", "t", "p"))
    return Events(*fields, width=parts[0].width, height=parts[0].height)


def test_a_moving_edge_is_kept_and_lone_noise_dropped():
    events, is_edge = edge_and_noise(5.0)
    kept = BackgroundActivityFilter(5_000)(events)
    # each column's pixels fire together: all kept but the first of each (none before it)
    assert kept.p.sum() >= W * H - W
    # a noise event has 8 neighbours firing at 5 Hz: 1 - exp(-8 x 5 x 0.005) = 18 % of them
    # meet one, and some more meet the edge (it crosses a neighbour every 10 ms)
    assert 0.1 < (kept.p == 0).sum() / (~is_edge).sum() < 0.5


def test_the_filter_keeps_what_the_reference_keeps():
    events, _ = edge_and_noise(20.0, seed=2)
    for within in (1, 2_000, 2_000.9, 0.5):
        kept = BackgroundActivityFilter(within)(events)
        same_events(kept, events.select(supported_reference(events, within)))


def test_a_neighbour_at_the_same_time_supports_and_a_dropped_event_too():
    # (0, 0) at t=10 has no support and is dropped, yet supports (1, 1) at t=10 and t=15;
    # (5, 5) is no neighbour of anything
    events = Events([0, 1, 5, 1], [0, 1, 5, 1], [10, 10, 12, 15], [1, 0, 1, 1], 8, 8)
    kept = BackgroundActivityFilter(5)(events)
    assert kept.x.tolist() == [1, 1] and kept.t.tolist() == [10, 15]
    assert len(BackgroundActivityFilter(4)(events)) == 1  # t=15 is 5 us after (0, 0)


def test_marking_marks_an_event_within_the_periods_of_its_pixels_previous():
    # pixel (1, 0) at 1000, 1300, 1600 (300 us apart: crowded after the first) and 6600;
    # pixel (2, 3) at 1500, 2500 (exactly 2 x 500 us: crowded) and 3501; either polarity
    events = Events(
        x=[1, 1, 2, 1, 2, 2, 1],
        y=[0, 0, 3, 0, 3, 3, 0],
        t=[1000, 1300, 1500, 1600, 2500, 3501, 6600],
        p=[1, 1, 0, 0, 1, 0, 1],
        width=8,
        height=6,
    )
    marked = RefractoryMarking(500.0)(events)
    assert marked.dtype == bool and marked.tolist() == [0, 1, 0, 1, 1, 0, 0]
    assert RefractoryMarking(500.0, periods=1.0)(events).tolist() == [0, 1, 0, 1, 0, 0, 0]
    assert RefractoryMarking(500.0).periods == CROWDED_PERIODS == 2.0
    np.testing.assert_array_equal(marked, crowded_reference(events, 1000.0))


def test_hot_pixels_are_dropped():
    events, _ = edge_and_noise(20.0, seed=3)
    mask = np.zeros((H, W), bool)
    mask[4, 7] = mask[0, 0] = True
    kept = HotPixelMask(mask)(events)
    hot = ((events.x == 7) & (events.y == 4)) | ((events.x == 0) & (events.y == 0))
    assert hot.any()
    same_events(kept, events.select(~hot))
    mask[:] = True  # the filter keeps its own copy
    assert len(HotPixelMask(np.zeros((H, W), bool))(events)) == len(events)


def test_a_mask_of_another_shape_or_type_is_refused():
    events, _ = edge_and_noise(1.0)
    with pytest.raises(InputError, match="mask"):
        HotPixelMask(np.zeros((H, W), np.uint8))
    with pytest.raises(InputError, match="mask"):
        HotPixelMask(np.zeros(W * H, bool))
    with pytest.raises(InputError, match="20 x 20 sensor"):
        HotPixelMask(np.zeros((H + 1, W), bool))(events)


def test_compose_applies_its_filters_in_order():
    events, _ = edge_and_noise(20.0, seed=4)
    mask = np.zeros((H, W), bool)
    mask[:, 5] = True
    hot, noise = HotPixelMask(mask), BackgroundActivityFilter(3_000)
    same_events(Compose(hot, noise)(events), noise(hot(events)))
    same_events(Compose(noise, hot)(events), hot(noise(events)))
    # a hot pixel's events support its neighbours only while they are not dropped first
    assert len(Compose(hot, noise)(events)) < len(Compose(noise, hot)(events))
    assert Compose()(events) is events
    with pytest.raises(TypeError, match="event filters"):
        Compose(noise, RefractoryMarking(100))  # a marking returns a mask, not events


def test_a_filter_called_again_starts_afresh():
    events, _ = edge_and_noise(20.0, seed=5)
    f = BackgroundActivityFilter(2_000)
    same_events(f(events), f(events))
    assert isinstance(f, EventFilter)


@pytest.mark.parametrize(
    "make, name",
    [
        (lambda v: BackgroundActivityFilter(v), "within_us"),
        (lambda v: RefractoryMarking(v), "period_us"),
        (lambda v: RefractoryMarking(100.0, periods=v), "periods"),
    ],
)
@pytest.mark.parametrize("value", [0, -1, -0.5, float("nan"), float("inf")])
def test_a_time_that_is_not_positive_is_refused_by_name(make, name, value):
    with pytest.raises(InputError, match=f"{name} must be a positive number"):
        make(value)


def test_a_stream_refuses_a_block_from_the_past_or_another_sensor():
    events, _ = edge_and_noise(5.0)
    for stream in (BackgroundActivityFilter(1_000).stream(), RefractoryMarking(100).stream()):
        stream(events.time_slice(50_000, 100_000))
        with pytest.raises(InputError, match="before the previous"):
            stream(events.time_slice(0, 60_000))
        with pytest.raises(InputError, match="8 x 8 sensor"):
            stream(Events.empty(8, 8))


@st.composite
def streams(draw):
    """Events on a small sensor, in time order with many at the same time, and block cuts."""
    n = draw(st.integers(0, 120))
    w, h = draw(st.integers(1, 6)), draw(st.integers(1, 5))
    steps = draw(st.lists(st.integers(0, 30), min_size=n, max_size=n))
    x = draw(st.lists(st.integers(0, w - 1), min_size=n, max_size=n))
    y = draw(st.lists(st.integers(0, h - 1), min_size=n, max_size=n))
    p = draw(st.lists(st.integers(0, 1), min_size=n, max_size=n))
    t = np.cumsum(steps, dtype=np.int64) + 7
    events = Events(*(np.asarray(a, np.int64) for a in (x, y, t, p)), width=w, height=h)
    cuts = draw(st.lists(st.integers(0, n), max_size=4))
    mask = np.array(draw(st.lists(st.booleans(), min_size=w * h, max_size=w * h)), bool)
    return events, cuts, mask.reshape(h, w)


@settings(max_examples=150, deadline=None)
@given(
    stream=streams(),
    within=st.floats(0.5, 60.0) | st.integers(1, 60),
    period=st.floats(0.25, 40.0),
)
def test_blocks_filter_and_mark_as_the_whole(stream, within, period):
    events, cuts, mask = stream
    noise = BackgroundActivityFilter(within)
    chain = Compose(HotPixelMask(mask), noise)
    marking = RefractoryMarking(period)
    same_events(noise(events), events.select(supported_reference(events, within)))
    np.testing.assert_array_equal(marking(events), crowded_reference(events, 2 * period))
    for f in (noise, chain):
        parts = in_blocks(f.stream(), events, cuts)
        same_events(concatenated(parts), f(events))
    marks = in_blocks(marking.stream(), events, cuts)
    np.testing.assert_array_equal(np.concatenate(marks), marking(events))


def test_the_windows_count_the_filtered_and_the_crowded_events(tmp_path, monkeypatch):
    from evcap.recon.events import windows as event_windows
    from evcap.recon.events.windows import EventWindows, WindowsConfig
    from evcap.session import SensorInfo, Session, SessionWriter

    events, _ = edge_and_noise(5.0)
    path = tmp_path / "s.h5"
    with SessionWriter(path, SensorInfo("simulated", W, H)) as w:
        w.append_events(events)
    monkeypatch.setattr(event_windows, "MIN_EVENTS", 0)
    c = np.full((H, W), 0.2)
    optics = SimpleNamespace(threshold_on=c, threshold_off=c, refractory_us=4e3)
    with Session.open(path) as s:
        grid = WindowsConfig(frame_interval_ms=10, max_frames=30)
        every = EventWindows.from_session(s, optics, 0, 200_000, grid)
        counted = replace(grid, refractory_bound=True, noise_filter_ms=5)
        some = EventWindows.from_session(s, optics, 0, 200_000, counted)
    kept = BackgroundActivityFilter(5_000)(events)
    assert every.events == len(events) and every.crowded is None
    assert some.events == len(kept)
    assert some.crowded.events == RefractoryMarking(4e3)(kept).sum() > 0
