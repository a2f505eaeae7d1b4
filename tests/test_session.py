import os
import subprocess
import sys
import zlib

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from evcap.errors import OutputExistsError, SessionFormatError
from evcap.events import Events
from evcap.session import (
    EVENT_CHUNK,
    SensorInfo,
    Session,
    SessionWriter,
)
from evcap.streams import Frames, ImuSamples, Triggers

W, H = 346, 260
SENSOR = SensorInfo("simulated", W, H, "RGBG", "SIM0001", 1_700_000_000_000_000)


def random_events(rng, n, t_start=0, max_gap=3000):
    t = t_start + np.cumsum(rng.integers(0, max_gap, n))
    return Events(
        rng.integers(0, W, n), rng.integers(0, H, n), t, rng.integers(0, 2, n), W, H, "RGBG"
    )


def concat(parts):
    return Events(*(np.concatenate([getattr(e, k) for e in parts]) for k in "xytp"), W, H, "RGBG")


def assert_same(a, b):
    for k in "xytp":
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))


@st.composite
def sessions(draw):
    """Random event batches (possibly empty), with random flush points."""
    seed = draw(st.integers(0, 2**32 - 1))
    sizes = draw(st.lists(st.integers(0, 400), max_size=6))
    flushes = draw(st.lists(st.booleans(), min_size=len(sizes), max_size=len(sizes)))
    max_gap = draw(st.sampled_from([1, 7, 1000, 2500]))
    return seed, sizes, flushes, max_gap


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(case=sessions(), data=st.data())
def test_round_trip_and_time_slices(tmp_path_factory, case, data):
    seed, sizes, flushes, max_gap = case
    rng = np.random.default_rng(seed)
    path = tmp_path_factory.mktemp("rt") / "s.h5"
    parts, t_next = [], 0
    with SessionWriter(path, SENSOR) as w:
        for size, flush in zip(sizes, flushes, strict=True):
            ev = random_events(rng, size, t_next, max_gap)
            if size:
                t_next = int(ev.t[-1])
            parts.append(ev)
            w.append_events(ev)
            if flush:
                w.flush()
    expected = concat(parts) if parts else Events.empty(W, H, "RGBG")
    with Session.open(path) as s:
        assert s.complete and s.sensor == SENSOR
        assert s.n_events == len(expected)
        assert_same(s.events(), expected)
        # Slices at and around millisecond edges, including outside the recording.
        last = int(expected.t[-1]) if len(expected) else 0
        edges = [k * 1000 + d for k in range(0, last // 1000 + 2) for d in (-1, 0, 1)]
        points = st.sampled_from(edges + [-5, last, last + 1])
        for _ in range(5):
            t0, t1 = data.draw(points), data.draw(points)
            assert_same(s.events(t0, t1), expected.time_slice(t0, t1))
        assert_same(s.events(None, None), expected)


def test_single_event_and_empty_session(tmp_path):
    with SessionWriter(tmp_path / "empty.h5", SENSOR):
        pass
    with Session.open(tmp_path / "empty.h5") as s:
        assert (s.n_events, s.n_frames, s.n_imu, s.n_triggers) == (0, 0, 0, 0)
        assert len(s.events(0, 10**9)) == 0 and s.time_range() is None
        assert s.ms_to_idx.tolist() == [0]
    one = Events([5], [7], [123_456], [1], W, H, "RGBG")
    with SessionWriter(tmp_path / "one.h5", SENSOR) as w:
        w.append_events(one)
    with Session.open(tmp_path / "one.h5") as s:
        assert_same(s.events(), one)
        assert len(s.events(123_000, 123_456)) == 0
        assert len(s.events(123_456, 123_457)) == 1
        assert s.ms_to_idx.size == 125 and s.ms_to_idx[-1] == 1


def test_many_chunks_and_other_streams(tmp_path):
    rng = np.random.default_rng(1)
    parts, t = [], 0
    for n in (EVENT_CHUNK - 3, 5, 2 * EVENT_CHUNK + 11, 70_000):
        parts.append(random_events(rng, n, t, 5))
        t = int(parts[-1].t[-1])
    frames = Frames(rng.integers(0, 1024, (3, H, W)), [0, 40_000, 80_000], [500, 500, 800])
    imu = ImuSamples(
        np.arange(10) * 1000, rng.normal(size=(10, 3)), rng.normal(size=(10, 3)), np.full(10, 30.5)
    )
    trig = Triggers([10, 20, 30], [6, 7, 1])
    with SessionWriter(tmp_path / "s.h5", SENSOR, attrs={"firmware_version": 6}) as w:
        for p in parts:
            w.append_events(p)
        w.append_frames(frames)
        w.append_imu(imu)
        w.append_triggers(trig)
    with Session.open(tmp_path / "s.h5") as s:
        assert_same(s.events(), concat(parts))
        np.testing.assert_array_equal(s.frames().data, frames.data)
        np.testing.assert_array_equal(s.frames(30_000, 80_000).t, [40_000])
        np.testing.assert_array_equal(s.imu().accel, imu.accel)
        np.testing.assert_array_equal(s.triggers().kind, [6, 7, 1])
        assert s.attrs["firmware_version"] == 6
        assert s.attrs["t_offset_us"] == SENSOR.t_offset_us
    with h5py.File(tmp_path / "s.h5") as f:  # plain HDF5 with standard filters only
        assert f["events/t"].compression == "gzip" and f["events/x"].shuffle


def test_writer_refuses_to_overwrite_and_out_of_order(tmp_path):
    path = tmp_path / "s.h5"
    with SessionWriter(path, SENSOR) as w:
        w.append_events(Events([0], [0], [100], [1], W, H, "RGBG"))
        with pytest.raises(SessionFormatError, match="time order"):
            w.append_events(Events([0], [0], [99], [1], W, H, "RGBG"))
        with pytest.raises(SessionFormatError, match="MONO"):
            w.append_events(Events([0], [0], [200], [1], W, H))
    with pytest.raises(OutputExistsError):
        SessionWriter(path, SENSOR)


def test_periodic_flush_uses_the_injected_clock(tmp_path):
    now = [0.0]
    path = tmp_path / "s.h5"
    w = SessionWriter(path, SENSOR, flush_interval_s=1.0, clock=lambda: now[0])
    w.append_events(Events([1], [1], [10], [1], W, H, "RGBG"))
    assert w.events_flushed == 0
    now[0] = 1.5
    w.append_events(Events([1], [1], [20], [1], W, H, "RGBG"))
    assert w.events_flushed == 2
    with Session.open(path) as s:  # readable while the writer still has it open
        assert s.n_events == 2 and not s.complete
    w.close()


CRASH = r"""
import os, sys
import numpy as np
from evcap.events import Events
from evcap.session import SensorInfo, SessionWriter
rng = np.random.default_rng(3)
n = int(sys.argv[2])
t = np.cumsum(rng.integers(0, 50, 2 * n))
x, y, p = rng.integers(0, 346, 2 * n), rng.integers(0, 260, 2 * n), rng.integers(0, 2, 2 * n)
ev = Events(x, y, t, p, 346, 260)
w = SessionWriter(sys.argv[1], SensorInfo("simulated", 346, 260), flush_interval_s=1e9)
w.append_events(ev._take(slice(0, n)))
w.flush()
w.append_events(ev._take(slice(n, 2 * n)))
os.kill(os.getpid(), 9)
"""


@pytest.mark.parametrize("n", [1000, EVENT_CHUNK + 17])
def test_kill_9_keeps_everything_flushed(tmp_path, n):
    path = tmp_path / "s.h5"
    subprocess.run([sys.executable, "-c", CRASH, str(path), str(n)], check=False)
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.integers(0, 50, 2 * n))
    x, y = rng.integers(0, 346, 2 * n), rng.integers(0, 260, 2 * n)
    with Session.open(path) as s:
        assert not s.complete
        assert n <= s.n_events <= 2 * n
        ev = s.events()
        np.testing.assert_array_equal(ev.t, t[: s.n_events])
        np.testing.assert_array_equal(ev.x, x[: s.n_events])
        np.testing.assert_array_equal(ev.y, y[: s.n_events])
        t0, t1 = int(t[n // 2]), int(t[n - 1]) + 1
        kept = t[: s.n_events]
        expected = np.searchsorted(kept, t1) - np.searchsorted(kept, t0)
        assert len(s.events(t0, t1)) == expected


@pytest.fixture
def valid_session(tmp_path):
    path = tmp_path / "s.h5"
    with SessionWriter(path, SENSOR) as w:
        w.append_events(random_events(np.random.default_rng(0), 5000))
    return path


@pytest.mark.parametrize(
    "damage, message",
    [
        (lambda f: f.attrs.__setitem__("schema_version", 99), "schema version 99"),
        (lambda f: f.attrs.__delitem__("schema_version"), "not an evcap session"),
        (lambda f: f.__delitem__("imu/gyro"), "missing dataset /imu/gyro"),
        (lambda f: f["events/t"].__setitem__(100, 0), "not in time order at event 100"),
        (lambda f: f["events/x"].__setitem__(7, 400), "x=400 at event 7 is outside"),
        (lambda f: f["events/y"].__setitem__(8, 260), "y=260 at event 8 is outside"),
        (lambda f: f["events/ms_to_idx"].__setitem__(3, 4000), "ms_to_idx"),
        (lambda f: f.attrs.__setitem__("color_filter", "XX"), "unknown color_filter"),
    ],
)
def test_validation_names_the_problem(valid_session, damage, message):
    with h5py.File(valid_session, "r+") as f:
        damage(f)
    with pytest.raises(SessionFormatError, match=message):
        Session.open(valid_session)


@pytest.mark.parametrize("fraction", [0.0, 0.01, 0.1, 0.5, 0.9, 0.999])
def test_truncated_session_file(valid_session, fraction):
    # a complete session cut short (a copy or a download that stopped) is called truncated,
    # however little of it is left
    data = valid_session.read_bytes()
    valid_session.write_bytes(data[: int(len(data) * fraction)])
    message = "empty" if fraction == 0 else f"truncated: it has {int(len(data) * fraction):,} of"
    with pytest.raises(SessionFormatError, match=message):
        Session.open(valid_session)


def test_not_a_session(tmp_path):
    (tmp_path / "x.h5").write_text("hello")
    with pytest.raises(SessionFormatError, match="not a session file"):
        Session.open(tmp_path / "x.h5")
    with pytest.raises(FileNotFoundError):
        Session.open(tmp_path / "missing.h5")
    os.mkdir(tmp_path / "dir.h5")
    with pytest.raises(SessionFormatError, match="folder"):
        Session.open(tmp_path / "dir.h5")


@pytest.mark.parametrize("dtype", [np.uint16, np.int64, np.uint8, np.float32])
def test_the_fast_chunks_hold_what_the_reference_chunks_hold(dtype):
    """ISA-L's deflate streams (the writer's) and zlib's (the reference) inflate to the same
    shuffled bytes, and back to the values."""
    from evcap import chunk_codec

    rng = np.random.default_rng(7)
    a = np.cumsum(rng.integers(0, 40, 5000)).astype(dtype)
    fast, reference = chunk_codec.compress(a), chunk_codec.compress_reference(a)
    assert zlib.decompress(fast) == zlib.decompress(reference) == chunk_codec.shuffled(a).tobytes()
    np.testing.assert_array_equal(chunk_codec.decompress(fast, dtype, a.shape), a)
    frame = rng.integers(0, 1024, (1, 7, 9)).astype(np.uint16)
    np.testing.assert_array_equal(
        chunk_codec.decompress(chunk_codec.compress(frame), np.uint16, frame.shape), frame
    )


def test_chunks_written_with_zlib_before_read_as_the_new_ones(tmp_path):
    """Sessions written before ISA-L (chunks made by zlib) and after are one format: a chunk of
    either kind reads the same through HDF5's own filters."""
    from evcap import chunk_codec

    t = np.cumsum(np.random.default_rng(2).integers(0, 9, 4096)).astype(np.int64)
    with h5py.File(tmp_path / "f.h5", "w") as f:
        for name, compress in (
            ("old", chunk_codec.compress_reference),
            ("new", chunk_codec.compress),
        ):
            d = f.create_dataset(
                name, (4096,), np.int64, chunks=(4096,), compression="gzip", shuffle=True
            )
            d.id.write_direct_chunk((0,), compress(t))
    with h5py.File(tmp_path / "f.h5") as f:
        np.testing.assert_array_equal(f["old"][:], t)
        np.testing.assert_array_equal(f["new"][:], t)


def test_frames_are_chunks_of_the_standard_filters(tmp_path):
    rng = np.random.default_rng(4)
    frames = Frames(rng.integers(0, 1024, (5, H, W)), np.arange(5) * 1000, [100] * 5)
    with SessionWriter(tmp_path / "s.h5", SENSOR) as w:
        w.append_frames(frames)
    with h5py.File(tmp_path / "s.h5") as f:  # plain h5py, no evcap
        d = f["frames/data"]
        assert d.compression == "gzip" and d.shuffle and d.chunks == (1, H, W)
        np.testing.assert_array_equal(d[:], frames.data)
        np.testing.assert_array_equal(f["frames/t"][:], frames.t)


@pytest.mark.parametrize("kind", ["events", "frames"])
def test_ctrl_c_while_a_chunk_is_written_leaves_a_whole_session(tmp_path, monkeypatch, kind):
    """Ctrl-C lands where the writer waits for a compressed chunk: the writer still closes
    (Ctrl-C keeps what was appended) and the session holds all of it."""
    from concurrent.futures import Future

    result, calls = Future.result, [0]

    def interrupted_once(self, timeout=None):
        calls[0] += 1
        if calls[0] == 3:
            raise KeyboardInterrupt
        return result(self, timeout)

    monkeypatch.setattr(Future, "result", interrupted_once)
    rng = np.random.default_rng(0)
    n = 24 * EVENT_CHUNK  # past the compressors' queue: appending waits for chunks
    x, y = rng.integers(0, W, n), rng.integers(0, H, n)
    events = Events(x, y, np.arange(n), [1] * n, W, H, "RGBG")
    frames = Frames(rng.integers(0, 1024, (30, H, W)), np.arange(30) * 1000, [10] * 30)
    appended = 0
    with pytest.raises(KeyboardInterrupt), SessionWriter(tmp_path / "s.h5", SENSOR) as w:
        if kind == "events":
            w.append_events(events)
        else:
            for i in range(len(frames)):
                appended = i + 1  # the frame being appended when Ctrl-C came is kept
                w.append_frames(Frames(frames.data[i : i + 1], frames.t[i : i + 1], [10]))
    monkeypatch.setattr(Future, "result", result)
    with Session.open(tmp_path / "s.h5") as s:
        assert s.complete
        if kind == "events":
            np.testing.assert_array_equal(s.events().t, events.t)
            np.testing.assert_array_equal(s.events().x, events.x)
        else:
            assert 0 < appended < 30  # Ctrl-C came while frames were being written
            np.testing.assert_array_equal(s.frames().data, frames.data[:appended])
            np.testing.assert_array_equal(s.frames().t, frames.t[:appended])
