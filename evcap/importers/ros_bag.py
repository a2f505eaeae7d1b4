"""Import ROS 1 and ROS 2 bags (recordings of rpg_dvs_ros and the ros-event-camera drivers)
into a session.

Bags are read with ``rosbags`` (pure Python: ROS 1 .bag files; ROS 2 bags, a folder with
metadata.yaml and sqlite3 or MCAP files, or one such file). Message types come from the
bag's own definitions where it carries them, else from evcap.importers.ros_types.

One event topic is imported (``topic``, else the first by name), with the sensor_msgs/Image
and sensor_msgs/Imu topics beside it (same namespace: /dvs/events goes with /dvs/image_raw
and /dvs/imu). Times are the sources' own: the events' timestamps, the images' and IMU
samples' header stamps (the DAVIS drivers stamp a frame at the middle of its exposure; the
exposure time is not in the message, so frames are stored with exposure_us = 0). The
session's t = 0 is the earliest of them.
"""

from __future__ import annotations

import json
import os
import sqlite3
import struct
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag1 import ReaderError as Ros1ReaderError
from rosbags.rosbag2 import ReaderError as Ros2ReaderError
from rosbags.serde import SerdeError
from rosbags.typesys import TypesysError
from rosbags.typesys.store import Typestore

from evcap.errors import ForeignFormatError, InputError, InputNotFoundError
from evcap.events import Events, check_color_filter
from evcap.importers.common import SENSOR_SIZES, ImportSummary, check_output, partial_output
from evcap.importers.ros_events import (
    DecodedEvents,
    PacketDecoder,
    dvs_event_array,
    packet_decoder,
)
from evcap.importers.ros_images import ENCODINGS as IMAGE_ENCODINGS
from evcap.importers.ros_images import bayer_filter, image_values, is_raw, precision_bits
from evcap.importers.ros_types import (
    DVS_EVENT_ARRAY,
    EVENT_PACKET,
    EVENT_TYPES,
    IMAGE,
    IMU,
    add_missing,
    describe,
    known_types,
)
from evcap.session import SensorInfo, SessionWriter
from evcap.streams import Frames, ImuSamples

_EVENT_BATCH = 1 << 18
_IMU_BATCH = 4096
_BAG_ERRORS = (
    AnyReaderError,
    Ros1ReaderError,
    Ros2ReaderError,
    SerdeError,
    TypesysError,
    sqlite3.DatabaseError,
    struct.error,
    EOFError,
)
_COLOR_DAVIS = "RGBG"  # the Color-DAVIS346's filter, which the CED recordings come from


_MAGICS = {
    b"#ROSBAG V2": (".bag", "ROS 1 bag"),
    b"\x89MCAP": (".mcap", "ROS 2 bag (MCAP)"),
    b"SQLite format 3\x00": (".db3", "ROS 2 bag (sqlite3)"),
}


@contextmanager
def _bag_path(src: Path) -> Iterator[tuple[Path, str]]:
    """The path rosbags opens (it tells the storage by the name's suffix: a file named
    otherwise is linked under the right one), and the container's name."""
    if not src.exists():
        raise InputNotFoundError(f"{src}: no such file or folder")
    if src.is_dir():
        if (src / "metadata.yaml").exists():
            storage = "MCAP" if any(src.glob("*.mcap*")) else "sqlite3"
            yield src, f"ROS 2 bag ({storage})"
            return
        files = sorted([*src.glob("*.db3"), *src.glob("*.mcap")])
        if len(files) != 1:
            raise ForeignFormatError(f"{src} is a folder without metadata.yaml: not a ROS 2 bag")
        src = files[0]
    with open(src, "rb") as f:
        head = f.read(16)
    kind = next((kind for magic, kind in _MAGICS.items() if head.startswith(magic)), None)
    if kind is None:
        raise ForeignFormatError(
            f"{src} is not a ROS bag: evcap reads ROS 1 bags (.bag) and ROS 2 bags (a folder "
            "with metadata.yaml, or its .db3 or .mcap file)"
        )
    suffix, container = kind
    if src.suffix == suffix:
        yield src, container
        return
    with tempfile.TemporaryDirectory() as folder:
        link = Path(folder) / f"bag{suffix}"
        link.symlink_to(src.resolve())
        yield link, container


@contextmanager
def _bag_errors(src: Path) -> Iterator[None]:
    """rosbags' and the parsers' errors on a broken bag as one-line ForeignFormatErrors."""
    try:
        yield
    except InputError:
        raise
    except (*_BAG_ERRORS, ValueError) as e:
        raise ForeignFormatError(f"{src}: cannot read the ROS bag: {e}") from None


def _stamp_ns(msg: object) -> int:
    stamp = msg.header.stamp
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


class _EventMessages:
    """The event messages of one topic, decoded in order."""

    def __init__(self, reader: AnyReader, msgtype: str) -> None:
        self._reader = reader
        self.msgtype = msgtype
        self.encoding = ""
        self._decoder: PacketDecoder | None = None

    @property
    def absolute(self) -> bool:
        """Whether the times are absolute (not the sensor's own clock, as evt3's are)."""
        return self._decoder is None or self._decoder.absolute

    def decode(self, raw: bytes | memoryview) -> tuple[int, int, int, DecodedEvents]:
        """(width, height, header stamp in ns, events) of one message."""
        if self.msgtype == DVS_EVENT_ARRAY:
            width, height, events = dvs_event_array(raw, cdr=self._reader.is2)
            return width, height, 0, events
        msg = self._reader.deserialize(raw, EVENT_PACKET)
        if self._decoder is None:
            self._decoder = packet_decoder(msg.encoding)
            self.encoding = msg.encoding
        elif msg.encoding != self.encoding:
            raise InputError(f"the encoding changes from {self.encoding!r} to {msg.encoding!r}")
        events = self._decoder.decode(msg.events, int(msg.time_base), msg.width, msg.height)
        return int(msg.width), int(msg.height), _stamp_ns(msg), events


def _check_dvs_layout(reader: AnyReader, known: Typestore) -> None:
    """dvs_msgs is parsed from its bytes: its definition in the bag must be rpg_dvs_ros's."""
    for name in ("dvs_msgs/msg/Event", DVS_EVENT_ARRAY):
        if reader.typestore.fielddefs.get(name) != known.fielddefs[name]:
            raise ForeignFormatError(
                f"{name} in this bag ({describe(reader.typestore, name)}) is not rpg_dvs_ros's "
                f"({describe(known, name)})"
            )


@dataclass
class _Plan:
    """What is imported, from which topics, and how its times map to the session's."""

    events: str
    event_type: str
    frames: str | None = None
    imu: str | None = None
    width: int = 0
    height: int = 0
    color_filter: str = "MONO"
    frame_encoding: str = ""
    frame_bits: int = 10
    encoding: str = ""
    clock_offset_ns: int = 0  # added to evt3's sensor times to make them absolute
    firsts_ns: list[int] = field(default_factory=list)
    left_out: list[str] = field(default_factory=list)

    def sensor(self) -> SensorInfo:
        model = next((m for m, s in SENSOR_SIZES.items() if s == (self.width, self.height)), "")
        if not model:
            model = "unknown"
        elif self.color_filter != "MONO":
            model = f"Color-{model}"
        t_offset_us = min(self.firsts_ns) // 1000 if self.firsts_ns else 0
        return SensorInfo(model, self.width, self.height, self.color_filter, "", t_offset_us)


def _first_message(reader: AnyReader, topic: str) -> tuple[object, bytes] | None:
    messages = reader.messages(connections=reader.topics[topic].connections)
    try:
        for conn, _, raw in messages:
            return conn, raw
    finally:
        messages.close()
    return None


def _event_topic(
    src: Path, types: dict[str, str | None], counts: dict[str, int], topic: str | None
) -> str:
    known = ", ".join(EVENT_TYPES)
    events = [name for name, msgtype in sorted(types.items()) if msgtype in EVENT_TYPES]
    if topic is None:
        if not any(counts[name] for name in events):
            listing = ", ".join(f"{name} ({msgtype})" for name, msgtype in sorted(types.items()))
            raise InputError(
                f"{src} has no event messages (its topics: {listing or 'none'}); "
                f"evcap imports {known}"
            )
        return next(name for name in events if counts[name])
    if topic not in types:
        raise InputError(
            f"{src} has no topic {topic!r}; its event topics: {', '.join(events) or 'none'}"
        )
    if types[topic] not in EVENT_TYPES:
        raise InputError(f"topic {topic} carries {types[topic]}; evcap imports events of {known}")
    return topic


def _survey_events(reader: AnyReader, plan: _Plan) -> None:
    """Sensor size, encoding and first timestamp from the first event messages."""
    decoder = _EventMessages(reader, plan.event_type)
    messages = reader.messages(connections=reader.topics[plan.events].connections)
    try:
        for index, (_, _, raw) in enumerate(messages):
            try:
                width, height, stamp, events = decoder.decode(raw)
            except InputError as e:
                raise ForeignFormatError(f"{plan.events}, message {index + 1}: {e}") from None
            if index == 0:
                plan.width, plan.height = width, height
            if len(events):
                first = int(events.t_ns[0])
                if not decoder.absolute:
                    # evt3 holds only the sensor's clock: its first event is put at the stamp
                    # of the message that brought it.
                    plan.clock_offset_ns = stamp - first
                plan.firsts_ns.append(first + plan.clock_offset_ns)
                break
    finally:
        messages.close()
    plan.encoding = decoder.encoding
    if reader.topics[plan.events].msgcount == 0:
        raise InputError(f"{plan.events} holds no messages")
    if plan.width <= 0 or plan.height <= 0:
        raise InputError(
            f"the event messages on {plan.events} state no sensor size "
            f"(width {plan.width}, height {plan.height})"
        )


def _choose_frames(
    reader: AnyReader, plan: _Plan, candidates: list[str], color_filter: str | None, hint: bool
) -> None:
    """The image topic (raw values first: mono or Bayer, then demosaiced RGB for a color
    sensor) and the color filter, which a Bayer encoding states."""
    firsts = {}
    for name in candidates:
        first = _first_message(reader, name)
        if first is not None:
            firsts[name] = reader.deserialize(first[1], first[0].msgtype)

    def rank(name: str) -> tuple[bool, bool, str]:
        return (not is_raw(firsts[name].encoding), not name.endswith("image_raw"), name)

    raw = sorted((n for n in firsts if is_raw(firsts[n].encoding)), key=rank)
    bayer = bayer_filter(firsts[raw[0]].encoding) if raw else None
    if bayer is not None:
        if color_filter is not None and color_filter != bayer:
            raise InputError(
                f"the images on {raw[0]} are {firsts[raw[0]].encoding} ({bayer}); "
                f"the color filter {color_filter} contradicts them"
            )
        plan.color_filter = bayer
    elif color_filter is not None:
        plan.color_filter = color_filter
    elif hint:
        plan.color_filter = _COLOR_DAVIS
    usable = []
    for name in sorted(firsts, key=rank):
        encoding = firsts[name].encoding
        size = (firsts[name].width, firsts[name].height)
        if encoding not in IMAGE_ENCODINGS:
            plan.left_out.append(f"{name} ({encoding} images)")
        elif not is_raw(encoding) and plan.color_filter == "MONO":
            plan.left_out.append(f"{name} ({encoding} images of a MONO sensor)")
        elif size != (plan.width, plan.height):
            plan.left_out.append(f"{name} ({size[0]} x {size[1]} images)")
        else:
            usable.append(name)
    if usable:
        plan.frames = usable[0]
        plan.frame_encoding = firsts[plan.frames].encoding
        plan.frame_bits = precision_bits(plan.frame_encoding)
        plan.firsts_ns.append(_stamp_ns(firsts[plan.frames]))
        plan.left_out += [f"{name} (one image topic: {plan.frames})" for name in usable[1:]]


def _plan(
    reader: AnyReader, known: Typestore, src: Path, topic: str | None, color_filter: str | None
) -> _Plan:
    types = {name: info.msgtype for name, info in reader.topics.items()}
    counts = {name: info.msgcount for name, info in reader.topics.items()}
    chosen = _event_topic(src, types, counts, topic)
    namespace = chosen.rpartition("/")[0]
    beside = [name for name in sorted(types) if name.rpartition("/")[0] == namespace]
    add_missing(reader.typestore, known, [types[chosen], IMAGE, IMU])
    plan = _Plan(chosen, types[chosen])
    if plan.event_type == DVS_EVENT_ARRAY:
        _check_dvs_layout(reader, known)
    _survey_events(reader, plan)
    hint = "color" in chosen.lower() or any("color" in name.lower() for name in beside)
    images = [name for name in beside if types[name] == IMAGE]
    _choose_frames(reader, plan, images, color_filter, hint)
    imus = [name for name in beside if types[name] == IMU]
    if imus:
        plan.imu = next((name for name in imus if name.endswith("/imu")), imus[0])
        first = _first_message(reader, plan.imu)
        if first is not None:
            plan.firsts_ns.append(_stamp_ns(reader.deserialize(first[1], IMU)))
    return plan


class _Writer:
    """Batches the streams into the session, with times relative to its t = 0."""

    def __init__(self, writer: SessionWriter, plan: _Plan) -> None:
        self.writer = writer
        self.sensor = writer.sensor
        self.plan = plan
        self.summary = ImportSummary()
        self._events: list[DecodedEvents] = []
        self._n_events = 0
        self._imu: list[tuple[int, tuple, tuple]] = []

    def _t(self, t_ns: np.ndarray | int) -> np.ndarray | int:
        return t_ns // 1000 - self.sensor.t_offset_us

    def events(self, events: DecodedEvents) -> None:
        if len(events):
            self._events.append(events)
            self._n_events += len(events)
        if self._n_events >= _EVENT_BATCH:
            self.flush_events()

    def flush_events(self) -> None:
        if not self._events:
            return
        s, batch = self.sensor, self._events
        t = self._t(np.concatenate([e.t_ns for e in batch]) + self.plan.clock_offset_ns)
        x, y, p = (np.concatenate([getattr(e, k) for e in batch]) for k in "xyp")
        self.writer.append_events(Events(x, y, t, p, s.width, s.height, s.color_filter))
        self.summary.events += self._n_events
        self._events, self._n_events = [], 0

    def frame(self, msg: object) -> None:
        if msg.encoding != self.plan.frame_encoding:
            raise InputError(
                f"the image encoding changes from {self.plan.frame_encoding} to {msg.encoding}"
            )
        values = image_values(msg, self.sensor.color_filter)
        self.writer.append_frames(Frames(values[None], [self._t(_stamp_ns(msg))], [0]))
        self.summary.frames += 1

    def imu(self, msg: object) -> None:
        a, g = msg.linear_acceleration, msg.angular_velocity
        self._imu.append((self._t(_stamp_ns(msg)), (a.x, a.y, a.z), (g.x, g.y, g.z)))
        if len(self._imu) >= _IMU_BATCH:
            self.flush_imu()

    def flush_imu(self) -> None:
        if not self._imu:
            return
        t, accel, gyro = zip(*self._imu, strict=True)
        nan = np.full(len(t), np.nan, np.float32)  # sensor_msgs/Imu has no temperature
        self.writer.append_imu(ImuSamples(np.array(t), np.array(accel), np.array(gyro), nan))
        self.summary.imu += len(t)
        self._imu = []


def _describe(plan: _Plan, container: str, sensor: SensorInfo) -> str:
    encoding = f" {plan.encoding}" if plan.encoding else ""
    parts = [f"{plan.events} ({plan.event_type}{encoding})"]
    if plan.frames:
        parts.append(f"{plan.frames} ({plan.frame_encoding})")
    if plan.imu:
        parts.append(plan.imu)
    text = f"{container}: {', '.join(parts)}; {sensor.sensor} {sensor.width} x {sensor.height}"
    text += f" {sensor.color_filter}"
    if plan.left_out:
        text += f"; left out: {', '.join(plan.left_out)}"
    return text


def import_ros_bag(
    path: str | os.PathLike,
    output: str | os.PathLike,
    *,
    topic: str | None = None,
    color_filter: str | None = None,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> ImportSummary:
    """Convert the ROS bag ``path`` into the session ``output``.

    ``topic`` picks the event topic (default: the first, by name). ``color_filter`` is the
    sensor's when the bag does not state it (Bayer images do; a topic named like CED's
    /dvs/image_color means the Color-DAVIS346's RGBG); default MONO. The session is written
    to a temporary name and renamed when complete. ``progress(done, total)`` counts messages.
    """
    src, dst = Path(path), Path(output)
    check_output(dst, overwrite)
    if color_filter is not None:
        check_color_filter(color_filter)
    with partial_output(dst) as tmp:
        known = known_types()
        with (
            _bag_path(src) as (bag, container),
            _bag_errors(src),
            AnyReader([bag], default_typestore=known) as reader,
        ):
            plan = _plan(reader, known, src, topic, color_filter)
            sensor = plan.sensor()
            attrs = {
                "source_file": src.name,
                "source_format": container,
                "source_encoding": f"{plan.event_type} {plan.encoding}".strip(),
                "source_topics": json.dumps(
                    {"events": plan.events, "frames": plan.frames, "imu": plan.imu}
                ),
            }
            with SessionWriter(
                tmp, sensor, attrs=attrs, overwrite=True, frame_bits=plan.frame_bits
            ) as writer:
                summary = _copy(reader, plan, writer, progress)
            summary.source = _describe(plan, container, sensor)
    return summary


def _copy(
    reader: AnyReader,
    plan: _Plan,
    writer: SessionWriter,
    progress: Callable[[int, int], None] | None,
) -> ImportSummary:
    """Every message of the chosen topics, in the bag's order, into the session."""
    out = _Writer(writer, plan)
    events = _EventMessages(reader, plan.event_type)
    topics = [t for t in (plan.events, plan.frames, plan.imu) if t]
    connections = [c for t in topics for c in reader.topics[t].connections]
    total = sum(c.msgcount for c in connections)
    counts = dict.fromkeys(topics, 0)
    for index, (conn, _, raw) in enumerate(reader.messages(connections=connections)):
        counts[conn.topic] += 1
        try:
            if conn.topic == plan.events:
                out.events(events.decode(raw)[3])
            elif conn.topic == plan.frames:
                out.frame(reader.deserialize(raw, conn.msgtype))
            else:
                out.imu(reader.deserialize(raw, conn.msgtype))
        except InputError as e:
            raise ForeignFormatError(f"{conn.topic}, message {counts[conn.topic]}: {e}") from None
        if progress:
            progress(index + 1, total)
    try:
        out.flush_events()
        out.flush_imu()
    except InputError as e:
        raise ForeignFormatError(f"{plan.events}: {e}") from None
    return out.summary
