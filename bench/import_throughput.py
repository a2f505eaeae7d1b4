"""`evcap import` throughput for each container evcap reads: AEDAT 2.0 (jAER, a DAVIS346),
AEDAT 3.1 (cAER, packets of 8,192 polarity events), a ROS 1 bag of dvs_msgs/EventArray (one
message per 33 ms, rpg_dvs_ros's 30 a second), a ROS 2 MCAP bag of event_camera_msgs/
EventPacket in evt3 (one packet per millisecond of events) and the Event-Camera Dataset's
events.txt (t x y p, seconds with 9 decimals). AEDAT 4 is left out here (measured on a real
recording elsewhere).

Every file holds the same events: the DAVIS346's dense stream of the other benchmarks (12 M
events/s, 12 events each microsecond in rows of 4), written by this script's own small writers.
Each container is imported once from a small file first (numba's compilations, rosbags' type
parsing), then timed: ``import_recording(src, dst, overwrite=True)``, wall time, the fastest of
``--rounds``; MB/s counts the source's bytes (a ROS 2 bag: its folder's files).

    .venv/bin/python bench/import_throughput.py [--events N] [--rounds N] [--containers ...]
"""

from __future__ import annotations

import argparse
import struct
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from _common import markdown_table, report
from _streams import H, W, dense_events
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from evcap.importers.detect import import_recording

Stream = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # x, y, t (us), p; int64

UNIX_US = 1_700_000_000 * 10**6  # the ROS bags' clock (absolute times)
SENSOR_START_US = 1_000  # the AEDAT files' and the evt3 sensor's clock at the first event


def stream(n: int) -> Stream:
    """``n`` events of the dense stream, in time order, then row, polarity and column (as a
    readout sends a row's pixels: evt3's vectors group them)."""
    ev = dense_events(n * 1.01 / 12e6 + 1e-5)
    x, y, t, p = (np.asarray(a, np.int64) for a in (ev.x, ev.y, ev.t, ev.p))
    order = np.lexsort((p, x, y, t))  # a pixel fires once a microsecond at most
    x, y, t, p = x[order], y[order], t[order], p[order]
    once = np.ones(t.size, bool)
    once[1:] = (t[1:] != t[:-1]) | (y[1:] != y[:-1]) | (x[1:] != x[:-1])
    x, y, t, p = x[once][:n], y[once][:n], t[once][:n], p[once][:n]
    order = np.lexsort((x, p, y, t))
    return x[order], y[order], t[order] + SENSOR_START_US, p[order]


# -- AEDAT 2.0 (jAER): header lines, then big-endian (int32 address, int32 timestamp) --------


def write_aedat2(path: Path, s: Stream) -> Path:
    x, y, t, p = s
    head = (
        b"#!AER-DAT2.0\r\n"
        b"# This is a raw AE data file - do not edit\r\n"
        b"# Data format is int32 address, int32 timestamp (8 bytes total)\r\n"
        b"# AEChip: eu.seebetter.ini.chips.davis.Davis346B\r\n"
        b"# DataStartTime: System.currentTimeMillis() 1700000000000\r\n"
        b"#End Of ASCII Header\r\n"
    )
    records = np.empty((t.size, 2), ">u4")  # jAER: x and y mirrored, polarity bit 11
    records[:, 0] = ((H - 1 - y) << 22) | ((W - 1 - x) << 12) | (p << 11)
    records[:, 1] = t & 0xFFFFFFFF
    path.write_bytes(head + records.tobytes())
    return path


# -- AEDAT 3.1 (cAER): header lines, then packets (28-byte header, 8-byte polarity events) ----


def write_aedat3(path: Path, s: Stream, per_packet: int = 8192) -> Path:
    x, y, t, p = s
    records = np.empty((t.size, 2), "<u4")
    records[:, 0] = (x << 17) | (y << 2) | (p << 1) | 1  # valid
    records[:, 1] = t & 0x7FFFFFFF
    overflow = t >> 31
    with path.open("wb") as f:
        f.write(
            b"#!AER-DAT3.1\r\n#Format: RAW\r\n#Source 1: DAVIS346B\r\n"
            b"#Start-Time: 2023-11-14 22:13:20 (TZ+0000)\r\n#!END-HEADER\r\n"
        )
        for i in range(0, t.size, per_packet):
            chunk = records[i : i + per_packet]
            n = len(chunk)
            f.write(struct.pack("<hhiiiiii", 1, 1, 8, 4, int(overflow[i]), n, n, n))
            f.write(chunk.tobytes())
    return path


# -- ROS bags ---------------------------------------------------------------------------------

# rpg_dvs_ros's dvs_msgs and ros-event-camera's event_camera_msgs
_MSGS = {
    "dvs_msgs/msg/Event": "uint16 x\nuint16 y\ntime ts\nbool polarity\n",
    "dvs_msgs/msg/EventArray": (
        "std_msgs/Header header\nuint32 height\nuint32 width\ndvs_msgs/Event[] events\n"
    ),
    "event_camera_msgs/msg/EventPacket": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nuint64 seq\nuint64 time_base\n"
        "string encoding\nbool is_bigendian\nuint8[] events\n"
    ),
}


def _typestore(store: Stores):
    types = get_typestore(store)
    for name, text in _MSGS.items():
        types.register(get_types_from_msg(text, name))
    return types


def _splits(key: np.ndarray) -> list[int]:
    """Where ``key`` (sorted) changes, with the ends: the bounds of its runs."""
    return [0, *np.flatnonzero(np.diff(key)) + 1, key.size]


_DVS_EVENT = np.dtype(
    {"names": ["x", "y", "sec", "nsec", "p"], "formats": ["<u2", "<u2", "<u4", "<u4", "u1"]}
)  # ROS 1 packs the fields: 13 bytes


def write_ros1_dvs(path: Path, s: Stream, message_us: int = 33_333) -> Path:
    """A ROS 1 bag, /dvs/events: dvs_msgs/EventArray, serialized here straight from arrays."""
    x, y, t, p = s
    t_ns = (t + UNIX_US) * 1000
    events = np.empty(t.size, _DVS_EVENT)
    events["x"], events["y"], events["p"] = x, y, p
    events["sec"], events["nsec"] = t_ns // 10**9, t_ns % 10**9
    store = _typestore(Stores.ROS1_NOETIC)
    bounds = _splits(t // message_us)
    with Writer1(path) as writer:
        conn = writer.add_connection("/dvs/events", "dvs_msgs/msg/EventArray", typestore=store)
        for seq, (a, b) in enumerate(zip(bounds[:-1], bounds[1:], strict=True)):
            stamp = int(t_ns[a])
            head = struct.pack("<III", seq, stamp // 10**9, stamp % 10**9)
            head += struct.pack("<I", 3) + b"cam" + struct.pack("<III", H, W, b - a)
            writer.write(conn, int(t_ns[b - 1]), head + events[a:b].tobytes())
    return path


def evt3_words(s: Stream) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Prophesee EVT 3.0 words (16 bits, code in the top 4) of the stream; where each group
    of events (one row, time and polarity within 12 columns) begins, and its time (us).
    Each group: TIME_HIGH (8, time bits 12-23) and TIME_LOW (6, bits 0-11) when they change,
    ADDR_Y (0) when the row changes, then one ADDR_X (2: x, polarity bit 11) for a lone
    event, or VECT_BASE_X (3: base column, polarity) and VECT_12 (4: a bit for each of the 12
    columns from the base)."""
    x, y, t, p = s
    block = x // 12
    new = np.ones(t.size, bool)
    new[1:] = (t[1:] != t[:-1]) | (y[1:] != y[:-1]) | (p[1:] != p[:-1]) | (block[1:] != block[:-1])
    starts = np.flatnonzero(new)
    count = np.diff(np.append(starts, t.size))
    mask = np.bitwise_or.reduceat(1 << (x - block * 12), starts)
    gt, gy, gp, gx, gbase = t[starts], y[starts], p[starts], x[starts], block[starts] * 12
    first = np.zeros(starts.size, bool)
    first[0] = True
    high = first.copy()
    high[1:] = (gt[1:] >> 12) != (gt[:-1] >> 12)
    low = first.copy()
    low[1:] = gt[1:] != gt[:-1]
    row = first.copy()
    row[1:] = gy[1:] != gy[:-1]
    vector = count > 1
    n_words = high.astype(np.int64) + low + row + 1 + vector
    at = np.concatenate([[0], np.cumsum(n_words)])
    words = np.empty(int(at[-1]), np.uint16)
    cursor = at[:-1].copy()
    for sel, value in (
        (high, 0x8000 | ((gt >> 12) & 0xFFF)),
        (low, 0x6000 | (gt & 0xFFF)),
        (row, 0x0000 | gy),
        (~vector, 0x2000 | (gp << 11) | gx),
        (vector, 0x3000 | (gp << 11) | gbase),
        (vector, 0x4000 | mask),
    ):
        words[cursor[sel]] = value[sel]
        cursor += sel
    return words, at[:-1], gt


def write_ros2_evt3(path: Path, s: Stream, packet_us: int = 1000) -> Path:
    """A ROS 2 bag (MCAP), /event_camera/events: EventPacket, evt3, one packet per
    ``packet_us`` of sensor time (the sensor's clock starts at its own 0; the stamps are
    absolute)."""
    words, word_at, group_t = evt3_words(s)
    store = _typestore(Stores.ROS2_HUMBLE)
    Packet = store.types["event_camera_msgs/msg/EventPacket"]
    Header = store.types["std_msgs/msg/Header"]
    Time = store.types["builtin_interfaces/msg/Time"]
    cuts = _splits(group_t // packet_us)
    data = words.view(np.uint8)
    with Writer2(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        msgtype = "event_camera_msgs/msg/EventPacket"
        conn = writer.add_connection("/event_camera/events", msgtype, typestore=store)
        for seq, (a, b) in enumerate(zip(cuts[:-1], cuts[1:], strict=True)):
            start = 2 * int(word_at[a])
            end = 2 * int(word_at[b]) if b < len(word_at) else data.size
            stamp = (int(group_t[a]) + UNIX_US) * 1000
            msg = Packet(
                header=Header(
                    stamp=Time(sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id="cam"
                ),
                height=H,
                width=W,
                seq=seq,
                time_base=0,
                encoding="evt3",
                is_bigendian=False,
                events=data[start:end],
            )
            writer.write(conn, stamp, store.serialize_cdr(msg, msgtype))
    return path


# -- the Event-Camera Dataset's events.txt: "t x y p", t in seconds ---------------------------


def write_ecd_text(path: Path, s: Stream, lines_per_write: int = 1 << 20) -> Path:
    x, y, t, p = s
    t = t - SENSOR_START_US  # ECD's times start near 0
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w") as f:
        for i in range(0, t.size, lines_per_write):
            part = slice(i, i + lines_per_write)
            sec, us = np.divmod(t[part], 10**6)
            f.write(
                "".join(
                    f"{a}.{b:06d}000 {c} {d} {e}\n"
                    for a, b, c, d, e in zip(
                        sec.tolist(),
                        us.tolist(),
                        x[part].tolist(),
                        y[part].tolist(),
                        p[part].tolist(),
                        strict=True,
                    )
                )
            )
    return path


Writer = Callable[[Path, Stream], Path]
CONTAINERS: dict[str, tuple[str, Writer]] = {
    "aedat2": ("AEDAT 2.0 (jAER, Davis346B)", lambda d, s: write_aedat2(d / "r.aedat", s)),
    "aedat3": ("AEDAT 3.1 (cAER, DAVIS346B)", lambda d, s: write_aedat3(d / "r.aedat", s)),
    "ros1": ("ROS 1 bag, dvs_msgs/EventArray", lambda d, s: write_ros1_dvs(d / "r.bag", s)),
    "ros2": ("ROS 2 bag (MCAP), EventPacket evt3", lambda d, s: write_ros2_evt3(d / "r", s)),
    "text": ("ECD events.txt", lambda d, s: write_ecd_text(d / "ecd" / "events.txt", s)),
}


def size_of(path: Path) -> int:
    if path.is_dir():
        return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
    return path.stat().st_size


def measure(name: str, big: Stream, small: Stream, rounds: int, tmp: Path) -> dict:
    label, write = CONTAINERS[name]
    (tmp / "warm").mkdir()
    (tmp / "big").mkdir()
    warm_src = write(tmp / "warm", small)
    start = time.perf_counter()
    src = write(tmp / "big", big)
    write_s = time.perf_counter() - start
    dst = tmp / "s.h5"
    import_recording(warm_src, dst, overwrite=True)
    best = float("inf")
    for _ in range(rounds):
        start = time.perf_counter()
        summary = import_recording(src, dst, overwrite=True)
        best = min(best, time.perf_counter() - start)
        assert summary.events == big[0].size, (name, summary)
    size = size_of(src)
    row = {
        "container": name,
        "format": label,
        "file_MB": size / 1e6,
        "events": summary.events,
        "seconds": best,
        "Mev_per_s": summary.events / best / 1e6,
        "MB_per_s": size / best / 1e6,
    }
    print(
        f"{name:<7} {label:<36} {size / 1e6:8.1f} MB  {summary.events:,} events  {best:6.2f} s"
        f"  {row['Mev_per_s']:6.2f} Mev/s  {row['MB_per_s']:6.1f} MB/s  (written in "
        f"{write_s:.1f} s)",
        flush=True,
    )
    return row


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--events", type=int, default=5_000_000, help="events per file")
    parser.add_argument("--warm-events", type=int, default=50_000, help="the warm-up file's")
    parser.add_argument(
        "--rounds", type=int, default=3, help="imports of each file; the fastest counts"
    )
    parser.add_argument(
        "--containers", nargs="+", choices=list(CONTAINERS), default=list(CONTAINERS)
    )
    args = parser.parse_args(argv)
    big, small = stream(args.events), stream(args.warm_events)
    rows = []
    for name in args.containers:
        with tempfile.TemporaryDirectory() as tmp:
            rows.append(measure(name, big, small, args.rounds, Path(tmp)))
    print()
    print(markdown_table(rows, ("format", "file_MB", "events", "seconds", "Mev_per_s", "MB_per_s")))
    figures: dict = {"rounds": args.rounds}
    for row in rows:
        for key in ("file_MB", "events", "seconds", "Mev_per_s", "MB_per_s"):
            figures[f"{row['container']}_{key}"] = row[key]
    report("import_throughput", figures)


if __name__ == "__main__":
    main()
