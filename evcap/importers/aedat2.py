"""Import AEDAT 2.0 files (jAER) into a session.

An AEDAT 2.0 file is ASCII header lines that start with '#' (the chip class on the
'# AEChip:' line), then big-endian records of an int32 address and an int32 timestamp (µs).
What an address means depends on the chip class (jAER's event extractors); old files (DVS128
recordings from before jAER wrote the '# AEChip:' line) name none, so the chip is given
(``--chip``) or inferred from the range of the addresses:

- DVS128: bit 0 polarity (0 = ON), bits 1-7 x, bits 8-14 y; bit 15 an external (sync) input.
- DAVIS240 and DAVIS346 (jAER's DavisChip): bit 31 clear is a DVS event (bits 22-30 y, 12-21
  x, 11 polarity; bit 10 set instead marks an external input), bit 31 set an APS ADC sample
  (bits 10-11 the read: 0 reset, 1 signal; bits 0-9 the value) or, with bits 10-11 both set,
  one of the 7 values of an IMU sample (bits 28-30 which, bits 12-27 the int16 value).

jAER's y axis points up: rows are stored as height - 1 - y. DVS columns are stored mirrored
too (width - 1 - x), APS columns are not.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evcap.errors import ForeignFormatError, InputError, InputNotFoundError
from evcap.events import Events, check_color_filter
from evcap.importers.common import SENSOR_SIZES, ImportSummary, check_output, partial_output
from evcap.session import SensorInfo, SessionWriter
from evcap.streams import APS_MAX, Frames, ImuSamples, TriggerKind, Triggers

MAGIC = b"#!AER-DAT"
STANDARD_GRAVITY = 9.80665  # m/s^2 per g
KNOWN_CHIPS = "DVS128, DAVIS240A/B/C, Davis346 (A, B, C, blue, red, ...)"

_RECORD = np.dtype([("address", ">u4"), ("t", ">u4")])
_BLOCK = 1 << 22  # records per block (32 MB)
_INFER_RECORDS = 1 << 22  # records scanned to infer the chip of a file that names none
_MAX_HEADER_LINE = 1 << 20
_WRAP = 1 << 32

# jAER's IMU scales (IMUSample): the file does not record the full-scale settings, so these
# are jAER's defaults, +-4 g and +-500 deg/s
_ACCEL_LSB_PER_G = 8192.0
_GYRO_LSB_PER_DPS = 65.5

# the external input edges jAER (since 2018) adds to its special address
_EXTERNAL_KINDS = {
    2: TriggerKind.EXTERNAL_SIGNAL_FALLING_EDGE,
    3: TriggerKind.EXTERNAL_SIGNAL_RISING_EDGE,
    4: TriggerKind.EXTERNAL_SIGNAL_PULSE,
}
_EXTERNAL_LOOKUP = np.zeros(1024, np.uint8)
for _code, _kind in _EXTERNAL_KINDS.items():
    _EXTERNAL_LOOKUP[_code] = _kind


@dataclass(frozen=True)
class Chip:
    """A jAER chip class and the address layout evcap decodes for it."""

    name: str  # the class's simple name, as the file states it (e.g. "Davis346B")
    layout: str  # "DVS128" or "DAVIS"
    width: int
    height: int


def chip_for_class(chip_class: str) -> Chip:
    """The chip of a jAER chip class (e.g. eu.seebetter.ini.chips.davis.DAVIS240C)."""
    name = chip_class.strip().rsplit(".", 1)[-1]
    low = name.lower()
    if low == "dvs128":
        return Chip(name, "DVS128", *SENSOR_SIZES["DVS128"])
    if low.startswith("davis240"):
        return Chip(name, "DAVIS", *SENSOR_SIZES["DAVIS240C"])
    if low.startswith("davis346"):
        return Chip(name, "DAVIS", *SENSOR_SIZES["DAVIS346"])
    raise ForeignFormatError(
        f"unknown jAER chip class {chip_class.strip()!r}: evcap reads {KNOWN_CHIPS}"
    )


def infer_chip(address: np.ndarray) -> Chip | None:
    """The chip whose address layout and sensor fit the record addresses ``address``, None if
    none does: DVS128 when no address uses bits 16-30, else DAVIS240 or DAVIS346 by the
    largest x and y of the DVS events and APS samples."""
    a = np.asarray(address).astype(np.uint32)
    if a.size == 0:
        return None
    # bit 31 is a special event in the DVS128 decoder too, so it does not rule DVS128 out
    if not (a & 0x7FFF0000).any():
        return chip_for_class("DVS128")
    aps_or_imu = (a & 0x80000000) != 0
    pixel = np.where(aps_or_imu, (a & 0xC00) != 0xC00, (a & 0x400) == 0)  # not IMU, not external
    if not pixel.any():
        return None
    x_max = int(((a[pixel] >> 12) & 0x3FF).max())
    y_max = int(((a[pixel] >> 22) & 0x1FF).max())
    for name in ("DAVIS240", "DAVIS346"):
        chip = chip_for_class(name)
        if x_max < chip.width and y_max < chip.height:
            return chip
    return None


@dataclass(frozen=True)
class Aedat2Header:
    """What the ASCII header of an AEDAT 2.0 file says."""

    chip_class: str | None  # from the '# AEChip:' line, None if there is none
    data_start: int  # byte where the records begin
    start_time_us: int | None  # Unix µs when jAER started writing data, None if not stated


def read_header(path: str | os.PathLike) -> Aedat2Header:
    """Read the header of an AEDAT 2.0 file; ForeignFormatError if it is not one."""
    path = Path(path)
    if not path.exists():
        raise InputNotFoundError(f"{path}: no such file")
    if path.is_dir():
        raise ForeignFormatError(f"{path} is a folder, not an AEDAT 2.0 file")
    chip_class = None
    start_ms = created_ms = None
    with open(path, "rb") as f:
        first = f.readline(64)
        if not first.startswith(MAGIC):
            raise ForeignFormatError(f"{path} is not an AEDAT file (no '#!AER-DAT' header)")
        version = first[len(MAGIC) :].strip().decode("ascii", "replace")
        if version != "2.0":
            raise ForeignFormatError(f"{path} is AEDAT {version}, not AEDAT 2.0")
        pos = len(first)
        while True:
            line = f.readline(_MAX_HEADER_LINE)
            if not line.startswith(b"#"):
                break
            if not line.endswith(b"\n"):
                if len(line) < _MAX_HEADER_LINE:
                    raise ForeignFormatError(f"{path} is truncated: it ends inside its header")
                raise ForeignFormatError(f"{path}: a header line at byte {pos} never ends")
            pos += len(line)
            text = line[1:].decode("latin-1").strip()
            if text.startswith("AEChip:"):
                chip_class = text[len("AEChip:") :].strip()
            elif m := re.match(r"DataStartTime: System\.currentTimeMillis\(\) (\d+)", text):
                start_ms = int(m.group(1))
            elif m := re.match(r"Creation time: System\.currentTimeMillis\(\) (\d+)", text):
                created_ms = int(m.group(1))
            elif text.lower() == "end of ascii header":
                break
    ms = start_ms if start_ms is not None else created_ms
    return Aedat2Header(chip_class, pos, None if ms is None else ms * 1000)


class _Clock:
    """jAER's 32-bit timestamps made continuous (µs since the first record).

    A step back by more than 2^31 µs is a wrap (2^32 µs); any other step back is a timestamp
    reset, after which time goes on from the last timestamp, so that it never goes back."""

    def __init__(self) -> None:
        self.last_raw: int | None = None
        self.now = 0

    def times(self, raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(continuous times, indices of the records that follow a timestamp reset)."""
        raw = raw.astype(np.int64)
        if raw.size == 0:
            return raw, np.zeros(0, np.intp)
        prev = raw[0] if self.last_raw is None else self.last_raw
        d = np.diff(raw, prepend=prev)
        wrap = d < -(_WRAP >> 1)
        step = np.where(d >= 0, d, np.where(wrap, d + _WRAP, 0))
        t = self.now + np.cumsum(step)
        self.last_raw, self.now = int(raw[-1]), int(t[-1])
        return t, np.flatnonzero((d < 0) & ~wrap)


class _FrameAssembler:
    """APS frames from jAER's ADC samples: a frame is every pixel's reset read and signal read,
    its value reset - signal. A new frame starts at the first sample that repeats a (read,
    pixel) of the current one; frames that miss samples (the recording starts or ends within
    one, samples were dropped) are left out."""

    def __init__(self, width: int, height: int) -> None:
        self.shape = (height, width)
        self.n = width * height
        self._start()

    def _start(self) -> None:
        self.values = np.zeros(2 * self.n, np.int32)  # reset reads, then signal reads
        self.seen = np.zeros(2 * self.n, bool)
        self.first_reset_t: int | None = None
        self.last_reset_t = 0
        self.first_signal_t: int | None = None
        self.reset_after_signal = False  # rolling shutter: reads interleaved

    def add(self, pixel: np.ndarray, read: np.ndarray, value: np.ndarray, t: np.ndarray) -> list:
        """Add samples (in file order); returns what ``finish`` gives for each frame they
        complete."""
        done = []
        start = 0
        while start < pixel.size:
            stop = min(pixel.size, start + 2 * self.n)
            cut = start + self._new_frame_at(pixel[start:stop], read[start:stop])
            self._take(pixel[start:cut], read[start:cut], value[start:cut], t[start:cut])
            start = cut
            if cut < stop:
                done.append(self.finish())
        return done

    def _new_frame_at(self, pixel: np.ndarray, read: np.ndarray) -> int:
        """Index of the first sample that cannot belong to the current frame (or the number of
        samples): a read the frame already has, or the reset read of a pixel whose signal read
        it has, or the first reset read after signal reads of a frame that has no reset read."""
        key = read * self.n + pixel
        keys, first = np.unique(key, return_index=True)
        stop = self.seen[key]
        later = np.ones(key.size, bool)
        later[first] = False
        stop |= later
        signal = keys >= self.n
        first_signal = np.full(self.n, key.size)
        first_signal[keys[signal] - self.n] = first[signal]
        resets = np.flatnonzero(read == 0)
        stop[resets] |= self.seen[self.n + pixel[resets]] | (first_signal[pixel[resets]] < resets)
        # a frame starts with reset reads: signal reads before any are the end of a frame the
        # recording started within
        no_reset_yet = resets.size and self.first_reset_t is None
        if no_reset_yet and (self.first_signal_t is not None or resets[0] > 0):
            stop[resets[0]] = True
        return int(np.argmax(stop)) if stop.any() else key.size

    def _take(self, pixel: np.ndarray, read: np.ndarray, value: np.ndarray, t: np.ndarray) -> None:
        if pixel.size == 0:
            return
        key = read * self.n + pixel
        self.values[key] = value
        self.seen[key] = True
        resets = np.flatnonzero(read == 0)
        signals = np.flatnonzero(read == 1)
        if resets.size:
            if self.first_reset_t is None:
                self.first_reset_t = int(t[resets[0]])
            self.last_reset_t = int(t[resets[-1]])
            if self.first_signal_t is not None or (signals.size and signals[0] < resets[-1]):
                self.reset_after_signal = True
        if signals.size and self.first_signal_t is None:
            self.first_signal_t = int(t[signals[0]])

    def finish(self) -> tuple[np.ndarray, int, int] | None:
        """Close the current frame: (image, t, exposure), or None if it misses samples."""
        frame = self._frame()
        self._start()
        return frame

    def _frame(self) -> tuple[np.ndarray, int, int] | None:
        if not self.seen.all():
            return None
        reset, signal = self.values[: self.n], self.values[self.n :]
        image = np.clip(reset - signal, 0, APS_MAX)
        # a saturated pixel reads white, as the camera's own decoder and libcaer make it
        image[(reset < 384) | (signal == 0)] = APS_MAX
        # jAER's exposure: global shutter from the last reset read, rolling shutter from the
        # first one, to the first signal read; the shutter is told from the order of the reads
        start = self.first_reset_t if self.reset_after_signal else self.last_reset_t
        exposure = max(0, self.first_signal_t - start)
        return image.reshape(self.shape).astype(np.uint16), start, exposure


def import_aedat2(
    src: str | os.PathLike,
    dst: str | os.PathLike,
    *,
    chip: str | None = None,
    color_filter: str | None = None,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> ImportSummary:
    """Convert the AEDAT 2.0 (jAER) file ``src`` into the session ``dst``.

    Imports DVS events (exact timestamps; 2^32 µs wraps unwrapped, a timestamp reset continues
    from the last timestamp and is kept as a trigger), IMU samples (jAER's 7-record encoding,
    scaled with jAER's defaults: 8192 LSB/g, 65.5 LSB/(deg/s), raw / 340 + 35 degC; the file
    does not record the full-scale settings), external input edges, and APS frames assembled
    from the ADC samples (reset - signal; frames missing samples are left out). t = 0 is the
    first record; t_offset_us is jAER's DataStartTime where the header states it, else 0.
    ``color_filter`` is the sensor's (the chip class does not state it; default MONO).

    ``chip`` (a jAER chip class, e.g. DVS128, DAVIS240C, Davis346B) is used instead of the one
    the file names (with a warning where they differ); a file that names none and no ``chip``:
    the chip is inferred from the range of the first records' addresses. The summary's notes
    and the session's ``source_chip_from`` say where the chip came from.

    The session is written to a temporary name and renamed when complete. A file that ends
    inside a record: the whole records are imported, then ForeignFormatError says where it
    breaks (its ``summary`` attribute holds the ImportSummary). ``progress(done, total)``
    counts bytes.
    """
    src, dst = Path(src), Path(dst)
    given_chip = None
    if chip is not None:
        try:
            given_chip = chip_for_class(chip)
        except ForeignFormatError:
            raise InputError(
                f"--chip {chip.strip()!r} is not a jAER chip class evcap knows: it reads "
                f"{KNOWN_CHIPS}"
            ) from None
    check_output(dst, overwrite)
    if color_filter is not None:
        check_color_filter(color_filter)
    header = read_header(src)
    size = src.stat().st_size
    n_records = (size - header.data_start) // _RECORD.itemsize
    whole_end = header.data_start + n_records * _RECORD.itemsize
    records = _records(src, header.data_start, n_records)
    summary = ImportSummary()
    the_chip, chip_from = _choose_chip(src, header, given_chip, records, summary)
    t_offset = header.start_time_us or 0
    sensor = SensorInfo(
        the_chip.name, the_chip.width, the_chip.height, color_filter or "MONO", "", t_offset
    )
    attrs = {
        "source_file": src.name,
        "source_format": "AEDAT 2.0",
        "source_chip_from": chip_from,
    }
    if header.chip_class is not None:
        attrs["source_chip_class"] = header.chip_class
    summary.source = f"AEDAT 2.0, {the_chip.name}"
    with (
        partial_output(dst) as tmp,
        SessionWriter(tmp, sensor, attrs=attrs, overwrite=True) as writer,
    ):
        decoder = _Decoder(src, the_chip, sensor, writer, summary)
        pos = 0
        while pos < n_records:
            block = records[pos : pos + _BLOCK]
            if pos + block.size < n_records:
                block = block[: _whole_imu_samples(block, the_chip)]
            decoder.decode(block, header.data_start + pos * _RECORD.itemsize)
            pos += block.size
            if progress:
                progress(header.data_start + pos * _RECORD.itemsize, size)
        decoder.finish()
    if whole_end < size:
        e = ForeignFormatError(
            f"{src} is truncated: it ends inside the record at byte {whole_end}; the "
            f"{n_records:,} whole records before it were imported into {dst}"
        )
        e.summary = summary
        raise e
    return summary


def _choose_chip(
    src: Path,
    header: Aedat2Header,
    given: Chip | None,
    records: np.ndarray,
    summary: ImportSummary,
) -> tuple[Chip, str]:
    """The chip to decode ``src`` as and where it came from ("--chip", "header" or "address
    range"); adds a note (and a warning where --chip overrides the file) to ``summary``."""
    stated = header.chip_class
    if given is not None:
        if stated is None:
            summary.notes.append(f"chip {given.name} (from --chip; the file states none)")
        elif stated.rsplit(".", 1)[-1].lower() == given.name.lower():
            summary.notes.append(f"chip {given.name} (from --chip, as the file states)")
        else:
            summary.notes.append(f"chip {given.name} (from --chip)")
            summary.warnings.append(
                f"the file states chip {stated}; {given.name} from --chip is used instead"
            )
        return given, "--chip"
    if stated is not None:
        try:
            return chip_for_class(stated), "header"
        except ForeignFormatError as e:
            raise ForeignFormatError(f"{src}: {e}; pass --chip to read it as one of them") from None
    inferred = infer_chip(records[:_INFER_RECORDS]["address"])
    if inferred is None:
        why = "its addresses fit none of the chips" if records.size else "no records"
        raise ForeignFormatError(
            f"{src} has no '# AEChip:' header line and {why}; pass --chip (evcap reads "
            f"{KNOWN_CHIPS})"
        )
    summary.notes.append(
        f"chip {inferred.name} (inferred from the address range; pass --chip to choose)"
    )
    return inferred, "address range"


def _records(path: Path, offset: int, n: int) -> np.ndarray:
    if n == 0:
        return np.zeros(0, _RECORD)
    return np.memmap(path, dtype=_RECORD, mode="r", offset=offset, shape=(n,))


def _whole_imu_samples(block: np.ndarray, chip: Chip) -> int:
    """How many records of ``block`` to decode now: an IMU sample (7 records) that the block
    end cuts waits for the next block."""
    if chip.layout != "DAVIS" or block.size < 7:
        return block.size
    tail = block["address"][-7:].astype(np.uint32)
    starts = np.flatnonzero(((tail & 0x80000C00) == 0x80000C00) & ((tail >> 28) & 7 == 0))
    if starts.size and starts[-1] > 0:
        return block.size - 7 + int(starts[-1])
    return block.size


class _Decoder:
    """Decodes blocks of records of one file and appends them to the session."""

    def __init__(
        self,
        src: Path,
        chip: Chip,
        sensor: SensorInfo,
        writer: SessionWriter,
        summary: ImportSummary,
    ) -> None:
        self.src, self.chip, self.sensor = src, chip, sensor
        self.writer, self.summary = writer, summary
        self.clock = _Clock()
        self.frames = _FrameAssembler(chip.width, chip.height)

    def decode(self, block: np.ndarray, byte0: int) -> None:
        """Decode ``block``, whose first record is at byte ``byte0``."""
        a = block["address"].astype(np.uint32)
        t, resets = self.clock.times(block["t"])
        trig_t = [t[resets]]
        trig_kind = [np.full(resets.size, TriggerKind.TIMESTAMP_RESET, np.uint8)]
        try:
            if self.chip.layout == "DVS128":
                special = (a & 0x80008000) != 0
                self._events(a, t, ~special, byte0)
                trig_t.append(t[special])
                trig_kind.append(
                    np.full(int(special.sum()), TriggerKind.EXTERNAL_SIGNAL_FALLING_EDGE, np.uint8)
                )
            else:
                aps_or_imu = (a & 0x80000000) != 0
                imu = (a & 0x80000C00) == 0x80000C00
                external = ~aps_or_imu & ((a & 0x400) != 0)
                self._events(a, t, ~aps_or_imu & ~external, byte0)
                self._imu(a, t, np.flatnonzero(imu))
                self._aps(a, t, aps_or_imu & ~imu, byte0)
                code = a[external] & 0x3FF
                known = np.isin(code, list(_EXTERNAL_KINDS))
                trig_t.append(t[external][known])
                trig_kind.append(_EXTERNAL_LOOKUP[code[known]])
            self._triggers(np.concatenate(trig_t), np.concatenate(trig_kind))
        except InputError as e:
            if isinstance(e, ForeignFormatError):
                raise
            raise ForeignFormatError(f"{self.src}: {e}") from None

    def finish(self) -> None:
        """The end of the file: the frame being read is complete if no sample is missing."""
        self._append_frames([self.frames.finish()])

    def _append_frames(self, frames: list) -> None:
        for frame in frames:
            if frame is not None:
                image, start, exposure = frame
                self.writer.append_frames(Frames(image[None], [start], [exposure]))
                self.summary.frames += 1

    def _check(self, bad: np.ndarray, what: str, index: np.ndarray, byte0: int) -> None:
        if bad.any():
            i = int(index[np.argmax(bad)])
            raise ForeignFormatError(
                f"{self.src}: the {what} at byte {byte0 + 8 * i} lies outside the "
                f"{self.chip.width} x {self.chip.height} sensor of chip {self.chip.name}; "
                "the chip class does not match the data"
            )

    def _events(self, a: np.ndarray, t: np.ndarray, mask: np.ndarray, byte0: int) -> None:
        index = np.flatnonzero(mask)
        if index.size == 0:
            return
        w, h = self.chip.width, self.chip.height
        a = a[index]
        if self.chip.layout == "DVS128":
            xr, yr, p = (a >> 1) & 0x7F, (a >> 8) & 0x7F, 1 - (a & 1)
        else:
            xr, yr, p = (a >> 12) & 0x3FF, (a >> 22) & 0x1FF, (a >> 11) & 1
        self._check((xr >= w) | (yr >= h), "DVS event", index, byte0)
        x, y = (w - 1 - xr).astype(np.uint16), (h - 1 - yr).astype(np.uint16)
        s = self.sensor
        ev = Events(x, y, t[index], p.astype(np.uint8), s.width, s.height, s.color_filter)
        self.writer.append_events(ev)
        self.summary.events += len(ev)

    def _imu(self, a: np.ndarray, t: np.ndarray, index: np.ndarray) -> None:
        """IMU samples: 7 consecutive records with codes 0..6 (ax, ay, az, temperature, gx,
        gy, gz); a group that is not whole is skipped."""
        if index.size < 7:
            return
        code = (a[index] >> 28) & 7
        value = ((a[index] >> 12) & 0xFFFF).astype(np.uint16).view(np.int16).astype(np.float32)
        k = np.arange(index.size - 6)
        whole = index[k + 6] - index[k] == 6
        for j in range(7):
            whole &= code[k + j] == j
        k = k[whole]
        if k.size == 0:
            return
        v = np.stack([value[k + j] for j in range(7)], axis=1)
        accel = v[:, 0:3] / _ACCEL_LSB_PER_G * STANDARD_GRAVITY
        gyro = np.deg2rad(v[:, 4:7] / _GYRO_LSB_PER_DPS)
        temperature = v[:, 3] / 340.0 + 35.0
        self.writer.append_imu(ImuSamples(t[index[k]], accel, gyro, temperature))
        self.summary.imu += int(k.size)

    def _aps(self, a: np.ndarray, t: np.ndarray, mask: np.ndarray, byte0: int) -> None:
        index = np.flatnonzero(mask)
        if index.size == 0:
            return
        a = a[index]
        read = (a >> 10) & 3
        xr, yr = (a >> 12) & 0x3FF, (a >> 22) & 0x1FF
        outside = (xr >= self.chip.width) | (yr >= self.chip.height)
        self._check(outside, "APS sample", index, byte0)
        keep = read <= 1  # 2 is the deprecated third read
        pixel = (self.chip.height - 1 - yr[keep]) * self.chip.width + xr[keep]
        value = (a[keep] & 0x3FF).astype(np.int32)
        self._append_frames(
            self.frames.add(
                pixel.astype(np.int64), read[keep].astype(np.int64), value, t[index][keep]
            )
        )

    def _triggers(self, t: np.ndarray, kind: np.ndarray) -> None:
        if t.size == 0:
            return
        order = np.argsort(t, kind="stable")
        self.writer.append_triggers(Triggers(t[order], kind[order]))
        self.summary.triggers += int(t.size)
