"""The session's writer thread: order, back-pressure, errors, and a kill -9 with a backlog."""

import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from evcap.acquire.decoder import Decoded
from evcap.acquire.writer_thread import WriterThread, batch_bytes
from evcap.errors import SessionWriteError
from evcap.events import Events
from evcap.session import SensorInfo, Session, SessionWriter
from evcap.streams import Frames, ImuSamples, Triggers

FIXTURES = Path(__file__).resolve().parents[2] / "hw-fixtures"
W, H = 346, 260


def batch(t0: int, n: int = 1000, frames: int = 0) -> Decoded:
    rng = np.random.default_rng(t0)
    t = t0 + np.arange(n, dtype=np.int64)
    events = Events(rng.integers(0, W, n), rng.integers(0, H, n), t, rng.integers(0, 2, n), W, H)
    data = rng.integers(0, 1024, (frames, H, W))
    return Decoded(
        events,
        Frames(data, t0 + np.arange(frames), np.full(frames, 10)),
        ImuSamples(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)),
        Triggers(np.zeros(0), np.zeros(0)),
    )


class SlowWriter:
    """Stands in for a SessionWriter: each batch takes ``seconds``; fails when told to."""

    def __init__(self, seconds: float = 0.0, fail_at: int | None = None) -> None:
        self.seconds, self.fail_at = seconds, fail_at
        self.events: list[int] = []
        self.closed = self.aborted = False

    def append_events(self, events: Events) -> None:
        time.sleep(self.seconds)
        if self.fail_at is not None and len(self.events) >= self.fail_at:
            raise SessionWriteError("writing s.h5 failed (the disk is full)")
        self.events.append(int(events.t[0]))

    def append_frames(self, frames) -> None:
        pass

    append_imu = append_triggers = append_frames

    def flush_if_due(self) -> None:
        pass

    def close(self, attrs=None) -> None:
        self.closed = True

    def abort(self) -> None:
        self.aborted = True


def test_batches_and_settings_are_appended_in_order(tmp_path):
    path = tmp_path / "s.h5"
    thread = WriterThread(SessionWriter(path, SensorInfo("simulated", W, H)))
    thread.put(batch(0, frames=2))
    thread.append_setting(1500, "bias.OnBn", 7)
    thread.put(batch(2000, frames=1))
    thread.close({"end_reason": "stopped"})
    with Session.open(path) as s:
        assert s.complete and s.n_events == 2000 and s.n_frames == 3
        np.testing.assert_array_equal(s.events().t[[0, 999, 1000]], [0, 999, 2000])
        np.testing.assert_array_equal(s.frames().data[2], batch(2000, frames=1).frames.data[0])
        assert s.settings_log() == [(1500, "bias.OnBn", 7)]


def test_a_full_queue_makes_the_recorder_wait_and_report():
    writer = SlowWriter(seconds=0.05)
    size = batch_bytes(batch(0))
    thread = WriterThread(writer, max_queued_bytes=2 * size)
    waits, peak = [], [0]

    def wait():
        waits.append(1)
        peak[0] = max(peak[0], thread.queued_bytes)

    for k in range(8):
        thread.put(batch(k * 1000), wait)
        assert thread.queued_bytes <= 2 * size
    assert waits and peak[0] > 0
    thread.close()
    assert writer.events == [k * 1000 for k in range(8)] and writer.closed
    assert thread.queued_bytes == 0


def test_a_write_error_reaches_the_recorder_and_ends_the_thread():
    writer = SlowWriter(fail_at=2)
    thread = WriterThread(writer)
    with pytest.raises(SessionWriteError, match="disk is full"):
        for k in range(100):
            thread.put(batch(k * 1000))
            time.sleep(0.01)
    with pytest.raises(SessionWriteError):
        thread.close()
    thread.abort()
    assert writer.events == [0, 1000] and writer.aborted and not writer.closed


def test_an_error_found_at_close_aborts_the_session():
    """The write error comes with the last batch, so the recorder first hears of it when it
    closes: the session is aborted (what was flushed kept, the file let go), and it is said."""
    writer = SlowWriter(fail_at=2)
    thread = WriterThread(writer)
    for k in range(3):
        thread.put(batch(k * 1000))
    with pytest.raises(SessionWriteError, match="disk is full"):
        thread.close()
    assert writer.aborted and not writer.closed


def test_abort_leaves_what_is_queued():
    writer = SlowWriter(seconds=0.1)
    thread = WriterThread(writer)
    for k in range(10):
        thread.put(batch(k * 1000))
    thread.abort()
    assert len(writer.events) < 10 and writer.aborted
    assert not any(t.name == "evcap-session-writer" for t in threading.enumerate())


KILL_WITH_A_BACKLOG = r"""
import os, sys
from evcap.acquire.device import Davis346, DeviceSpec
from evcap.acquire.recorder import Recorder, Stats
from evcap.session import SessionWriter
import evcap.acquire.recorder as recorder_module

recorder_module.STATS_INTERVAL_S = 0.05
slow = SessionWriter.append_events
def append_events(self, events):
    import time
    time.sleep(0.05)  # a slow disk: the writer thread falls behind the camera
    slow(self, events)
SessionWriter.append_events = append_events

def on_event(event):
    rec = recorder.recording
    if isinstance(event, Stats) and rec is not None and rec.writer.events_flushed > 0:
        if event.backlog.decoded_bytes > 0:
            print(rec.writer.events_flushed, flush=True)
            os.kill(os.getpid(), 9)

with Davis346.open(DeviceSpec("replay", path=sys.argv[1], speed=2.0)) as cam:
    recorder = Recorder(cam, sys.argv[2], on_event=on_event)
    recorder.run()
print("not killed")
"""


def test_kill_9_with_a_backlog_in_the_writer_thread_keeps_what_was_flushed(tmp_path):
    """Killed while the writer thread has batches queued (a slow disk): the session opens
    with every event flushed before, each as the camera sent it, and every frame it holds
    complete."""
    out = tmp_path / "s.h5"
    fixture = FIXTURES / "color-scene"
    r = subprocess.run(
        [sys.executable, "-c", KILL_WITH_A_BACKLOG, str(fixture), str(out)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == -9, (r.stdout, r.stderr)
    flushed = int(r.stdout.split()[0])
    exp = np.load(fixture / "expected.npz")
    with Session.open(out) as s:
        assert not s.complete
        assert flushed <= s.n_events < 60_000
        ev = s.events()
        for k in "xytp":
            np.testing.assert_array_equal(getattr(ev, k), exp[f"events_{k}"][: s.n_events])
        frames = s.frames()
        for data, t in zip(frames.data, frames.t, strict=True):
            i = int(np.searchsorted(exp["frames_t"], t))
            np.testing.assert_array_equal(data, exp["frames_data"][i])
