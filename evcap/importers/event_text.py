"""Import a sequence of the Event-Camera Dataset's text layout into a session.

The Event-Camera Dataset (ECD: Mueggler et al., IJRR 2017, rpg.ifi.uzh.ch/davis_data.html)
gives each sequence as a folder of space-separated text files, one record a line, times in
seconds as decimals:

- ``events.txt``: ``t x y p`` (p: 1 ON, 0 OFF) -> /events
- ``images.txt``: ``t images/frame_00000000.png``, 8-bit gray PNG files -> /frames
- ``imu.txt``: ``t ax ay az gx gy gz`` (m/s^2, rad/s) -> /imu
- ``groundtruth.txt``: ``t px py pz qx qy qz qw``, the camera's pose in the world (camera-to-
  world, as in the TUM format: the position of the camera and its orientation, metres) -> /poses
- ``calib.txt``: ``fx fy cx cy k1 k2 p1 p2 k3`` (radtan, OpenCV's order) -> /calibration

Only events.txt is needed. What the text does not say is stored so:

- Times are whole microseconds, read from the digits (never through a float; digits past the
  microsecond round to the nearest). t = 0 is the first event; ``t_offset_us`` is its time when
  the times are Unix times, else 0. Samples of the other files before the first event are left
  out (root attribute ``source_left_out`` counts them).
- The sensor's size: ``width``/``height``, else the smallest known sensor that holds every
  event (the ECD's DAVIS240C), named so in the ``sensor`` attribute.
- Frames: ``value << 2`` (``precision_bits`` 8, as AEDAT 4's), at the times images.txt gives;
  the exposure is unknown and stored as 0 (root attribute ``source_frames`` says so).
- IMU samples as the file gives them, in its axes; temperature NaN (not given).
- The poses' camera axes are taken as OpenCV's (x right, y down, z forward), as the ECD's
  calibration (OpenCV's model) implies.

events.txt is read in blocks by a compiled parser (numba, as the camera's stream decoder is):
a line at a time in Python would take minutes for the ECD's larger sequences; compiled, about
8 M lines a second. It is read twice: once to check every line and find the first time and the
largest coordinates (the session's size is needed before anything is written), then to write.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Callable, Iterator
from pathlib import Path

import numba
import numpy as np

from evcap.errors import InputError, InputNotFoundError
from evcap.events import Events, check_color_filter
from evcap.importers.common import SENSOR_SIZES, ImportSummary, check_output, partial_output
from evcap.records import Calibration, Poses
from evcap.rotations import quat_to_rotmat
from evcap.session import SensorInfo, SessionWriter
from evcap.streams import Frames, ImuSamples

EVENTS_FILE = "events.txt"
FORMAT = "ECD text (Event-Camera Dataset)"
BLOCK_BYTES = 16 << 20
MAX_LINE_BYTES = 1 << 20  # longer "lines": not a text file of events
UNIX_SECONDS = 10**9  # times from here on (2001-09-09) are taken as Unix times
_MAX_COORD = 1 << 16  # session coordinates are uint16

# what a line of events.txt failed on, by the parser's code
_EXPECTED = {
    1: "a time in seconds (digits, optionally a '.' and more digits)",
    2: "x, a column (0 or more)",
    3: "y, a row (0 or more)",
    4: "the polarity, 0 or 1",
    5: "the end of the line after 't x y p'",
    6: "times in order (this one is before the line above's)",
    7: "x inside the sensor",
    8: "y inside the sensor",
}


def import_event_text(
    path: str | os.PathLike,
    output: str | os.PathLike,
    *,
    width: int | None = None,
    height: int | None = None,
    color_filter: str | None = None,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> ImportSummary:
    """Convert an ECD text sequence (``path``: its events.txt, or the folder holding it) and
    the files beside it into the session ``output``.

    ``width``/``height`` give the sensor's size (default: the smallest known sensor holding
    every event); ``color_filter`` its filter (default MONO). The session is written under a
    temporary name and renamed when complete. ``progress(done, total)`` counts bytes of
    events.txt: read once to check it and find the size and start, then again to write it.
    """
    events_path = _events_path(Path(path))
    folder, output = events_path.parent, Path(output)
    check_output(output, overwrite)
    if (width is None) != (height is None):
        raise InputError("give both the width and the height of the sensor, or neither")
    if width is not None and not (0 < width <= _MAX_COORD and 0 < height <= _MAX_COORD):
        raise InputError(f"sensor size {width} x {height} is not valid (1 to {_MAX_COORD})")
    color_filter = check_color_filter(color_filter or "MONO")

    size = events_path.stat().st_size
    total = 2 * size

    def scan_progress(done: int) -> None:
        if progress:
            progress(done, total)

    limits = (width, height) if width is not None else (_MAX_COORD, _MAX_COORD)
    t0, x_max, y_max = _scan(events_path, limits, scan_progress)
    if width is not None and height is not None:
        sensor_name = _sensor_named(width, height)
    else:
        width, height, sensor_name = _infer_sensor(events_path, x_max, y_max)
    if color_filter != "MONO" and sensor_name != "unknown":
        sensor_name = f"Color-{sensor_name}"  # as the AEDAT 4 importer names color sensors
    sensor = SensorInfo(sensor_name, width, height, color_filter, "", _offset(t0))

    summary = ImportSummary(source=f"{FORMAT}, {sensor_name}")
    imported = [EVENTS_FILE]
    left_out: dict[str, int] = {}
    attrs = {"source_file": events_path.name, "source_format": FORMAT}
    frames = _read_frames_list(folder / "images.txt", t0)
    if frames is not None:
        attrs["source_frames"] = (
            "images.txt: 8-bit gray PNG stored as value << 2 (precision_bits 8); t is the time "
            "images.txt gives; the exposure is unknown (exposure_us 0)"
        )
    imu = _read_imu(folder / "imu.txt", t0)
    calibration = _read_calibration(folder / "calib.txt", sensor)
    poses = _read_poses(folder / "groundtruth.txt", t0)
    with partial_output(output) as tmp:
        with SessionWriter(tmp, sensor, attrs=attrs, overwrite=True, frame_bits=8) as writer:
            for events, done in _read_events(events_path, (width, height), t0, sensor):
                writer.append_events(events)
                summary.events += len(events)
                if progress:
                    progress(size + done, total)
            if frames is not None:
                entries, left_out["images.txt"] = frames
                for t_us, image in entries:
                    writer.append_frames(_frame(image, t_us, sensor))
                summary.frames = len(entries)
                imported.append("images.txt")
            if imu is not None:
                samples, left_out["imu.txt"] = imu
                writer.append_imu(samples)
                summary.imu = len(samples)
                imported.append("imu.txt")
        if calibration is not None:
            calibration.write(tmp)
            imported.append("calib.txt")
        if poses is not None:
            track, left_out["groundtruth.txt"] = poses
            track.write(tmp)
            imported.append("groundtruth.txt")
        _set_root_attrs(tmp, imported, {k: v for k, v in left_out.items() if v})
    if progress:
        progress(total, total)
    return summary


# -- events.txt --------------------------------------------------------------------------


def _events_path(path: Path) -> Path:
    if path.is_dir():
        path = path / EVENTS_FILE
    if not path.exists():
        raise InputNotFoundError(f"{path}: no such file")
    return path


def _blocks(path: Path) -> Iterator[tuple[bytes, int, int]]:
    """(whole lines, the number of the first, bytes read so far) of a text file, in blocks."""
    line, carry, done = 1, b"", 0
    with open(path, "rb") as f:
        while True:
            data = f.read(BLOCK_BYTES)
            done += len(data)
            buf = carry + data
            end = len(buf) if not data else buf.rfind(b"\n") + 1
            if end == 0 and data:  # a line longer than a block: read on
                if len(buf) > MAX_LINE_BYTES:
                    raise InputError(
                        f"{path}: line {line} is longer than {MAX_LINE_BYTES} bytes: not a "
                        "text file of events"
                    )
                carry = buf
                continue
            block, carry = buf[:end], buf[end:]
            if block:
                yield block, line, done
                line += block.count(b"\n")
            if not data:
                return


def _parse(
    path: Path, block: bytes, line: int, limits: tuple[int, int], t_prev: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The events (absolute t in µs, x, y, p) of a block of lines; InputError naming the
    first bad line."""
    buf = np.frombuffer(block, np.uint8)
    n_max = block.count(b"\n") + 1
    t = np.empty(n_max, np.int64)
    x = np.empty(n_max, np.uint16)
    y = np.empty(n_max, np.uint16)
    p = np.empty(n_max, np.uint8)
    n, bad_line, code, start = _parse_lines(buf, limits[0], limits[1], t_prev, t, x, y, p)
    if code:
        text = block[start:].split(b"\n", 1)[0].decode("utf-8", "replace").rstrip("\r")
        expected = _EXPECTED[code]
        if code in (7, 8):
            expected = f"{expected} ({'x' if code == 7 else 'y'} < {limits[code - 7]})"
        raise InputError(
            f"{path}: line {line + bad_line}: expected {expected} in 't x y p' "
            f"(seconds, column, row, polarity 0/1), got {text[:80]!r}"
        )
    return t[:n], x[:n], y[:n], p[:n]


def _scan(
    path: Path, limits: tuple[int, int], progress: Callable[[int], None]
) -> tuple[int, int, int]:
    """Check every line of events.txt: (the first time in µs, the largest x, y)."""
    first, x_max, y_max, t_prev = None, -1, -1, 0
    for block, line, done in _blocks(path):
        t, x, y, _ = _parse(path, block, line, limits, t_prev)
        if len(t):
            first = int(t[0]) if first is None else first
            t_prev = int(t[-1])
            x_max, y_max = max(x_max, int(x.max())), max(y_max, int(y.max()))
        progress(done)
    if first is None:
        raise InputError(f"{path} holds no events: nothing to import")
    return first, x_max, y_max


def _read_events(
    path: Path, limits: tuple[int, int], t0: int, sensor: SensorInfo
) -> Iterator[tuple[Events, int]]:
    """(events, bytes read so far) of events.txt, a block at a time, with t = 0 at ``t0``."""
    t_prev = 0
    for block, line, done in _blocks(path):
        t, x, y, p = _parse(path, block, line, limits, t_prev)
        if len(t):
            t_prev = int(t[-1])
            t -= t0
            # the parser checked them: inside the sensor, in order, polarity 0 or 1
            events = Events._unchecked(x, y, t, p, sensor.width, sensor.height, sensor.color_filter)
            yield events, done


@numba.njit(cache=True, nogil=True)
def _skip_blanks(buf: np.ndarray, i: int) -> int:
    while i < buf.size and (buf[i] == 32 or buf[i] == 9 or buf[i] == 13):  # space, tab, \r
        i += 1
    return i


@numba.njit(cache=True, nogil=True)
def _field_ends(buf: np.ndarray, i: int) -> bool:
    """Whether a field ends at ``i``: a blank, the end of the line or of the buffer."""
    return i == buf.size or buf[i] == 32 or buf[i] == 9 or buf[i] == 13 or buf[i] == 10


@numba.njit(cache=True, nogil=True)
def _digits(buf: np.ndarray, i: int, most: int) -> tuple[int, int, int]:
    """(value, next position, digits read) of the digits at ``i``; digits beyond ``most``
    are counted but not added (so nothing overflows)."""
    value, count = 0, 0
    while i < buf.size and 48 <= buf[i] <= 57:
        if count < most:
            value = value * 10 + (buf[i] - 48)
        count += 1
        i += 1
    return value, i, count


@numba.njit(cache=True, nogil=True)
def _parse_lines(buf, width, height, t_prev, t, x, y, p):
    """Parse the lines ``t x y p`` of ``buf`` into t (µs), x, y, p. Returns (events, line of
    the first bad one (0-based), what it failed on (0: none; keys of _EXPECTED), where that
    line starts). Blank lines are skipped."""
    n, line, i, size = 0, 0, 0, buf.size
    while i < size:
        start = i
        i = _skip_blanks(buf, i)
        if i == size:
            break
        if buf[i] == 10:  # a blank line
            i += 1
            line += 1
            continue
        seconds, i, count = _digits(buf, i, 13)
        if count == 0 or count > 12:
            return n, line, 1, start
        micros = 0
        if i < size and buf[i] == 46:  # '.'
            fraction, i, count = _digits(buf, i + 1, 7)
            for _ in range(count, 7):
                fraction *= 10
            micros = (fraction + 5) // 10  # to the nearest microsecond
        if not _field_ends(buf, i):
            return n, line, 1, start
        time = seconds * 1_000_000 + micros
        if time < t_prev:
            return n, line, 6, start
        column, i, count = _digits(buf, _skip_blanks(buf, i), 6)
        if count == 0 or count > 5 or not _field_ends(buf, i):
            return n, line, 2, start
        row, i, count = _digits(buf, _skip_blanks(buf, i), 6)
        if count == 0 or count > 5 or not _field_ends(buf, i):
            return n, line, 3, start
        polarity, i, count = _digits(buf, _skip_blanks(buf, i), 2)
        if count != 1 or polarity > 1 or not _field_ends(buf, i):
            return n, line, 4, start
        i = _skip_blanks(buf, i)
        if i < size and buf[i] != 10:
            return n, line, 5, start
        if column >= width:
            return n, line, 7, start
        if row >= height:
            return n, line, 8, start
        t[n], x[n], y[n], p[n] = time, column, row, polarity
        t_prev = time
        n += 1
        i += 1
        line += 1
    return n, line, 0, 0


def _offset(t0: int) -> int:
    """t_offset_us: the first event's time when the times are Unix times, else 0."""
    return t0 if t0 >= UNIX_SECONDS * 1_000_000 else 0


def _sensor_named(width: int, height: int) -> str:
    for name, size in SENSOR_SIZES.items():
        if size == (width, height):
            return name
    return "unknown"


def _infer_sensor(path: Path, x_max: int, y_max: int) -> tuple[int, int, str]:
    """The smallest known sensor that holds every event: (width, height, sensor attribute)."""
    for name, (w, h) in sorted(SENSOR_SIZES.items(), key=lambda item: item[1][0] * item[1][1]):
        if x_max < w and y_max < h:
            return w, h, f"{name} (inferred from the coordinates)"
    known = ", ".join(f"{n} {w} x {h}" for n, (w, h) in SENSOR_SIZES.items())
    raise InputError(
        f"{path}: events reach x = {x_max}, y = {y_max}, outside every known sensor ({known}); "
        "give the sensor's width and height"
    )


# -- the smaller files -------------------------------------------------------------------

_TIME = re.compile(r"(\d{1,12})(?:\.(\d*))?")


def _micros(text: str) -> int | None:
    """Decimal seconds as whole microseconds (nearest), from the digits; None if not a time."""
    m = _TIME.fullmatch(text)
    if m is None:
        return None
    fraction = (m.group(2) or "")[:7].ljust(7, "0")
    return int(m.group(1)) * 1_000_000 + (int(fraction) + 5) // 10


def _rows(path: Path, layout: str) -> Iterator[tuple[int, int, list[str]]]:
    """(line number, time in µs, the other fields) of each non-blank line of a small text
    file whose lines are ``layout`` (e.g. "t ax ay az gx gy gz")."""
    names = layout.split()
    with open(path, encoding="utf-8", errors="replace") as f:
        for number, text in enumerate(f, 1):
            fields = text.split()
            if not fields:
                continue
            if len(fields) != len(names):
                raise InputError(
                    f"{path}: line {number}: expected {len(names)} fields '{layout}', got "
                    f"{len(fields)}: {text.strip()[:80]!r}"
                )
            t_us = _micros(fields[0])
            if t_us is None:
                raise InputError(
                    f"{path}: line {number}: expected a time in seconds (e.g. 12.345678), got "
                    f"{fields[0][:40]!r}"
                )
            yield number, t_us, fields[1:]


def _numbers(path: Path, number: int, fields: list[str], layout: str) -> list[float]:
    try:
        values = [float(v) for v in fields]
    except ValueError:
        values = [float("nan")]
    if not np.isfinite(values).all():
        raise InputError(
            f"{path}: line {number}: expected numbers '{layout}', got {' '.join(fields)[:80]!r}"
        )
    return values


def _table(path: Path, layout: str, t0: int) -> tuple[np.ndarray, np.ndarray, int] | None:
    """(times in session µs, [N, fields] values, rows left out before t = 0) of a small
    numeric file, or None when there is none; InputError at a bad line or a time out of
    order."""
    if not path.exists():
        return None
    times, values, t_prev = [], [], None
    for number, t_us, fields in _rows(path, layout):
        if t_prev is not None and t_us < t_prev:
            raise InputError(f"{path}: line {number}: the time goes back from the line above")
        t_prev = t_us
        times.append(t_us - t0)
        values.append(_numbers(path, number, fields, layout))
    t = np.asarray(times, np.int64)
    keep = t >= 0
    v = np.asarray(values, np.float64).reshape(len(times), len(layout.split()) - 1)
    return t[keep], v[keep], int((~keep).sum())


def _read_imu(path: Path, t0: int) -> tuple[ImuSamples, int] | None:
    table = _table(path, "t ax ay az gx gy gz", t0)
    if table is None:
        return None
    t, v, left_out = table
    return ImuSamples(t, v[:, :3], v[:, 3:], np.full(len(t), np.nan, np.float32)), left_out


def _read_poses(path: Path, t0: int) -> tuple[Poses, int] | None:
    table = _table(path, "t px py pz qx qy qz qw", t0)
    if table is None:
        return None
    t, v, left_out = table
    quats = v[:, [6, 3, 4, 5]]  # (w, x, y, z)
    norms = np.linalg.norm(quats, axis=1)
    if np.any(norms < 1e-6):
        raise InputError(f"{path}: a pose's quaternion is zero (qx qy qz qw = 0 0 0 0)")
    T = np.zeros((len(t), 4, 4))
    T[:, :3, :3] = quat_to_rotmat(quats / norms[:, None])
    T[:, :3, 3] = v[:, :3]
    T[:, 3, 3] = 1
    try:
        poses = Poses(t, T, source="groundtruth.txt (ECD)", scale="metres")
    except InputError as e:
        raise InputError(f"{path}: {e}") from None
    return poses, left_out


def _read_calibration(path: Path, sensor: SensorInfo) -> Calibration | None:
    if not path.exists():
        return None
    layout = "fx fy cx cy k1 k2 p1 p2 k3"
    lines = [(n, line.split()) for n, line in enumerate(path.read_text().splitlines(), 1)]
    lines = [(n, fields) for n, fields in lines if fields]
    if len(lines) != 1 or len(lines[0][1]) != 9:
        raise InputError(f"{path}: expected one line of 9 numbers '{layout}'")
    number, fields = lines[0]
    fx, fy, cx, cy, *dist = _numbers(path, number, fields, layout)
    if fx <= 0 or fy <= 0:
        raise InputError(f"{path}: line {number}: the focal lengths fx, fy must be positive")
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    return Calibration(
        sensor.width,
        sensor.height,
        "calib.txt (ECD)",
        K=K,
        distortion_model="radtan",
        dist=np.asarray(dist),
        notes={"intrinsics_source": "calib.txt (ECD)"},
    )


def _read_frames_list(path: Path, t0: int) -> tuple[list[tuple[int, Path]], int] | None:
    """(session time, image file) of each frame of images.txt at or after t = 0, and how many
    came before; None when there is no images.txt."""
    if not path.exists():
        return None
    entries, left_out, t_prev = [], 0, None
    for number, t_us, (name,) in _rows(path, "t image"):
        if t_prev is not None and t_us < t_prev:
            raise InputError(f"{path}: line {number}: the time goes back from the line above")
        t_prev = t_us
        image = path.parent / name
        if not image.exists():
            raise InputError(f"{path}: line {number}: {image} does not exist")
        if t_us < t0:
            left_out += 1
        else:
            entries.append((t_us - t0, image))
    return entries, left_out


def _frame(image: Path, t_us: int, sensor: SensorInfo) -> Frames:
    """One 8-bit gray image as a frame on the sensor's 10-bit scale."""
    import cv2

    pixels = cv2.imread(str(image), cv2.IMREAD_UNCHANGED)
    if pixels is None or pixels.ndim != 2 or pixels.dtype != np.uint8:
        what = "unreadable" if pixels is None else f"{pixels.dtype} {pixels.shape}"
        raise InputError(f"{image}: expected an 8-bit gray image, got {what}")
    if pixels.shape != (sensor.height, sensor.width):
        raise InputError(
            f"{image} is {pixels.shape[1]} x {pixels.shape[0]} pixels, the sensor "
            f"{sensor.width} x {sensor.height}; give the sensor's width and height"
        )
    return Frames(pixels[None].astype(np.uint16) << 2, [t_us], [0])


def _set_root_attrs(path: Path, imported: list[str], left_out: dict[str, int]) -> None:
    import h5py

    with h5py.File(path, "r+") as f:
        f.attrs["source_files"] = json.dumps(imported)
        if left_out:
            f.attrs["source_left_out"] = json.dumps(left_out)
