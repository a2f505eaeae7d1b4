"""Small ROS bags for the importer's tests, written with rosbags' writers, and encoders of the
event_camera_msgs encodings written from their descriptions (not from evcap's decoders)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

# The messages of rpg_dvs_ros (dvs_msgs) and ros-event-camera (event_camera_msgs).
EVENT_MSG = "uint16 x\nuint16 y\ntime ts\nbool polarity\n"
EVENT_ARRAY_MSG = "Header header\nuint32 height\nuint32 width\nEvent[] events\n"
EVENT_PACKET_MSG = (
    "Header header\nuint32 height\nuint32 width\nuint64 seq\nuint64 time_base\n"
    "string encoding\nbool is_bigendian\nuint8[] events\n"
)
KINDS = ("ros1", "sqlite3", "mcap")


def typestore(kind: str, event_msg: str = EVENT_MSG):
    store = get_typestore(Stores.ROS1_NOETIC if kind == "ros1" else Stores.ROS2_HUMBLE)
    types = {}
    types.update(get_types_from_msg(event_msg, "dvs_msgs/msg/Event"))
    types.update(get_types_from_msg(EVENT_ARRAY_MSG, "dvs_msgs/msg/EventArray"))
    types.update(get_types_from_msg(EVENT_PACKET_MSG, "event_camera_msgs/msg/EventPacket"))
    store.register(types)
    return store


class Bag:
    """Messages to write: ``add(topic, msgtype, stamp_ns, msg)``, then ``write(path)``."""

    def __init__(self, kind: str, event_msg: str = EVENT_MSG) -> None:
        self.kind = kind
        self.store = typestore(kind, event_msg)
        self.messages: list[tuple[int, int, str, str, object]] = []

    def _t(self, name: str):
        return self.store.types[name]

    def header(self, stamp_ns: int, frame_id: str = "cam"):
        time = self._t("builtin_interfaces/msg/Time")(
            sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9
        )
        if self.kind == "ros1":
            return self._t("std_msgs/msg/Header")(seq=0, stamp=time, frame_id=frame_id)
        return self._t("std_msgs/msg/Header")(stamp=time, frame_id=frame_id)

    def add(self, topic: str, msgtype: str, bag_time_ns: int, msg: object) -> None:
        self.messages.append((bag_time_ns, len(self.messages), topic, msgtype, msg))

    def dvs(self, topic, bag_time_ns, x, y, t_ns, p, width=346, height=260, frame_id="cam"):
        Event = self._t("dvs_msgs/msg/Event")
        Time = self._t("builtin_interfaces/msg/Time")
        events = [
            Event(
                x=int(a),
                y=int(b),
                ts=Time(sec=int(t) // 10**9, nanosec=int(t) % 10**9),
                polarity=bool(q),
            )
            for a, b, t, q in zip(x, y, t_ns, p, strict=True)
        ]
        msg = self._t("dvs_msgs/msg/EventArray")(
            header=self.header(int(t_ns[0]) if len(t_ns) else bag_time_ns, frame_id),
            height=height,
            width=width,
            events=events,
        )
        self.add(topic, "dvs_msgs/msg/EventArray", bag_time_ns, msg)

    def packet(self, topic, bag_time_ns, stamp_ns, encoding, data, time_base, width, height, seq):
        msg = self._t("event_camera_msgs/msg/EventPacket")(
            header=self.header(stamp_ns),
            height=height,
            width=width,
            seq=seq,
            time_base=time_base,
            encoding=encoding,
            is_bigendian=False,
            events=np.frombuffer(bytes(data), np.uint8),
        )
        self.add(topic, "event_camera_msgs/msg/EventPacket", bag_time_ns, msg)

    def image(self, topic, stamp_ns, encoding, pixels: np.ndarray):
        h, w = pixels.shape[:2]
        data = np.ascontiguousarray(pixels).view(np.uint8).reshape(-1)
        msg = self._t("sensor_msgs/msg/Image")(
            header=self.header(stamp_ns),
            height=h,
            width=w,
            encoding=encoding,
            is_bigendian=0,
            step=data.size // h,
            data=data,
        )
        self.add(topic, "sensor_msgs/msg/Image", stamp_ns + 1000, msg)

    def imu(self, topic, stamp_ns, accel, gyro):
        Vector3 = self._t("geometry_msgs/msg/Vector3")
        msg = self._t("sensor_msgs/msg/Imu")(
            header=self.header(stamp_ns),
            orientation=self._t("geometry_msgs/msg/Quaternion")(x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=np.zeros(9),
            angular_velocity=Vector3(x=gyro[0], y=gyro[1], z=gyro[2]),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=Vector3(x=accel[0], y=accel[1], z=accel[2]),
            linear_acceleration_covariance=np.zeros(9),
        )
        self.add(topic, "sensor_msgs/msg/Imu", stamp_ns + 500, msg)

    def write(self, path: Path) -> Path:
        """Write the bag; returns what to import (the .bag file or the ROS 2 folder)."""
        if self.kind == "ros1":
            path = path.with_suffix(".bag")
            writer = Writer1(path)
        else:
            plugin = StoragePlugin.MCAP if self.kind == "mcap" else StoragePlugin.SQLITE3
            writer = Writer2(path, version=9, storage_plugin=plugin)
        connections = {}
        with writer:
            for bag_time, _, topic, msgtype, msg in sorted(self.messages, key=lambda m: m[:2]):
                if topic not in connections:
                    connections[topic] = writer.add_connection(topic, msgtype, typestore=self.store)
                if self.kind == "ros1":
                    raw = self.store.serialize_ros1(msg, msgtype)
                else:
                    raw = self.store.serialize_cdr(msg, msgtype)
                writer.write(connections[topic], bag_time, raw)
        return path


# -- encoders ---------------------------------------------------------------------------------


def evt3_words(x, y, t_us, p, width: int) -> list[int]:
    """Prophesee EVT 3.0: 16-bit words, code in the top 4 bits. TIME_HIGH (8) holds bits
    12-23 of the microsecond time, TIME_LOW (6) bits 0-11; ADDR_Y (0) sets the row; ADDR_X
    (2) is one event (x in bits 0-10, polarity bit 11); VECT_BASE_X (3) sets a column and
    polarity for VECT_12 (4) and VECT_8 (5), whose set bits are events at base + bit, each
    moving the base on by 12 or 8. Words without CD events are sprinkled in, and garbage
    before the first time words."""
    words = [0x0000 | 7, 0x2000 | 5]  # before any time: ignored
    high = low = row = None
    n, i = len(t_us), 0
    while i < n:
        t = int(t_us[i])
        if t >> 12 != high:
            words.append(0x8000 | ((t >> 12) & 0xFFF))
            high, low = t >> 12, None
        if t & 0xFFF != low:
            words.append(0x6000 | (t & 0xFFF))
            low = t & 0xFFF
        if y[i] != row:
            words.append(0x0000 | int(y[i]))
            row = y[i]
        j = i + 1
        while (
            j < n and t_us[j] == t and y[j] == y[i] and p[j] == p[i] and x[j - 1] < x[j] < x[i] + 20
        ):
            j += 1
        pol = int(p[i]) << 11
        if j - i == 1:
            words.append(0x2000 | pol | int(x[i]))
        else:
            offsets = [int(x[k] - x[i]) for k in range(i, j)]
            mask = sum(1 << o for o in offsets)
            words.append(0x3000 | pol | int(x[i]))
            if max(offsets) < 8:
                words.append(0x5000 | mask)
            else:
                words.append(0x4000 | (mask & 0xFFF))
                if mask >> 12:
                    words.append(0x5000 | (mask >> 12))
        if i % 7 == 3:
            words += [0xE000 | 0x019, 0xF000 | 0x123, 0xA000 | 1, 0x9000]
        i = j
    return words


def libcaer_cmp_packet(x, y, t_us, p) -> bytes:
    """libcaer_cmp (one packet; times are microseconds since the packet's first event): 16-bit
    words, code in the top 4 bits: TIME_HIGH (0, offset bits 12-23), TIME_LOW (1, bits 0-11),
    ADDR_X (2, column), ADDR_Y (3, one event: row bits 0-10, polarity bit 11), VECT_BASE_Y (4,
    row and polarity for VECT_8), VECT_8 (5: an event at base + bit for each bit set, then
    the base moves on by 8). Times restart at 0 in each packet."""
    t0 = int(t_us[0])
    words = [0x2000 | int(x[0])]
    high = low = 0
    column = int(x[0])
    n, i = len(t_us), 0
    while i < n:
        dt = int(t_us[i]) - t0
        if dt >> 12 != high:
            words.append(0x0000 | (dt >> 12))
            high = dt >> 12
        if dt & 0xFFF != low:
            words.append(0x1000 | (dt & 0xFFF))
            low = dt & 0xFFF
        if x[i] != column:
            words.append(0x2000 | int(x[i]))
            column = int(x[i])
        base = int(y[i]) & ~7
        j = i + 1
        while (
            j < n
            and t_us[j] == t_us[i]
            and x[j] == x[i]
            and p[j] == p[i]
            and y[j - 1] < y[j] < base + 16
        ):
            j += 1
        pol = int(p[i]) << 11
        if j - i == 1:
            words.append(0x3000 | pol | int(y[i]))
        else:
            mask = sum(1 << int(y[k] - base) for k in range(i, j))
            words += [0x4000 | pol | base, 0x5000 | (mask & 0xFF)]
            if mask >> 8:
                words.append(0x5000 | (mask >> 8))
        i = j
    return np.array(words, "<u2").tobytes()


def libcaer_packet(x, y, t_us, p) -> tuple[int, bytes]:
    """libcaer polarity events, 8 bytes each: uint32 data (x bits 17-31, y bits 2-16,
    polarity bit 1, valid bit 0) and int32 timestamp (the low 31 bits of the sensor's
    microseconds). Returns (the high bits of the first event's time, in us; the bytes)."""
    t = np.asarray(t_us, np.int64)
    data = (np.asarray(x, np.uint32) << 17) | (np.asarray(y, np.uint32) << 2)
    data |= (np.asarray(p, np.uint32) << 1) | 1
    records = np.empty(t.size, [("data", "<u4"), ("t", "<i4")])
    records["data"], records["t"] = data, t & ((1 << 31) - 1)
    return int(t[0]) & ~((1 << 31) - 1), records.tobytes()


# -- word-by-word readings of the encodings, as the codecs describe them -----------------------


def _evt3_high(high: int, t: int) -> int:
    """A new TIME_HIGH: a step back of more than 10 is a rollover of the 24-bit time."""
    last = (high >> 12) & 0xFFF
    if t < last and last - t > 10:
        high += 1 << 24
    return (high & ~0xFFFFFF) | (t << 12)


def evt3_reference(packets, width, height):
    """(x, y, t_us, p) of EVT 3.0 packets, one word at a time; nothing before a TIME_HIGH
    and then a TIME_LOW in one packet."""
    valid, high, low, row, base, pol, out = False, 0, 0, 0, 0, 0, []
    for data in packets:
        words = [int(w) for w in np.frombuffer(data, "<u2")]
        i, seen_high = 0, False
        while not valid and i < len(words):
            code, value = words[i] >> 12, words[i] & 0xFFF
            if code == 8:
                high, seen_high = _evt3_high(high, value), True
            elif code == 6:
                low = value
                valid = seen_high
            i += 1
        for word in words[i:]:
            code, value = word >> 12, word & 0xFFF
            if code == 0:
                row = value & 0x7FF
            elif code == 2 and (value & 0x7FF) < width and row < height:
                out.append((value & 0x7FF, row, high | low, value >> 11))
            elif code == 3:
                base, pol = value & 0x7FF, value >> 11
            elif code in (4, 5):
                bits = 12 if code == 4 else 8
                for b in range(bits):
                    if value >> b & 1 and base + b < width and row < height:
                        out.append((base + b, row, high | low, pol))
                base += bits
            elif code == 6:
                low = value
            elif code == 8:
                high = _evt3_high(high, value)
    return np.array(out, np.int64).reshape(-1, 4).T


def libcaer_cmp_reference(packets, width, height):
    """(x, y, t offset in us, p) of libcaer_cmp packets, one word at a time; the time starts
    at 0 in each packet, the column and the vector base run on."""
    column, base, pol, out = 0, 0, 0, []
    for data in packets:
        high = low = 0
        for word in (int(w) for w in np.frombuffer(data, "<u2")):
            code, value = word >> 12, word & 0xFFF
            if code == 0:
                high = value << 12
            elif code == 1:
                low = value
            elif code == 2:
                column = value & 0x7FF
            elif code == 3 and column < width and (value & 0x7FF) < height:
                out.append((column, value & 0x7FF, high | low, value >> 11))
            elif code == 4:
                base, pol = value & 0x7FF, value >> 11
            elif code == 5:
                for b in range(8):
                    if value >> b & 1 and column < width and base + b < height:
                        out.append((column, base + b, high | low, pol))
                base += 8
    return np.array(out, np.int64).reshape(-1, 4).T
