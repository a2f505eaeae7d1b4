"""The recorder: a running DAVIS346 -> a session file, losing nothing the camera sent.

It decodes what the reader thread received and appends it to the session as it comes (the
session writer flushes every 0.5 s). Stopping (a stop request, the duration, the end of a
replay fixture) stops the camera, takes in what was still in flight, decodes it and closes the
session. A lost camera or a failing disk end the recording with what was received; the
session stays valid either way.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

from evcap.acquire import protocol as P
from evcap.acquire.decoder import Decoded, StreamDecoder
from evcap.acquire.device import Davis346
from evcap.errors import (
    DeviceError,
    DeviceLostError,
    DiskFullError,
    OutputExistsError,
    SessionWriteError,
)
from evcap.session import SensorInfo, SessionWriter

STATS_INTERVAL_S = 1.0  # how often the device's dropped-event counters are read


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
    min_free_bytes: int = 200 << 20  # stop (cleanly) when the disk has less free space


@dataclass
class RecordResult:
    path: Path
    # "stopped", "duration", "end of replay", "camera lost", "disk full", "write failed"
    end_reason: str
    events: int = 0
    frames: int = 0
    imu: int = 0
    triggers: int = 0
    device_dropped: dict = field(default_factory=dict)
    decoder: dict = field(default_factory=dict)
    reader: dict = field(default_factory=dict)
    error: str | None = None  # what went wrong, for "camera lost" and "write failed"


class Recorder:
    """Records ``device`` into the session at ``path``. ``on_batch`` (if given) sees every
    decoded batch; it runs in the recording thread and must be quick."""

    def __init__(
        self,
        device: Davis346,
        path: str | Path,
        options: RecordOptions | None = None,
        *,
        on_batch: Callable[[Decoded], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.device = device
        self.path = Path(path)
        self.options = options or RecordOptions()
        self.on_batch = on_batch
        self._clock = clock
        self.stop_requested = threading.Event()
        self.result = RecordResult(self.path, "stopped")
        self.device_dropped: dict[str, int] = {}

    def stop(self) -> None:
        """Ask the recording to end (thread-safe; also from a signal handler)."""
        self.stop_requested.set()

    def _sensor(self, t_offset_us: int) -> SensorInfo:
        info = self.device.info
        g = info.geometry
        return SensorInfo(
            info.model, g.width, g.height, info.color_filter, info.serial, t_offset_us
        )

    def _attrs(self) -> dict:
        o = self.options
        return {
            **self.device.info.as_attrs(),
            "device": (
                f"replay:{self.device.spec.path}"
                if self.device.spec.kind == "replay"
                else f"usb:{self.device.info.serial}"
            ),
            "biases": json.dumps(o.biases),
            "settings": json.dumps(asdict(o.settings)),
            "aps_enabled": o.aps,
            "imu_enabled": o.imu,
        }

    def run(self) -> RecordResult:
        """Record until stopped; returns what happened. Raises DeviceLostError (after closing
        the session) when the camera vanished, and SessionWriteError when the disk failed."""
        o, dev = self.options, self.device
        if self.path.exists() and not o.overwrite:
            raise OutputExistsError(f"{self.path} exists; choose another name or pass --force")
        dev.configure(o.biases, o.settings)
        decoder = StreamDecoder(dev.info.geometry)
        reader = dev.start(
            aps=o.aps, imu=o.imu, transfers=o.transfers, transfer_size=o.transfer_size
        )
        try:
            writer = SessionWriter(
                self.path,
                self._sensor(dev.clock_started_us),
                attrs=self._attrs(),
                overwrite=o.overwrite,
                clock=self._clock,
            )
        except BaseException:
            dev.stop()
            raise
        started = self._clock()
        next_stats = started
        r = self.result
        try:
            while True:
                self._write(writer, decoder, reader.take(0.05))
                writer.flush_if_due()
                now = self._clock()
                if now >= next_stats and dev.streaming:
                    self._read_stats()
                    next_stats = now + STATS_INTERVAL_S
                    free = writer.free_bytes()
                    if free is not None and free < o.min_free_bytes:
                        r.end_reason = "disk full"
                        r.error = f"only {free / 1e6:.0f} MB left on the disk"
                        break
                if reader.lost or reader.failure:
                    r.end_reason, r.error = "camera lost", reader.lost or repr(reader.failure)
                    break
                if self.stop_requested.is_set():
                    break
                if o.duration_s is not None and now - started >= o.duration_s:
                    r.end_reason = "duration"
                    break
                if dev.stream_exhausted:
                    r.end_reason = "end of replay"
                    break
            if r.end_reason != "camera lost":
                self._read_stats()
            dev.stop()  # the reader takes in what was in flight, then ends
            self._write(writer, decoder, reader.take())
            r.decoder, r.reader = decoder.counters, asdict(reader.stats)
            r.device_dropped = dict(self.device_dropped)
            writer.close(
                {
                    "end_reason": r.end_reason,
                    "device_dropped_events": json.dumps(r.device_dropped),
                    "host_dropped_events": r.decoder["dvs_out_of_range"],
                    "decoder_counters": json.dumps(r.decoder),
                    "usb_transfers": json.dumps(r.reader),
                }
            )
        except SessionWriteError as e:
            r.end_reason, r.error = "write failed", str(e)
            dev.stop()
            writer.abort()
            raise
        except BaseException:
            dev.stop()
            writer.abort()
            raise
        if r.end_reason == "camera lost":
            raise DeviceLostError(
                f"the camera was lost ({r.error}); {self.path} holds everything received "
                f"before: {r.events:,} events, {r.frames:,} frames"
            )
        if r.end_reason == "disk full":
            raise DiskFullError(
                f"recording stopped: {r.error}. {self.path} is complete up to now: "
                f"{r.events:,} events, {r.frames:,} frames"
            )
        return r

    def _read_stats(self) -> None:
        try:
            self.device_dropped = self.device.dropped_counters()
        except DeviceError:
            pass  # a camera being unplugged: the reader reports it

    def _write(self, writer: SessionWriter, decoder: StreamDecoder, chunks: list[bytes]) -> None:
        if not chunks:
            return
        d = decoder.decode(b"".join(chunks))
        writer.append_events(d.events)
        writer.append_frames(d.frames)
        writer.append_imu(d.imu)
        writer.append_triggers(d.triggers)
        r = self.result
        r.events += len(d.events)
        r.frames += len(d.frames)
        r.imu += len(d.imu)
        r.triggers += len(d.triggers)
        if self.on_batch is not None:
            self.on_batch(d)
