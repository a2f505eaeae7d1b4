"""Import AEDAT 3.1 files (cAER / libcaer) into a session.

An AEDAT 3.1 file is ASCII header lines ('#!AER-DAT3.1', '#Format: RAW', '#Source 1: NAME',
'#Start-Time: ...', '#!END-HEADER'), then packets: a 28-byte little-endian header (int16
eventType and eventSource; int32 eventSize, eventTSOffset, eventTSOverflow, eventCapacity,
eventNumber, eventValid) followed by eventNumber events of eventSize bytes (libcaer's
include/libcaer/events/*.h). An event's time is its 31-bit timestamp plus the packet's
eventTSOverflow << 31; bit 0 of its first word marks it valid. Pixels have their origin at the
top left (AEDAT 3.1; 3.0 had it at the bottom left).
"""

from __future__ import annotations

import datetime
import functools
import os
import re
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from evcap.errors import ForeignFormatError, InputError, InputNotFoundError
from evcap.events import Events, check_color_filter, pixel_channels
from evcap.importers.common import SENSOR_SIZES, ImportSummary, check_output, partial_output
from evcap.session import SensorInfo, SessionWriter
from evcap.streams import LIBCAER_TO_CAMERA, Frames, ImuSamples, TriggerKind, Triggers

MAGIC = b"#!AER-DAT"
STANDARD_GRAVITY = 9.80665  # m/s^2 per g
SPECIAL, POLARITY, FRAME, IMU6, IMU9 = 0, 1, 2, 3, 4

_PACKET = struct.Struct("<hhiiiiii")
_MAX_HEADER = 1 << 20
_BATCH = 1 << 20  # events decoded at once
_FRAME_HEADER = 36  # info, 4 timestamps, lengths and positions
_COLOR_FILTERS = ("MONO", "RGBG", "GRGB", "GBGR", "BGRG")  # libcaer's numbering, 0..4
# libcaer's special event types -> TriggerKind (resets become the clock's seams, below)
_TRIGGERS = {
    2: TriggerKind.EXTERNAL_SIGNAL_RISING_EDGE,
    3: TriggerKind.EXTERNAL_SIGNAL_FALLING_EDGE,
    4: TriggerKind.EXTERNAL_SIGNAL_PULSE,
    12: TriggerKind.EXTERNAL_GENERATOR_RISING_EDGE,
    13: TriggerKind.EXTERNAL_GENERATOR_FALLING_EDGE,
    14: TriggerKind.APS_FRAME_START,
    15: TriggerKind.APS_FRAME_END,
    16: TriggerKind.APS_EXPOSURE_START,
    17: TriggerKind.APS_EXPOSURE_END,
}
_TIMESTAMP_WRAP, _TIMESTAMP_RESET = 0, 1  # stamped INT32_MAX by libcaer: no time of their own
_SPECIAL_FIELDS = (("data", "<u4", 0), ("t", "<i4", 4))
_POLARITY_FIELDS = _SPECIAL_FIELDS
_IMU_FIELDS = (("info", "<u4", 0), ("t", "<i4", 4)) + tuple(
    (name, "<f4", 8 + 4 * i) for i, name in enumerate(("ax", "ay", "az", "gx", "gy", "gz", "temp"))
)
# the sensors a source line names by the start of its name
_FAMILIES = {"DVS128": "DVS128", "DAVIS240": "DAVIS240C", "DAVIS346": "DAVIS346"}


@dataclass
class Packet:
    """One packet's header; ``number`` counts the whole events the file holds."""

    offset: int  # byte of its header
    type: int
    source: int
    size: int  # bytes per event
    ts_offset: int  # byte of the main timestamp in an event
    overflow: int
    number: int

    @property
    def body(self) -> int:
        return self.offset + _PACKET.size


@dataclass
class Aedat3Layout:
    """The header and the packet framing of an AEDAT 3.1 file."""

    sources: dict[int, str]  # source id -> name, from the '#Source' lines
    start_time_us: int | None  # '#Start-Time' as Unix µs
    packets: list[Packet] = field(default_factory=list)
    broken: str | None = None  # where a truncated or corrupt file breaks


def _parse_header(path: Path, head: bytes) -> tuple[int, dict[int, str], int | None]:
    """(byte where the packets begin, sources, start time) from the ASCII header."""
    end = head.find(b"#!END-HEADER")
    if not head.startswith(MAGIC):
        raise ForeignFormatError(f"{path} is not an AEDAT file (no '#!AER-DAT' header)")
    version = head[len(MAGIC) :].split(b"\n", 1)[0].strip().decode("ascii", "replace")
    if version != "3.1":
        raise ForeignFormatError(f"{path} is AEDAT {version}, not AEDAT 3.1")
    if end < 0 or head.find(b"\n", end) < 0:
        raise ForeignFormatError(f"{path} is truncated or corrupt: its header has no end")
    data_start = head.find(b"\n", end) + 1
    sources: dict[int, str] = {}
    start_time = None
    for line in head[:end].decode("latin-1").splitlines():
        if m := re.match(r"#Format: *(.*)", line):
            if m.group(1).strip() != "RAW":
                raise ForeignFormatError(
                    f"{path}: packets in format {m.group(1).strip()!r}; evcap reads RAW"
                )
        elif m := re.match(r"#Source (\d+): *(.*)", line):
            sources[int(m.group(1))] = m.group(2).strip()
        elif m := re.match(r"#Start-Time: *(.*)", line):
            try:
                when = datetime.datetime.strptime(m.group(1).strip(), "%Y-%m-%d %H:%M:%S (TZ%z)")
                start_time = int(when.timestamp()) * 1_000_000
            except ValueError:
                pass
    return data_start, sources, start_time


def read_layout(path: str | os.PathLike) -> Aedat3Layout:
    """Read the header and walk the packets of an AEDAT 3.1 file (no event is decoded);
    ForeignFormatError if it is not one. A file that breaks (truncated, corrupt) keeps the
    packets before the break, and the whole events of a packet it cuts; ``broken`` says where."""
    path = Path(path)
    if not path.exists():
        raise InputNotFoundError(f"{path}: no such file")
    if path.is_dir():
        raise ForeignFormatError(f"{path} is a folder, not an AEDAT 3.1 file")
    size = path.stat().st_size
    with open(path, "rb") as f:
        data_start, sources, start_time = _parse_header(path, f.read(_MAX_HEADER))
        layout = Aedat3Layout(sources, start_time)
        f.seek(data_start)
        pos = data_start
        while pos < size:
            head = f.read(_PACKET.size)
            if len(head) < _PACKET.size:
                layout.broken = f"is truncated: it ends inside the packet header at byte {pos}"
                break
            kind, source, esize, ts_offset, overflow, _, number, _ = _PACKET.unpack(head)
            if kind < 0 or esize < 8 or number < 0 or overflow < 0:
                layout.broken = f"is corrupt: the packet header at byte {pos} is not valid"
                break
            if not 4 <= ts_offset <= esize - 4:
                layout.broken = f"is corrupt: the packet header at byte {pos} is not valid"
                break
            end = pos + _PACKET.size + number * esize
            if end > size:
                whole = (size - pos - _PACKET.size) // esize
                if whole:
                    layout.packets.append(
                        Packet(pos, kind, source, esize, ts_offset, overflow, whole)
                    )
                layout.broken = f"is truncated: it ends inside the packet at byte {pos}"
                break
            if number:
                layout.packets.append(Packet(pos, kind, source, esize, ts_offset, overflow, number))
            pos = end
            f.seek(pos)
    return layout


@functools.cache
def _event_dtype(fields: tuple[tuple[str, str, int], ...], size: int) -> np.dtype:
    return np.dtype(
        {
            "names": [f[0] for f in fields],
            "formats": [f[1] for f in fields],
            "offsets": [f[2] for f in fields],
            "itemsize": size,
        }
    )


def _events(buf: np.ndarray, p: Packet, fields: tuple[tuple[str, str, int], ...]) -> np.ndarray:
    """A packet's events as a structured array of ``fields`` (name, dtype, byte offset)."""
    return np.frombuffer(buf, _event_dtype(fields, p.size), count=p.number, offset=p.body)


def _span(buf: np.ndarray, p: Packet) -> tuple[int, int] | None:
    """Raw (first, last) main time of a packet (timestamp + overflow << 31), or None."""
    if p.type == SPECIAL:
        ev = _events(buf, p, _SPECIAL_FIELDS)
        timed = (ev["data"] >> 1) & 0x7F > _TIMESTAMP_RESET
        if not timed.any():
            return None
        t = ev["t"][timed]
        return (p.overflow << 31) + int(t[0]), (p.overflow << 31) + int(t[-1])
    # frames: their start of exposure, the time they are stored at
    offset = 12 if p.type == FRAME else p.ts_offset
    first = struct.unpack_from("<i", buf, p.body + offset)[0]
    last = struct.unpack_from("<i", buf, p.body + (p.number - 1) * p.size + offset)[0]
    return (p.overflow << 31) + first, (p.overflow << 31) + last


def _time_bases(spans: list, types: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """The clock made continuous across timestamp resets: (base of each packet, the times
    where a reset happened).

    After a reset libcaer's timestamps start again from 0; a stream whose time goes back is
    past one. Each stretch between resets (an epoch) starts where the one before ended, so
    that time never goes back."""
    epoch: dict[int, int] = {}
    last: dict[int, int] = {}
    ends = [0]
    of = []
    for span, kind in zip(spans, types, strict=True):
        e = epoch.get(kind, 0)
        if span is not None:
            if kind in last and span[0] < last[kind]:
                e = epoch[kind] = e + 1
            last[kind] = span[1]
            ends += [0] * (e + 1 - len(ends))
            ends[e] = max(ends[e], span[1])
        of.append(e)
    starts = np.concatenate([[0], np.cumsum(ends, dtype=np.int64)[:-1]])
    return starts[np.array(of, np.intp)], starts[1:]


def _first_source(layout: Aedat3Layout) -> tuple[int | None, str]:
    """(id, name) of the source to import: the first the header names that has packets."""
    ids = {p.source for p in layout.packets}
    named = [i for i in sorted(layout.sources) if i in ids]
    source = named[0] if named else (layout.packets[0].source if layout.packets else None)
    fallback = next(iter(layout.sources.values()), "unknown")
    return source, layout.sources.get(source, fallback)


def _known_size(name: str) -> tuple[int, int] | None:
    """The pixel array of a sensor the source line names (e.g. DAVIS346B, DVS128)."""
    for prefix, model in _FAMILIES.items():
        if name.upper().startswith(prefix):
            return SENSOR_SIZES[model]
    return None


def import_aedat3(
    src: str | os.PathLike,
    dst: str | os.PathLike,
    *,
    color_filter: str | None = None,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> ImportSummary:
    """Convert the AEDAT 3.1 (cAER) file ``src`` into the session ``dst``.

    Imports polarity events, frames (16-bit pixels >> 6 = the 10-bit values; ROI 0 only), IMU
    samples (IMU6 and IMU9; g and deg/s become SI units) and special events as triggers
    (external inputs, generator edges, APS frame and exposure marks), all with exact
    timestamps; invalid events are skipped. A timestamp reset: time goes on from the last
    timestamp before it (a TIMESTAMP_RESET trigger marks the seam). Only the first source of
    the header that has packets is imported. t = 0 is the first timestamp; t_offset_us is
    '#Start-Time'. The sensor is the source line's name and size (else the size the frames
    or events span); ``color_filter`` is the frames' own, else the option, else MONO.

    The session is written to a temporary name and renamed when complete. A file that breaks
    (truncated, corrupt packet header): what is whole is imported, then ForeignFormatError says
    where it breaks (its ``summary`` attribute holds the ImportSummary). ``progress(done,
    total)`` counts bytes.
    """
    src, dst = Path(src), Path(dst)
    check_output(dst, overwrite)
    if color_filter is not None:
        check_color_filter(color_filter)
    layout = read_layout(src)
    size = src.stat().st_size
    source, name = _first_source(layout)
    packets = [p for p in layout.packets if p.source == source]
    summary = ImportSummary(source=f"AEDAT 3.1, {name}")
    buf = np.memmap(src, np.uint8, mode="r")
    spans = [_span(buf, p) for p in packets]
    bases, seams = _time_bases(spans, [p.type for p in packets])
    firsts = [b + s[0] for b, s in zip(bases, spans, strict=True) if s is not None]
    t0 = min(firsts + [int(x) for x in seams]) if firsts else 0
    width, height = _known_size(name) or _size_from_data(src, buf, packets)
    filter_stated = _frame_color_filter(src, buf, packets)
    if filter_stated and color_filter and filter_stated != color_filter:
        raise InputError(
            f"{src}: its frames state color filter {filter_stated}, not {color_filter}"
        )
    cf = filter_stated or color_filter or "MONO"
    sensor = SensorInfo(name, width, height, cf, "", layout.start_time_us or 0)
    attrs = {"source_file": src.name, "source_format": "AEDAT 3.1"}
    with (
        partial_output(dst) as tmp,
        SessionWriter(tmp, sensor, attrs=attrs, overwrite=True) as writer,
    ):
        decoder = _Decoder(src, buf, sensor, writer, summary, t0)
        try:
            decoder.triggers(packets, bases, seams)
            for i, (p, base) in enumerate(zip(packets, bases, strict=True)):
                decoder.add(p, int(base))
                if progress and i % 256 == 0:
                    progress(p.body + p.number * p.size, size)
            decoder.flush()
        except InputError as e:
            if isinstance(e, ForeignFormatError):
                raise
            raise ForeignFormatError(f"{src}: {e}") from None
    if progress:
        progress(size, size)
    if layout.broken:
        e = ForeignFormatError(
            f"{src} {layout.broken}; what is whole before it was imported into {dst}"
        )
        e.summary = summary
        raise e
    return summary


def _size_from_data(src: Path, buf: np.ndarray, packets: list[Packet]) -> tuple[int, int]:
    """The sensor size a source line does not name: what the frames or events span."""
    w = h = 0
    for p in packets:
        if p.type == FRAME:
            for i in range(p.number):
                lx, ly, px, py = struct.unpack_from("<4i", buf, p.body + i * p.size + 20)
                w, h = max(w, px + lx), max(h, py + ly)
        elif p.type == POLARITY:
            data = _events(buf, p, _POLARITY_FIELDS)["data"]
            w = max(w, int(((data >> 17) & 0x7FFF).max()) + 1)
            h = max(h, int(((data >> 2) & 0x7FFF).max()) + 1)
    if not (w and h):
        raise ForeignFormatError(f"{src} has no events or frames to import")
    return w, h


def _frame_color_filter(src: Path, buf: np.ndarray, packets: list[Packet]) -> str | None:
    """The color filter the first valid frame states, or None without frames."""
    for p in packets:
        if p.type != FRAME:
            continue
        for i in range(p.number):
            info = struct.unpack_from("<I", buf, p.body + i * p.size)[0]
            if info & 1:
                code = (info >> 4) & 7
                if code >= len(_COLOR_FILTERS):
                    raise ForeignFormatError(
                        f"{src}: frames with color filter {code} (RGBW); evcap reads "
                        f"{', '.join(_COLOR_FILTERS)}"
                    )
                return _COLOR_FILTERS[code]
    return None


class _Decoder:
    """Decodes packets of one file and appends them to the session (events and IMU samples
    in batches)."""

    def __init__(
        self,
        src: Path,
        buf: np.ndarray,
        sensor: SensorInfo,
        writer: SessionWriter,
        summary: ImportSummary,
        t0: int,
    ) -> None:
        self.src, self.buf, self.sensor = src, buf, sensor
        self.writer, self.summary, self.t0 = writer, summary, t0
        self.pending: dict[int, list] = {POLARITY: [], IMU6: []}
        self.pending_n = {POLARITY: 0, IMU6: 0}

    def add(self, p: Packet, base: int) -> None:
        hi = base + (p.overflow << 31) - self.t0
        if p.type == POLARITY:
            self._queue(POLARITY, _events(self.buf, p, _POLARITY_FIELDS), hi, p)
        elif p.type in (IMU6, IMU9):
            if p.size < 36:
                raise ForeignFormatError(
                    f"{self.src}: the IMU packet at byte {p.offset} is corrupt"
                )
            self._queue(IMU6, _events(self.buf, p, _IMU_FIELDS), hi, p)
        elif p.type == FRAME:
            self._frames(p, hi)

    def flush(self) -> None:
        for kind in self.pending:
            self._decode(kind)

    def _queue(self, kind: int, ev: np.ndarray, hi: int, p: Packet) -> None:
        self.pending[kind].append((ev, hi, p.offset))
        self.pending_n[kind] += ev.size
        if self.pending_n[kind] >= _BATCH:
            self._decode(kind)

    def _decode(self, kind: int) -> None:
        batch = self.pending[kind]
        if not batch:
            return
        self.pending[kind], self.pending_n[kind] = [], 0
        ev = np.concatenate([b[0] for b in batch])
        counts = [b[0].size for b in batch]
        hi = np.repeat(np.array([b[1] for b in batch], np.int64), counts)
        offsets = np.repeat(np.array([b[2] for b in batch], np.int64), counts)
        first = ev["data"] if kind == POLARITY else ev["info"]
        valid = (first & 1) == 1
        ev, hi, offsets = ev[valid], hi[valid], offsets[valid]
        t = hi + ev["t"]
        if kind == POLARITY:
            self._polarity(ev, t, offsets)
        else:
            self._imu(ev, t)

    def _polarity(self, ev: np.ndarray, t: np.ndarray, offsets: np.ndarray) -> None:
        data = ev["data"]
        x, y = (data >> 17) & 0x7FFF, (data >> 2) & 0x7FFF
        s = self.sensor
        bad = (x >= s.width) | (y >= s.height)
        if bad.any():
            i = int(np.argmax(bad))
            raise ForeignFormatError(
                f"{self.src}: an event of the packet at byte {int(offsets[i])} lies at "
                f"({int(x[i])}, {int(y[i])}), outside the {s.width} x {s.height} sensor"
            )
        p = ((data >> 1) & 1).astype(np.uint8)
        x, y = x.astype(np.uint16), y.astype(np.uint16)
        ev = Events(x, y, t, p, s.width, s.height, s.color_filter)
        self.writer.append_events(ev)
        self.summary.events += len(ev)

    def _imu(self, ev: np.ndarray, t: np.ndarray) -> None:
        # cAER stores libcaer's axes
        accel = np.stack([ev["ax"], ev["ay"], ev["az"]], axis=1) * STANDARD_GRAVITY
        gyro = np.deg2rad(np.stack([ev["gx"], ev["gy"], ev["gz"]], axis=1))
        accel, gyro = accel * LIBCAER_TO_CAMERA, gyro * LIBCAER_TO_CAMERA
        self.writer.append_imu(ImuSamples(t, accel, gyro, ev["temp"]))
        self.summary.imu += int(t.size)

    def _frames(self, p: Packet, hi: int) -> None:
        s = self.sensor
        for i in range(p.number):
            at = p.body + i * p.size
            info, _, _, start, end, lx, ly, px, py = struct.unpack_from("<I8i", self.buf, at)
            channels = (info >> 1) & 7
            if not info & 1 or (info >> 7) & 0x7F:  # invalid, or a ROI other than 0
                continue
            n = lx * ly * channels
            if lx < 0 or ly < 0 or _FRAME_HEADER + 2 * n > p.size:
                raise ForeignFormatError(f"{self.src}: the frame at byte {at} is corrupt")
            if px < 0 or py < 0 or px + lx > s.width or py + ly > s.height:
                raise ForeignFormatError(
                    f"{self.src}: the frame at byte {at} lies outside the {s.width} x "
                    f"{s.height} sensor"
                )
            pixels = np.frombuffer(self.buf, "<u2", count=n, offset=at + _FRAME_HEADER)
            image = np.zeros((s.height, s.width), np.uint16)
            image[py : py + ly, px : px + lx] = self._mosaic(pixels, lx, ly, px, py, channels, at)
            self.writer.append_frames(Frames(image[None], [hi + start], [end - start]))
            self.summary.frames += 1

    def _mosaic(self, pixels, lx: int, ly: int, px: int, py: int, channels: int, at: int):
        """The 10-bit raw values of a frame: libcaer normalises pixels to 16 bits; a color
        frame (RGB, RGBA) keeps at each pixel the channel its filter passes."""
        values = (pixels >> 6).reshape(ly, lx, channels)
        if channels == 1:
            return values[..., 0]
        if channels not in (3, 4) or self.sensor.color_filter == "MONO":
            raise ForeignFormatError(
                f"{self.src}: the frame at byte {at} has {channels} channels and no color filter"
            )
        yy, xx = np.mgrid[py : py + ly, px : px + lx]
        channel = pixel_channels(xx, yy, self.sensor.color_filter).astype(np.intp)
        return np.take_along_axis(values[..., :3], channel[..., None], axis=2)[..., 0]

    def triggers(self, packets: list[Packet], bases: np.ndarray, seams: np.ndarray) -> None:
        """Special events and the timestamp resets' seams, all at once."""
        t = [seams - self.t0]
        kind = [np.full(seams.size, TriggerKind.TIMESTAMP_RESET, np.uint8)]
        lookup = np.full(128, 255, np.uint8)
        for code, k in _TRIGGERS.items():
            lookup[code] = k
        for p, base in zip(packets, bases, strict=True):
            if p.type != SPECIAL:
                continue
            ev = _events(self.buf, p, _SPECIAL_FIELDS)
            k = lookup[(ev["data"] >> 1) & 0x7F]
            keep = ((ev["data"] & 1) == 1) & (k != 255)
            t.append(int(base) + (p.overflow << 31) + ev["t"][keep].astype(np.int64) - self.t0)
            kind.append(k[keep])
        t_all, kind_all = np.concatenate(t), np.concatenate(kind)
        if t_all.size:
            order = np.argsort(t_all, kind="stable")
            self.writer.append_triggers(Triggers(t_all[order], kind_all[order]))
            self.summary.triggers += int(t_all.size)
