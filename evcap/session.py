"""The session file: one HDF5 file per recording, the format every step reads and writes.

The layout is documented in docs/session-format.md. ``SessionWriter`` creates a session and
appends to it while it is recorded (HDF5 SWMR mode, flushed periodically, so that a crash keeps
everything up to the last flush); ``Session`` opens one, checks it and reads time slices
without reading the whole file.
"""

from __future__ import annotations

import contextlib
import ctypes
import datetime
import gc
import os
import re
import shutil
import sys
import time
import traceback
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from evcap import __version__, chunk_codec
from evcap.errors import (
    InputNotFoundError,
    OutputExistsError,
    SessionFormatError,
    SessionWriteError,
)
from evcap.events import COLOR_FILTERS, Events, check_color_filter, first_unsorted
from evcap.hdf5_attributes import from_hdf5, read_attributes, to_hdf5
from evcap.streams import APS_MAX, Frames, ImuSamples, TriggerKind, Triggers

SCHEMA_VERSION = 1
EVENT_CHUNK = 1 << 17
"""Events per HDF5 chunk in /events/{x,y,t,p}."""
DEFLATE_LEVEL = 1
"""The deflate filter's level as HDF5 records it (chunk_codec makes the event chunks)."""
FLUSH_INTERVAL_S = 0.5
"""How often the writer flushes by default; a crash loses at most this much data."""
T_FILL = -1
"""Fill value of /events/t: a timestamp no written event has, so unwritten chunks show."""

EVENT_FIELDS = {"x": np.uint16, "y": np.uint16, "t": np.int64, "p": np.uint8}
RESERVED_GROUPS = ("calibration", "poses", "gt")
"""Groups that later steps add (calibration, poses, ground truth of simulated sessions)."""
_SMALL_CHUNK = 4096
MAX_INFLIGHT = 16
"""Chunks handed to the compressors and not yet written: past this, appending waits."""
_READ_BLOCK = 8 * EVENT_CHUNK
_READ_CACHE = 16 << 20  # HDF5 chunk cache per dataset: a few event chunks of each field


@dataclass(frozen=True)
class SensorInfo:
    """What the session's data comes from; stored as root attributes."""

    sensor: str  # model: "DAVIS346", "Color-DAVIS346", "simulated", ...
    width: int  # pixels
    height: int  # pixels
    color_filter: str = "MONO"  # "MONO", or the Bayer cell such as "RGBG" (see evcap.events)
    serial: str = ""  # the camera's serial number, "" when unknown
    t_offset_us: int = 0  # absolute time (Unix microseconds) of t = 0

    def __post_init__(self) -> None:
        check_color_filter(self.color_filter)
        if not (0 < self.width <= 65536 and 0 < self.height <= 65536):
            raise SessionFormatError(f"sensor size {self.width} x {self.height} is not valid")


def _ms_entries(t_new: np.ndarray, n_before: int, ms_done: int) -> np.ndarray:
    """The millisecond-index entries that events ``t_new`` (following ``n_before`` earlier ones,
    all earlier than ms ``ms_done``) settle: the first event at or after each millisecond
    ms_done .. t_new[-1] // 1000."""
    if t_new.size == 0:
        return np.zeros(0, np.int64)
    ms = np.arange(ms_done, int(t_new[-1]) // 1000 + 1, dtype=np.int64)
    return n_before + np.searchsorted(t_new, ms * 1000, "left").astype(np.int64)


def _now_iso() -> str:
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")


class SessionWriter:
    """Create a session file and append streams to it in time order.

    Event chunks are compressed by worker threads and written directly (HDF5's deflate and
    shuffle filters, so that any HDF5 reader opens the file). The file is flushed every
    ``flush_interval_s`` of ``clock`` time; ``close`` writes the final attributes. Use it as a
    context manager. ``frame_bits`` is the number of significant bits of the frames' values
    (10 from the camera; 8 for frames imported from 8-bit files, stored as value << 2).
    """

    def __init__(
        self,
        path: str | os.PathLike,
        sensor: SensorInfo,
        *,
        attrs: dict | None = None,
        overwrite: bool = False,
        flush_interval_s: float = FLUSH_INTERVAL_S,
        clock: Callable[[], float] = time.monotonic,
        workers: int | None = None,
        frame_bits: int = 10,
    ) -> None:
        self.path = Path(path)
        self.sensor = sensor
        if self.path.exists() and not overwrite:
            raise OutputExistsError(f"{self.path} exists; choose another name or allow overwriting")
        self._clock = clock
        self._flush_interval = flush_interval_s
        self._last_flush = clock()
        self._pool = ThreadPoolExecutor(max_workers=workers or min(4, os.cpu_count() or 1))
        # Chunks being compressed, written in the order they were handed over: (dataset,
        # chunk offset, the dataset's length once written, the compressed bytes, the rows of
        # other datasets that go in after it: a frame's time and exposure follow its data).
        self._inflight: deque[tuple[str, tuple, int, Future, dict | None]] = deque()
        # Chunks made and not yet handed over (dataset, offset, length, values, rows): the
        # counters move first, then these go out; what an interrupt (Ctrl-C) left here goes
        # out at the next flush, so that a writer closed after one is whole.
        self._unsent: deque[tuple[str, tuple, int, np.ndarray, dict | None]] = deque()
        try:
            # No chunk cache: every write goes to the file at once, so that nothing is left to
            # flush when a dataset is closed (after a write error that could never succeed).
            self._file = h5py.File(self.path, "w", libver="latest", rdcc_nbytes=0)
        except OSError as e:
            self._pool.shutdown()
            raise SessionWriteError(f"cannot create {self.path}: {e}") from e
        self._closed = False
        self._failed = False  # a write failed: HDF5 cannot finish the file
        f = self._file
        root = {
            "schema_version": SCHEMA_VERSION,
            "sensor": sensor.sensor,
            "serial": sensor.serial,
            "width": sensor.width,
            "height": sensor.height,
            "color_filter": sensor.color_filter,
            "t_offset_us": int(sensor.t_offset_us),
            "evcap_version": __version__,
            "created": _now_iso(),
            "complete": False,
        }
        for key, value in {**root, **(attrs or {})}.items():
            f.attrs[key] = to_hdf5(value)
        h, w = sensor.height, sensor.width
        self._ds: dict[str, h5py.Dataset] = {}

        def series(group: str, name: str, dtype: type, unit: str, shape: tuple = (), **kw):
            chunks = kw.pop("chunks", (_SMALL_CHUNK, *shape))
            d = f.create_dataset(
                f"{group}/{name}",
                shape=(0, *shape),
                maxshape=(None, *shape),
                dtype=dtype,
                chunks=chunks,
                compression="gzip",
                compression_opts=DEFLATE_LEVEL,
                shuffle=np.dtype(dtype).itemsize > 1,
                **kw,
            )
            d.attrs["unit"] = unit
            # Kept open: a dataset closed by garbage collection flushes then, where a write
            # error (a full disk) could not be reported.
            self._ds[f"{group}/{name}"] = d

        for name, dtype in EVENT_FIELDS.items():
            fill = {"fillvalue": T_FILL} if name == "t" else {}
            unit = {"x": "pixel", "y": "pixel", "t": "us", "p": "1 = ON, 0 = OFF"}[name]
            series("events", name, dtype, unit, chunks=(EVENT_CHUNK,), **fill)
        series("events", "ms_to_idx", np.int64, "event index")
        series("frames", "data", np.uint16, "ADC counts, 10 bit", (h, w), chunks=(1, h, w))
        f["frames"].attrs["precision_bits"] = frame_bits
        series("frames", "t", np.int64, "us")
        series("frames", "exposure_us", np.int64, "us")
        series("imu", "t", np.int64, "us")
        series("imu", "accel", np.float32, "m/s^2", (3,))
        series("imu", "gyro", np.float32, "rad/s", (3,))
        series("imu", "temperature", np.float32, "degC")
        series("triggers", "t", np.int64, "us")
        series("triggers", "kind", np.uint8, "TriggerKind")
        f["triggers/kind"].attrs["names"] = ",".join(k.name for k in TriggerKind)
        series("settings_log", "t", np.int64, "us")
        series("settings_log", "value", np.int64, "register value")
        log = f.create_dataset(
            "settings_log/name",
            shape=(0,),
            maxshape=(None,),
            chunks=(256,),
            dtype=h5py.string_dtype(),
        )
        self._ds["settings_log/name"] = log
        f.swmr_mode = True

        # Events not yet in a full chunk, per field; the tail chunk is rewritten until full.
        self._tail: dict[str, list[np.ndarray]] = {name: [] for name in EVENT_FIELDS}
        self._tail_n = 0
        self._n_events = 0  # events appended
        self._n_chunked = 0  # events in full chunks handed to the compressors
        self._ms_done = 0  # millisecond-index entries settled
        self._ms_pending: list[np.ndarray] = []
        self._last_t = {"events": 0, "frames": 0, "imu": 0, "triggers": 0}
        self._flushed_events = 0
        self._n_frames = 0  # frames handed to the compressors

    # -- appending ---------------------------------------------------------------------------

    def _check_order(self, stream: str, t: np.ndarray) -> None:
        if t.size == 0:
            return
        if int(t[0]) < 0:
            raise SessionFormatError(f"{stream}: t={int(t[0])} is before t = 0 of the session")
        if int(t[0]) < self._last_t[stream]:
            raise SessionFormatError(
                f"{stream}: t={int(t[0])} comes after t={self._last_t[stream]}: "
                "streams must be appended in time order"
            )
        self._last_t[stream] = int(t[-1])

    def append_events(self, events: Events) -> None:
        """Append events that follow (in time) those already written."""
        s = self.sensor
        if (events.width, events.height, events.color_filter) != (
            s.width,
            s.height,
            s.color_filter,
        ):
            raise SessionFormatError(
                f"events from a {events.width} x {events.height} {events.color_filter} sensor "
                f"cannot go into a {s.width} x {s.height} {s.color_filter} session"
            )
        if len(events) == 0:
            return
        self._check_order("events", events.t)
        self._ms_pending.append(_ms_entries(events.t, self._n_events, self._ms_done))
        self._ms_done = int(events.t[-1]) // 1000 + 1
        self._n_events += len(events)
        for name in EVENT_FIELDS:
            self._tail[name].append(getattr(events, name))
        self._tail_n += len(events)
        if self._tail_n >= EVENT_CHUNK:
            full = (self._tail_n // EVENT_CHUNK) * EVENT_CHUNK
            for name in EVENT_FIELDS:
                tail = np.concatenate(self._tail[name])
                for start in range(0, full, EVENT_CHUNK):
                    first = self._n_chunked + start
                    chunk = tail[start : start + EVENT_CHUNK]
                    self._unsent.append(
                        (f"events/{name}", (first,), first + EVENT_CHUNK, chunk, None)
                    )
                self._tail[name] = [tail[full:]]
            self._tail_n -= full
            self._n_chunked += full
            self._send()
        self.flush_if_due()

    def _send(self) -> None:
        """Hand the chunks made to the compressors, in order (see ``_unsent``)."""
        while self._unsent:
            self._submit(*self._unsent[0])
            self._unsent.popleft()

    def _submit(self, name: str, offset: tuple, end: int, a: np.ndarray, rows=None) -> None:
        """Have chunk ``a`` of dataset ``name`` compressed; it is written in its turn (and
        then ``rows``: {dataset of the same group: values} written from row ``offset[0]``)."""
        self._inflight.append((name, offset, end, self._pool.submit(chunk_codec.compress, a), rows))
        self._write_done(wait_above=MAX_INFLIGHT)

    def _write_done(self, wait_above: int) -> None:
        """Write compressed chunks in order: those ready, and more while over ``wait_above``.
        A chunk leaves the queue once written (each write goes to its own place, so one that
        an interrupt cut short is made again whole at close)."""
        try:
            while self._inflight and (
                len(self._inflight) > wait_above or self._inflight[0][3].done()
            ):
                name, offset, end, future, rows = self._inflight[0]
                d = self._ds[name]
                if d.shape[0] < end:
                    d.resize((end, *d.shape[1:]))
                d.id.write_direct_chunk(offset, future.result())
                if rows:
                    self._write_rows(name.split("/")[0], rows, offset[0])
                self._inflight.popleft()
        except OSError as e:
            raise self._write_error(e) from e

    def _write_rows(self, group: str, columns: dict[str, np.ndarray], at: int | None = None):
        """``columns`` written from row ``at`` of their datasets (default: appended)."""
        for name, values in columns.items():
            d = self._ds[f"{group}/{name}"]
            n = d.shape[0] if at is None else at
            if d.shape[0] < n + values.shape[0]:
                d.resize((n + values.shape[0], *d.shape[1:]))
            d[n : n + values.shape[0]] = values

    def _append_rows(self, group: str, columns: dict[str, np.ndarray]) -> None:
        try:
            self._write_rows(group, columns)
        except OSError as e:
            raise self._write_error(e) from e
        self.flush_if_due()

    def append_frames(self, frames: Frames) -> None:
        if len(frames) == 0:
            return
        shape = (self.sensor.height, self.sensor.width)
        if frames.data.shape[1:] != shape:
            raise SessionFormatError(
                f"frames of {frames.data.shape[2]} x {frames.data.shape[1]} pixels cannot go "
                f"into a {shape[1]} x {shape[0]} session"
            )
        self._check_order("frames", frames.t)
        # One chunk a frame, compressed as the events are; a frame's time goes in after its
        # data, so that a killed writer never leaves a time without its frame.
        for i in range(len(frames)):
            rows = {"t": frames.t[i : i + 1], "exposure_us": frames.exposure_us[i : i + 1]}
            n = self._n_frames
            self._n_frames += 1
            self._unsent.append(("frames/data", (n, 0, 0), n + 1, frames.data[i : i + 1], rows))
        self._send()
        self.flush_if_due()

    def append_imu(self, imu: ImuSamples) -> None:
        if len(imu) == 0:
            return
        self._check_order("imu", imu.t)
        self._append_rows(
            "imu",
            {"t": imu.t, "accel": imu.accel, "gyro": imu.gyro, "temperature": imu.temperature},
        )

    def append_setting(self, t: int, name: str, value: int) -> None:
        """Log a setting changed while recording (e.g. "bias.OnBn", its new 16-bit code)."""
        self._append_rows(
            "settings_log",
            {
                "t": np.array([t], np.int64),
                "name": np.array([name], object),
                "value": np.array([value], np.int64),
            },
        )

    def append_triggers(self, triggers: Triggers) -> None:
        if len(triggers) == 0:
            return
        self._check_order("triggers", triggers.t)
        self._append_rows("triggers", {"t": triggers.t, "kind": triggers.kind})

    # -- flushing and closing ----------------------------------------------------------------

    @property
    def events_written(self) -> int:
        """Events appended so far (the file holds them once flushed)."""
        return self._n_events

    @property
    def events_flushed(self) -> int:
        """Events that are in the file for sure: a crash now keeps these."""
        return self._flushed_events

    def flush_if_due(self) -> None:
        """Flush if the flush interval has passed (appending calls it; so should a writer's
        loop while no data comes, so that the last data does not wait)."""
        if self._clock() - self._last_flush >= self._flush_interval:
            self.flush()

    def flush(self) -> None:
        """Write everything appended so far to the file, so that a crash keeps it."""
        self._send()
        self._write_done(wait_above=0)
        try:
            tail = self._tail_n
            if tail:
                index = self._n_chunked // EVENT_CHUNK
                for name, dtype in EVENT_FIELDS.items():
                    padded = np.zeros(EVENT_CHUNK, dtype)
                    padded[:tail] = np.concatenate(self._tail[name])
                    d = self._ds[f"events/{name}"]
                    d.resize((self._n_events,))
                    d.id.write_direct_chunk((index * EVENT_CHUNK,), chunk_codec.compress(padded))
            if self._ms_pending:
                new = np.concatenate(self._ms_pending)
                d = self._ds["events/ms_to_idx"]
                n = d.shape[0]
                d.resize((n + new.size,))
                d[n:] = new
                self._ms_pending = []
            self._file.flush()
        except OSError as e:
            raise self._write_error(e) from e
        self._flushed_events = self._n_events
        self._last_flush = self._clock()

    def free_bytes(self) -> int | None:
        """Free space on the session's disk (None if it cannot be told)."""
        try:
            return shutil.disk_usage(self.path.parent).free
        except OSError:
            return None

    def _write_error(self, e: OSError) -> SessionWriteError:
        if isinstance(e, SessionWriteError):
            return e
        free = self.free_bytes()
        if free is not None and free < (64 << 20):
            reason = "the disk is full"
        else:
            reason = os.strerror(e.errno) if e.errno else str(e).splitlines()[0]
        self._failed = True
        return SessionWriteError(
            f"writing {self.path} failed ({reason}). The session holds the "
            f"{self._flushed_events:,} events written before; the file stays readable"
        )

    def close(self, attrs: dict | None = None) -> None:
        """Flush, finish the millisecond index, and write ``attrs`` and complete=True."""
        if self._closed:
            return
        self._ms_pending.append(np.array([self._n_events], np.int64))  # the last entry
        try:
            self.flush()
        except SessionWriteError:
            self.abort()
            raise
        self._closed = True
        self._pool.shutdown()
        self._ds.clear()
        try:
            self._file.close()
            # New attributes cannot be added in SWMR mode: reopen without it.
            with h5py.File(self.path, "r+") as f:
                for key, value in (attrs or {}).items():
                    f.attrs[key] = to_hdf5(value)
                f.attrs["complete"] = True
        except OSError as e:
            raise self._write_error(e) from e

    def abort(self) -> None:
        """Stop without the final steps (after an error): keep what was flushed."""
        if self._closed:
            return
        self._closed = True
        self._pool.shutdown(cancel_futures=True)
        # After a write error HDF5 fails again whenever a dataset is closed, and h5py reports
        # it from its destructors. Close everything here, with those reports (which say
        # nothing new) silenced: first free the datasets the error's frames still hold.
        seen, error = set(), sys.exc_info()[1]
        while error is not None and id(error) not in seen:
            seen.add(id(error))
            traceback.clear_frames(error.__traceback__)
            error = error.__cause__ or error.__context__
        hooks = sys.unraisablehook, sys.excepthook
        sys.unraisablehook = sys.excepthook = lambda *args: None
        try:
            self._ds.clear()
            for _ in range(3):  # closing can fail half-way the first time
                try:
                    self._file.close()
                    break
                except Exception:
                    continue
            gc.collect()
        finally:
            sys.unraisablehook, sys.excepthook = hooks

    def __enter__(self) -> SessionWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None or exc_type is KeyboardInterrupt:
            self.close()
        else:
            with contextlib.suppress(Exception):
                self.flush()
            self.abort()


def write_group(
    path: str | os.PathLike,
    name: str,
    datasets: dict[str, np.ndarray],
    attrs: dict | None = None,
    *,
    replace: bool = False,
    compression_level: int = 4,
) -> None:
    """Add the group /``name`` to a closed session (the records of evcap.records store
    calibration, poses and ground truth so; docs/session-format.md). Arrays of 3 or more
    dimensions are chunked one item of their first axis at a time, so that readers load single
    frames."""
    path = Path(path)
    try:
        f = h5py.File(path, "r+")
    except OSError as e:
        if "already open for write" in str(e):
            raise SessionFormatError(
                f"{path} is being recorded, or its recorder did not close it: groups are added "
                "to closed sessions only"
            ) from None
        raise SessionFormatError(f"{path} cannot be opened for writing: {e}") from None
    with f:
        if name in f:
            if not replace:
                raise SessionFormatError(f"{path} already has /{name}")
            del f[name]
        group = f.create_group(name)
        for key, value in datasets.items():
            a = np.asarray(value)
            options = {}
            if a.size > 256 and a.dtype.kind in "biuf":
                options = {
                    "compression": "gzip",
                    "compression_opts": compression_level,
                    "shuffle": True,
                }
                options["chunks"] = (1, *a.shape[1:]) if a.ndim >= 3 else True
            group.create_dataset(key, data=a, **options)
        for key, value in (attrs or {}).items():
            group.attrs[key] = to_hdf5(value)


# -- reading ---------------------------------------------------------------------------------

_REQUIRED = {
    "events/x": np.uint16,
    "events/y": np.uint16,
    "events/t": np.int64,
    "events/p": np.uint8,
    "events/ms_to_idx": np.int64,
    "frames/data": np.uint16,
    "frames/t": np.int64,
    "frames/exposure_us": np.int64,
    "imu/t": np.int64,
    "imu/accel": np.float32,
    "imu/gyro": np.float32,
    "imu/temperature": np.float32,
    "triggers/t": np.int64,
    "triggers/kind": np.uint8,
}
_ROOT_ATTRS = (
    "schema_version",
    "sensor",
    "serial",
    "width",
    "height",
    "color_filter",
    "t_offset_us",
    "evcap_version",
    "created",
)


def _limit_read_attempts(fapl) -> None:
    """Let HDF5 try a metadata read twice, not its SWMR default of 100 with backoff (which
    makes a damaged file hang its reader for hours). h5py has no binding for it: call the
    HDF5 library h5py is linked with."""
    try:
        lib = ctypes.CDLL(h5py.h5p.__file__)
        set_attempts = lib.H5Pset_metadata_read_attempts
    except (OSError, AttributeError):
        return
    set_attempts.argtypes = [ctypes.c_int64, ctypes.c_uint]
    set_attempts(fapl.id, 2)


def _open_swmr(path: Path) -> h5py.File:
    """Open a file that a writer has open, or had when it was killed (SWMR read mode)."""
    fapl = h5py.h5p.create(h5py.h5p.FILE_ACCESS)
    fapl.set_cache(0, 521, _READ_CACHE, 0.75)
    _limit_read_attempts(fapl)
    fid = h5py.h5f.open(os.fsencode(path), h5py.h5f.ACC_RDONLY | h5py.h5f.ACC_SWMR_READ, fapl=fapl)
    return h5py.File(fid)


def _cut_too_short(f: h5py.File) -> bool:
    """A truncated file that is no recording cut short: complete (so nothing may be missing),
    or cut before the end of its own root attributes."""
    try:
        return bool(f.attrs.get("complete", False)) or "schema_version" not in f.attrs
    except (RuntimeError, OSError, KeyError):  # HDF5: the attributes lie past the cut
        return True


def _open_h5(path: Path) -> h5py.File:
    if not path.exists():
        raise InputNotFoundError(f"{path}: no such file")
    if path.is_dir():
        raise SessionFormatError(f"{path} is a folder, not a session file")
    if path.stat().st_size == 0:
        raise SessionFormatError(f"{path} is empty (0 bytes): not a session file")
    if not h5py.is_hdf5(path):
        raise SessionFormatError(f"{path} is not a session file (not HDF5)")
    try:
        return h5py.File(path, "r", rdcc_nbytes=_READ_CACHE)
    except OSError as e:
        error = e
    if "already open for write" in str(error) or "truncated" in str(error):
        # Being recorded, or its recorder was killed or ran out of disk (then HDF5 may have
        # allocated more than it could write): read what was flushed. A complete session that
        # is shorter than HDF5 wrote is refused by Session.
        try:
            f = _open_swmr(path)
        except OSError:
            pass
        else:
            if "truncated" in str(error) and _cut_too_short(f):
                f.close()
            else:
                return f
    if "truncated" in str(error):
        sizes = re.search(r"eof = (\d+).*stored_eof = (\d+)", str(error))
        if sizes is None:
            raise SessionFormatError(f"{path} is truncated: {str(error).splitlines()[0]}")
        have, wrote = (int(v) for v in sizes.groups())
        raise SessionFormatError(
            f"{path} is truncated: it has {have:,} of the {wrote:,} bytes it was written with "
            "(copied or downloaded only in part?); copy it again"
        )
    raise SessionFormatError(
        f"{path} cannot be read as HDF5 (corrupt or truncated?): {str(error).splitlines()[0]}"
    )


class Session:
    """An open session file (read-only). Open with ``Session.open(path)``.

    Opening checks the schema version, the datasets and their dtypes, and (unless
    ``validate=False``) scans the events: time order, coordinates inside the sensor, polarity,
    and the millisecond index. A session whose writer stopped without closing it (a crash or a
    kill) opens with what was flushed; ``complete`` is False for it.
    """

    def __init__(self, path: Path, f: h5py.File) -> None:
        self.path = path
        self._f = f
        self.attrs: dict = read_attributes(f)
        try:
            self.sensor = SensorInfo(
                sensor=str(self.attrs["sensor"]),
                width=int(self.attrs["width"]),
                height=int(self.attrs["height"]),
                color_filter=str(self.attrs["color_filter"]),
                serial=str(self.attrs["serial"]),
                t_offset_us=int(self.attrs["t_offset_us"]),
            )
        except (ValueError, TypeError) as e:
            raise SessionFormatError(f"{path}: bad sensor attributes: {e}") from None
        self.complete = bool(self.attrs.get("complete", False))
        self.n_events = self._common_length("events", ("x", "y", "t", "p"))
        self.n_frames = self._common_length("frames", ("data", "t", "exposure_us"))
        self.n_imu = self._common_length("imu", ("t", "accel", "gyro", "temperature"))
        self.n_triggers = self._common_length("triggers", ("t", "kind"))
        self._ms_to_idx: np.ndarray | None = None

    @classmethod
    def open(
        cls,
        path: str | os.PathLike,
        *,
        validate: bool = True,
        progress: Callable[[int, int], None] | None = None,
    ) -> Session:
        """Open and check a session; ``progress(done, total)`` follows the event scan."""
        path = Path(path)
        f = _open_h5(path)
        try:
            _check_structure(path, f)
            session = cls(path, f)
            if validate:
                session._scan(progress)
        except SessionFormatError:
            f.close()
            raise
        except (OSError, KeyError, ValueError) as e:
            f.close()
            raise SessionFormatError(f"{path} is corrupt or truncated: {e}") from None
        return session

    def _common_length(self, group: str, names: tuple[str, ...]) -> int:
        lengths = {name: self._f[group][name].shape[0] for name in names}
        n = min(lengths.values())
        if len(set(lengths.values())) > 1 and self.complete:
            raise SessionFormatError(
                f"{self.path}: the datasets of /{group} have different lengths {lengths}"
            )
        return n  # a crashed writer may leave one field ahead of the others: keep the common part

    def _scan(self, progress: Callable[[int, int], None] | None) -> None:
        """Check the events block by block, and the other streams' times."""
        ev = self._f["events"]
        w, h = self.sensor.width, self.sensor.height
        index = self.ms_to_idx
        last_t = 0
        for start in range(0, self.n_events, _READ_BLOCK):
            stop = min(start + _READ_BLOCK, self.n_events)
            t = ev["t"][start:stop]
            bad = first_unsorted(np.concatenate([[last_t], t]))
            if bad >= 0 or (t.size and t[0] < 0):
                at = start + max(bad - 1, 0)
                if not self.complete:
                    # The writer was stopped mid-flush: keep the events before the damage.
                    self.n_events = at
                    self._ms_to_idx = None
                    break
                raise SessionFormatError(
                    f"{self.path}: /events/t is not in time order at event {at} "
                    f"(t={int(t[max(bad - 1, 0)])} after t={last_t})"
                )
            for name, limit in (("x", w), ("y", h), ("p", 2)):
                v = ev[name][start:stop]
                if v.size and int(v.max()) >= limit:
                    i = start + int(np.argmax(v >= limit))
                    raise SessionFormatError(
                        f"{self.path}: /events/{name}={int(v[i - start])} at event {i} is outside "
                        f"the sensor (0..{limit - 1})"
                    )
            ms_from = int(last_t) // 1000 + 1 if start else 0
            expected = _ms_entries(t, start, ms_from)
            got = index[ms_from : ms_from + expected.size]
            if not np.array_equal(np.minimum(got, self.n_events), expected[: got.size]):
                raise SessionFormatError(
                    f"{self.path}: /events/ms_to_idx does not match /events/t "
                    f"(milliseconds {ms_from}..{ms_from + expected.size})"
                )
            if t.size:
                last_t = int(t[-1])
            if progress:
                progress(stop, self.n_events)
        if self.complete:
            size = last_t // 1000 + 2 if self.n_events else 1
            if index.size != size or int(index[-1]) != self.n_events:
                raise SessionFormatError(
                    f"{self.path}: /events/ms_to_idx has {index.size} entries ending at "
                    f"{int(index[-1]) if index.size else None}; expected {size} ending at "
                    f"{self.n_events}"
                )
        for group, n in (
            ("frames", self.n_frames),
            ("imu", self.n_imu),
            ("triggers", self.n_triggers),
        ):
            t = self._f[group]["t"][:n]
            bad = first_unsorted(t)
            if bad >= 0:
                raise SessionFormatError(f"{self.path}: /{group}/t is not in time order at {bad}")

    # -- reading -------------------------------------------------------------------------------

    @property
    def ms_to_idx(self) -> np.ndarray:
        if self._ms_to_idx is None:
            index = self._f["events/ms_to_idx"][:]
            self._ms_to_idx = np.minimum(index, self.n_events)
            if first_unsorted(self._ms_to_idx) >= 0:
                raise SessionFormatError(f"{self.path}: /events/ms_to_idx is not monotonic")
        return self._ms_to_idx

    @property
    def groups(self) -> list[str]:
        return sorted(self._f.keys())

    def group(self, name: str) -> h5py.Group:
        """A group added by a later step (calibration, poses, gt), read lazily."""
        if name not in self._f:
            raise SessionFormatError(f"{self.path} has no /{name} group")
        return self._f[name]

    def event_index(self, t_us: int) -> int:
        """Index of the first event at or after ``t_us``, reading only a millisecond of events."""
        if t_us <= 0:
            return 0
        index = self.ms_to_idx
        ms = t_us // 1000
        if ms >= index.size:
            # Past the index: past the last event, or (crashed writer) past what was indexed.
            lo, hi = (int(index[-1]) if index.size else 0), self.n_events
        else:
            lo = int(index[ms])
            hi = int(index[ms + 1]) if ms + 1 < index.size else self.n_events
        t = self._f["events/t"][lo:hi]
        return lo + int(np.searchsorted(t, t_us, "left"))

    def events(self, t0: int | None = None, t1: int | None = None) -> Events:
        """The events with t0 <= t < t1 (microseconds; None for no bound)."""
        lo = 0 if t0 is None else self.event_index(t0)
        hi = self.n_events if t1 is None else max(lo, self.event_index(t1))
        return self.events_by_index(lo, hi)

    def events_by_index(self, start: int, stop: int) -> Events:
        ev = self._f["events"]
        start, stop = max(0, start), min(stop, self.n_events)
        stop = max(start, stop)
        s = self.sensor
        return Events(
            ev["x"][start:stop],
            ev["y"][start:stop],
            ev["t"][start:stop],
            ev["p"][start:stop],
            s.width,
            s.height,
            s.color_filter,
        )

    def iter_events(self, block: int = _READ_BLOCK) -> Iterator[Events]:
        """All events, ``block`` at a time."""
        for start in range(0, self.n_events, block):
            yield self.events_by_index(start, start + block)

    def _slice(self, group: str, n: int, t0: int | None, t1: int | None) -> slice:
        t = self._f[group]["t"][:n]
        lo = 0 if t0 is None else int(np.searchsorted(t, t0, "left"))
        hi = n if t1 is None else int(np.searchsorted(t, t1, "left"))
        return slice(lo, max(lo, hi))

    def frames(self, t0: int | None = None, t1: int | None = None) -> Frames:
        """The frames whose exposure starts in [t0, t1)."""
        g = self._f["frames"]
        s = self._slice("frames", self.n_frames, t0, t1)
        data = g["data"][s]
        if data.size and int(data.max()) > APS_MAX:
            raise SessionFormatError(f"{self.path}: /frames/data has values above {APS_MAX}")
        return Frames(data, g["t"][s], g["exposure_us"][s])

    def imu(self, t0: int | None = None, t1: int | None = None) -> ImuSamples:
        g = self._f["imu"]
        s = self._slice("imu", self.n_imu, t0, t1)
        return ImuSamples(g["t"][s], g["accel"][s], g["gyro"][s], g["temperature"][s])

    def settings_log(self) -> list[tuple[int, str, int]]:
        """Settings changed while recording: (t, name, value), in time order."""
        if "settings_log" not in self._f:
            return []
        g = self._f["settings_log"]
        n = min(g["t"].shape[0], g["name"].shape[0], g["value"].shape[0])
        names = g["name"].asstr()[:n]
        return list(zip(g["t"][:n].tolist(), list(names), g["value"][:n].tolist(), strict=True))

    def triggers(self, t0: int | None = None, t1: int | None = None) -> Triggers:
        g = self._f["triggers"]
        s = self._slice("triggers", self.n_triggers, t0, t1)
        return Triggers(g["t"][s], g["kind"][s])

    def time_range(self) -> tuple[int, int] | None:
        """(first, last) timestamp over all streams, or None for an empty session."""
        ends = []
        for group, n in (
            ("events", self.n_events),
            ("frames", self.n_frames),
            ("imu", self.n_imu),
            ("triggers", self.n_triggers),
        ):
            if n:
                t = self._f[group]["t"]
                ends += [int(t[0]), int(t[n - 1])]
        return (min(ends), max(ends)) if ends else None

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _check_structure(path: Path, f: h5py.File) -> None:
    version = f.attrs.get("schema_version")
    if version is None:
        raise SessionFormatError(f"{path} is HDF5 but not an evcap session (no schema_version)")
    if int(version) != SCHEMA_VERSION:
        raise SessionFormatError(
            f"{path} has schema version {int(version)}; this evcap ({__version__}) reads "
            f"version {SCHEMA_VERSION}"
        )
    missing = [k for k in _ROOT_ATTRS if k not in f.attrs]
    if missing:
        raise SessionFormatError(f"{path}: missing root attributes: {', '.join(missing)}")
    if str(from_hdf5(f.attrs["color_filter"])) not in COLOR_FILTERS:
        raise SessionFormatError(f"{path}: unknown color_filter {f.attrs['color_filter']!r}")
    for name, dtype in _REQUIRED.items():
        if name not in f:
            raise SessionFormatError(f"{path}: missing dataset /{name}")
        d = f[name]
        if not isinstance(d, h5py.Dataset) or d.dtype != np.dtype(dtype):
            raise SessionFormatError(
                f"{path}: /{name} should be {np.dtype(dtype).name}, is "
                f"{getattr(d, 'dtype', 'a group')}"
            )
    h, w = int(f.attrs["height"]), int(f.attrs["width"])
    if f["frames/data"].shape[1:] != (h, w):
        raise SessionFormatError(
            f"{path}: /frames/data is {f['frames/data'].shape[1:]} per frame, the sensor {(h, w)}"
        )
