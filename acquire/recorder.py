"""The recorder: a running DAVIS346 -> session files, losing nothing the camera sent.

It decodes what the reader thread received, hands every batch to ``on_batch`` (the monitor's
live view) and, while a recording is open, hands it to the session's writer thread, which
appends it and flushes every 0.5 s (so that decoding and writing run side by side).
``evcap record`` keeps one recording open for the whole run; the monitor opens and closes
recordings on request. Stopping (a stop request, the duration, the end of a
replay fixture) stops the camera, takes in what was still in flight, decodes it and closes the
session. A lost camera or a failing disk end the recording with what was received; the session
stays valid either way.

Other threads talk to a running recorder only through its request methods (``stop``,
``start_recording``, ``stop_recording``, ``set_bias``); it reports back through ``on_event``
with the event dataclasses below. Every second it reports the device's dropped-event counters
and the backlog (``Stats``), also while it waits for a writer that has fallen behind, so that
users see the host falling behind while it happens.
"""

from __future__ import annotations

import json
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Literal, get_args

from evcap.acquire import protocol as P
from evcap.acquire.backlog import Backlog
from evcap.acquire.decoder import Decoded, StreamDecoder
from evcap.acquire.device import Davis346
from evcap.acquire.writer_thread import WriterThread
from evcap.errors import (
    DeviceError,
    DeviceLostError,
    DiskFullError,
    EvcapError,
    OutputExistsError,
    SessionWriteError,
)
from evcap.events import Events
from evcap.session import SensorInfo, SessionWriter
from evcap.streams import Frames, ImuSamples, Triggers

STATS_INTERVAL_S = 1.0  # how often the device's counters and the free disk space are read

# How a recording ended: written into the session file (its end_reason attribute) and shown to
# users, so the values are kept as they are.
EndReason = Literal[
    "stopped", "duration", "end of replay", "camera lost", "disk full", "write failed"
]
END_REASONS: tuple[EndReason, ...] = get_args(EndReason)
# the ends the monitor reports as information; the others it shows as errors
NORMAL_ENDS: tuple[EndReason, ...] = ("stopped", "end of replay")


@dataclass
class RecordOptions:
    duration_s: float | None = None  # stop after this long (None: until stopped)
    aps: bool = True  # record APS frames
    imu: bool = True  # record IMU samples
    biases: dict[str, int] = field(default_factory=P.default_bias_codes)  # bias codes by name
    settings: P.Settings = field(default_factory=P.Settings)  # camera settings
    transfers: int = 8  # bulk transfers in flight
    transfer_size: int = 8192  # bytes per transfer
    overwrite: bool = False  # replace an existing session file
    min_free_bytes: int = 200 << 20  # stop recording (cleanly) below this much free disk space


@dataclass
class RecordResult:
    """What one recording (one session file) holds, and how it ended."""

    path: Path
    end_reason: EndReason = "stopped"
    events: int = 0
    frames: int = 0
    imu: int = 0
    triggers: int = 0
    device_dropped: dict = field(default_factory=dict)
    decoder: dict = field(default_factory=dict)
    reader: dict = field(default_factory=dict)
    error: str | None = None  # what went wrong, for "camera lost", "disk full", "write failed"
    largest_backlog_bytes: int = 0  # the most data received and not yet written, at a Stats
    behind_seconds: int = 0  # Stats (one a second) that found the host falling behind


# -- what the recorder reports (through on_event, from its own thread) -------------------------


@dataclass(frozen=True)
class RecordingStarted:
    path: Path


@dataclass(frozen=True)
class RecordingStopped:
    result: RecordResult


@dataclass(frozen=True)
class BiasChanged:
    name: str
    code: int


@dataclass(frozen=True)
class CameraLost:
    reason: str


@dataclass(frozen=True)
class RecorderError:
    """A request could not be carried out (the recorder goes on)."""

    message: str


@dataclass(frozen=True)
class Stats:
    """Read every second: the device's dropped-event counters, the free disk space and the
    backlog."""

    device_dropped: dict
    free_bytes: int | None
    backlog: Backlog = field(default_factory=Backlog)

    @property
    def dropped(self) -> int:
        """Events the camera dropped since it started, all counters together."""
        return sum(self.device_dropped.values())


def _shifted(d: Decoded, t0: int) -> Decoded:
    """The batch with ``t0`` subtracted from its times (a session starts at its t = 0)."""
    if t0 == 0:
        return d
    e = d.events
    return Decoded(
        Events._unchecked(e.x, e.y, e.t - t0, e.p, e.width, e.height, e.color_filter),
        Frames(d.frames.data, d.frames.t - t0, d.frames.exposure_us),
        ImuSamples(d.imu.t - t0, d.imu.accel, d.imu.gyro, d.imu.temperature),
        Triggers(d.triggers.t - t0, d.triggers.kind),
    )


class _Recording:
    """One session being written (by a writer thread of its own)."""

    def __init__(self, writer: SessionWriter, t0: int) -> None:
        self.writer = writer
        self.thread = WriterThread(writer)
        self.t0 = t0  # decoder time of the session's t = 0
        self.result = RecordResult(writer.path)

    def write(self, d: Decoded, wait: Callable[[], None] | None = None) -> None:
        """Hand the batch to the writer thread (``wait`` is called while its queue is full)."""
        d = _shifted(d, self.t0)
        self.thread.put(d, wait)
        r = self.result
        r.events += len(d.events)
        r.frames += len(d.frames)
        r.imu += len(d.imu)
        r.triggers += len(d.triggers)


class Recorder:
    """Runs ``device`` and records it into session files.

    With ``path``, the recording into it lasts the whole run (``evcap record``): the run ends
    when it does, and ``run`` raises DeviceLostError or SessionWriteError after closing it
    when the camera or the disk failed. Without, the run only watches until recordings are
    asked for with ``start_recording`` (the monitor). ``on_batch`` sees every decoded batch
    and ``on_event`` every event; ``on_tick`` is called at every turn of the loop, data or not.
    All run in the recorder's thread and must be quick.
    """

    def __init__(
        self,
        device: Davis346,
        path: str | Path | None = None,
        options: RecordOptions | None = None,
        *,
        on_batch: Callable[[Decoded], None] | None = None,
        on_event: Callable[[object], None] | None = None,
        on_tick: Callable[[], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.device = device
        self.path = Path(path) if path is not None else None
        self.options = options or RecordOptions()
        self.on_batch = on_batch
        self.on_event = on_event or (lambda event: None)
        self.on_tick = on_tick  # called every turn of the loop (at least 20 times a second)
        self._clock = clock
        self.stop_requested = threading.Event()
        self._requests: queue.SimpleQueue[tuple] = queue.SimpleQueue()
        self._recording: _Recording | None = None
        self.biases = dict(self.options.biases)  # in force now
        self.result: RecordResult | None = None  # of the last recording
        self.device_dropped: dict[str, int] = {}
        self.decoder: StreamDecoder | None = None
        self.end_reason: EndReason = "stopped"
        self._next_stats = 0.0  # clock time of the next Stats
        self._disk_low = False  # a Stats read while waiting for the writer found the disk full

    # -- requests from other threads -----------------------------------------------------------

    def stop(self) -> None:
        """Ask the run to end (thread-safe; also from a signal handler)."""
        self.stop_requested.set()

    def start_recording(self, path: str | Path) -> None:
        self._requests.put(("start", Path(path)))

    def stop_recording(self) -> None:
        self._requests.put(("stop",))

    def set_bias(self, name: str, code: int) -> None:
        """Write a bias to the camera now (and log it in the open session)."""
        self._requests.put(("bias", name, code))

    @property
    def recording(self) -> _Recording | None:
        return self._recording

    # -- the run -------------------------------------------------------------------------------

    def _sensor(self, t_offset_us: int) -> SensorInfo:
        info = self.device.info
        g = info.geometry
        return SensorInfo(
            info.model, g.width, g.height, info.color_filter, info.serial, t_offset_us
        )

    def _attrs(self) -> dict:
        o = self.options
        spec = self.device.spec
        return {
            **self.device.info.as_attrs(),
            "device": (
                f"replay:{spec.path}" if spec.kind == "replay" else f"usb:{self.device.info.serial}"
            ),
            "biases": json.dumps(self.biases),
            "settings": json.dumps(asdict(o.settings)),
            "aps_enabled": o.aps,
            "imu_enabled": o.imu,
        }

    def _open(self, path: Path) -> None:
        """Open a recording into ``path``; its t = 0 is now."""
        if path.exists() and not self.options.overwrite:
            raise OutputExistsError(f"{path} exists; choose another name or pass --force")
        t0 = self.decoder.pending_since_us  # a frame being read keeps its exposure start
        writer = SessionWriter(
            path,
            self._sensor(self.device.clock_started_us + t0),
            attrs=self._attrs(),
            overwrite=self.options.overwrite,
            clock=self._clock,
        )
        self._recording = _Recording(writer, t0)
        self.on_event(RecordingStarted(path))

    def _close(self, end_reason: EndReason, error: str | None = None) -> RecordResult:
        """Close the open recording normally (its final attributes, complete = True)."""
        rec, self._recording = self._recording, None
        r = rec.result
        r.end_reason, r.error = end_reason, error
        r.decoder = self.decoder.counters
        r.reader = asdict(self.device.reader.stats)
        r.device_dropped = dict(self.device_dropped)
        try:
            rec.thread.close(
                {
                    "end_reason": end_reason,
                    "device_dropped_events": json.dumps(r.device_dropped),
                    "host_dropped_events": r.decoder["dvs_out_of_range"],
                    "decoder_counters": json.dumps(r.decoder),
                    "usb_transfers": json.dumps(r.reader),
                }
            )
        except SessionWriteError as e:
            r.end_reason, r.error = "write failed", str(e)
            raise
        finally:
            self.result = r
            self.on_event(RecordingStopped(r))
        return r

    def _fail(self, error: SessionWriteError) -> RecordResult:
        """The open recording's disk failed: keep what was flushed."""
        rec, self._recording = self._recording, None
        rec.thread.abort()
        r = rec.result
        r.end_reason, r.error = "write failed", str(error)
        self.result = r
        self.on_event(RecordingStopped(r))
        return r

    def _apply_requests(self) -> None:
        while True:
            try:
                request = self._requests.get_nowait()
            except queue.Empty:
                return
            try:
                if request[0] == "start" and self._recording is None:
                    self._open(request[1])
                elif request[0] == "stop" and self._recording is not None:
                    self._close("stopped")
                elif request[0] == "bias":
                    _, name, code = request
                    self.device.set_bias(name, code)
                    self.biases[name] = code
                    if self._recording is not None:
                        t = self.decoder.now_us - self._recording.t0
                        self._recording.thread.append_setting(t, f"bias.{name}", code)
                    self.on_event(BiasChanged(name, code))
            except EvcapError as e:
                self.on_event(RecorderError(str(e)))

    def _take(self, chunks: list[bytes]) -> None:
        if not chunks:
            return
        d = self.decoder.decode(b"".join(chunks))
        if self._recording is not None:
            try:
                self._recording.write(d, self._report_while_waiting)
            except SessionWriteError as e:
                if self.path is not None:
                    raise
                self._fail(e)
        if self.on_batch is not None:
            self.on_batch(d)

    def backlog(self) -> Backlog:
        """What was received and is not yet written (or decoded, while not recording)."""
        reader, rec = self.device.reader, self._recording
        b = Backlog(reader.queued_bytes, reader.max_queued_bytes, reader.held_transfers)
        if rec is not None:
            q = rec.thread
            b = replace(b, decoded_bytes=q.queued_bytes, decoded_limit=q.max_queued_bytes)
        return b

    def _read_stats(self) -> Stats:
        """The device's counters, the free disk space and the backlog, reported."""
        self._next_stats = self._clock() + STATS_INTERVAL_S
        try:
            self.device_dropped = self.device.dropped_counters()
        except DeviceError:
            pass  # a camera being unplugged: the reader reports it
        rec = self._recording
        free = rec.writer.free_bytes() if rec is not None else None
        stats = Stats(dict(self.device_dropped), free, self.backlog())
        if rec is not None:
            r = rec.result
            r.largest_backlog_bytes = max(r.largest_backlog_bytes, stats.backlog.total_bytes)
            r.behind_seconds += stats.backlog.falling_behind
        self.on_event(stats)
        return stats

    def _report_while_waiting(self) -> None:
        """Called while the writer's queue is full: the monitor goes on, and so do Stats (a
        disk found almost full then is acted on by the main loop, between batches)."""
        if self.on_tick is not None:
            self.on_tick()
        if self._clock() >= self._next_stats and self.device.streaming:
            self._disk_low = self._too_little(self._read_stats().free_bytes)

    def _too_little(self, free: int | None) -> bool:
        return free is not None and free < self.options.min_free_bytes

    def _stats(self) -> bool:
        """Read and report the stats; False if the disk is full (the recording is closed)."""
        free = self._read_stats().free_bytes
        self._disk_low = False
        if self._too_little(free):
            self._close("disk full", f"only {free / 1e6:.0f} MB left on the disk")
            return False
        return True

    def run(self) -> RecordResult | None:
        """Run until stopped; returns the last recording's result (None if there was none)."""
        o, dev = self.options, self.device
        if self.path is not None and self.path.exists() and not o.overwrite:
            raise OutputExistsError(f"{self.path} exists; choose another name or pass --force")
        dev.configure(self.biases, o.settings)
        self.decoder = StreamDecoder(dev.info.geometry)
        self.decoder.decode(b"")  # compiles the decoder (or loads it) before data flows
        reader = dev.start(
            aps=o.aps, imu=o.imu, transfers=o.transfers, transfer_size=o.transfer_size
        )
        try:
            if self.path is not None:
                self._open(self.path)
            started = self._next_stats = self._clock()
            while True:
                self._apply_requests()
                self._take(reader.take(0.01))
                if self.on_tick is not None:
                    self.on_tick()
                now = self._clock()
                due = (now >= self._next_stats or self._disk_low) and dev.streaming
                if due and not self._stats() and self.path is not None:
                    self.end_reason = "disk full"
                    break
                if reader.lost or reader.failure:
                    self.end_reason = "camera lost"
                    break
                if self.stop_requested.is_set():
                    break
                if o.duration_s is not None and now - started >= o.duration_s:
                    self.end_reason = "duration"
                    break
                if dev.stream_exhausted:
                    self.end_reason = "end of replay"
                    break
            lost = reader.lost or (repr(reader.failure) if reader.failure else None)
            if not lost:
                self._stats()
            self._apply_requests()  # those made as the loop ended
            dev.stop()  # the reader takes in what was in flight, then ends
            while chunks := reader.take():
                self._take(chunks)
            self._apply_requests()
            if lost:
                self.on_event(CameraLost(lost))
            if self._recording is not None:
                self._close(self.end_reason, lost)
        except SessionWriteError as e:
            dev.stop()
            if self._recording is not None:
                self._fail(e)
            raise
        except BaseException:
            dev.stop()
            if self._recording is not None:
                self._recording.thread.abort()
            raise
        r = self.result
        if self.path is not None and r is not None:
            if r.end_reason == "camera lost":
                raise DeviceLostError(
                    f"the camera was lost ({r.error}); {r.path} holds everything received "
                    f"before: {r.events:,} events, {r.frames:,} frames"
                )
            if r.end_reason == "disk full":
                raise DiskFullError(
                    f"recording stopped: {r.error}. {r.path} is complete up to now: "
                    f"{r.events:,} events, {r.frames:,} frames"
                )
        return r
