"""The message types the ROS importer reads, for bags that do not carry their definitions.

ROS 1 bags and ROS 2 bags from Iron on store every type's definition; ROS 2 bags recorded
before (Humble's sqlite3 bags) store only type names. For those, the types are taken from
rosbags' store of the latest ROS 2 types (sensor_msgs, std_msgs, ...) and from the definitions
below of the two event packages, which no ROS distribution ships.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator

from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

DVS_EVENT_ARRAY = "dvs_msgs/msg/EventArray"
EVENT_PACKET = "event_camera_msgs/msg/EventPacket"
IMAGE = "sensor_msgs/msg/Image"
IMU = "sensor_msgs/msg/Imu"
EVENT_TYPES = (DVS_EVENT_ARRAY, EVENT_PACKET)
"""Message types evcap imports events from."""

# rpg_dvs_ros (uzh-rpg), dvs_msgs/msg/*.msg
_DVS_EVENT_MSG = """
uint16 x
uint16 y
time ts
bool polarity
"""
_DVS_EVENT_ARRAY_MSG = """
std_msgs/Header header
uint32 height
uint32 width
dvs_msgs/Event[] events
"""
# ros-event-camera/event_camera_msgs, msg_ros2/EventPacket.msg
_EVENT_PACKET_MSG = """
std_msgs/Header header
uint32 height
uint32 width
uint64 seq
uint64 time_base
string encoding
bool is_bigendian
uint8[] events
"""


def known_types() -> Typestore:
    """The latest ROS 2 types with dvs_msgs and event_camera_msgs added."""
    store = get_typestore(Stores.LATEST)
    types = {}
    types.update(get_types_from_msg(_DVS_EVENT_MSG, "dvs_msgs/msg/Event"))
    types.update(get_types_from_msg(_DVS_EVENT_ARRAY_MSG, DVS_EVENT_ARRAY))
    types.update(get_types_from_msg(_EVENT_PACKET_MSG, EVENT_PACKET))
    store.register(types)
    return store


def _named(desc: tuple) -> Iterator[str]:
    """The message types a field descriptor refers to."""
    kind, arg = desc
    if kind == Nodetype.NAME:
        yield arg
    elif kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        yield from _named(arg[0])


def add_missing(store: Typestore, known: Typestore, msgtypes: Iterable[str]) -> None:
    """Register in ``store`` those of ``msgtypes`` (and the types they use) that it lacks and
    ``known`` has; the bag's own definitions stay as they are."""
    missing: dict = {}
    todo = [name for name in msgtypes if name not in store.fielddefs]
    while todo:
        name = todo.pop()
        if name in missing or name in store.fielddefs or name not in known.fielddefs:
            continue
        missing[name] = known.fielddefs[name]
        for _, desc in missing[name][1]:
            todo.extend(_named(desc))
    if missing:
        store.register(missing)


def _type_name(desc: tuple) -> str:
    kind, arg = desc
    if kind == Nodetype.BASE:
        return arg[0]
    if kind == Nodetype.NAME:
        return arg
    return f"{_type_name(arg[0])}[]"


def describe(store: Typestore, msgtype: str) -> str:
    """A type's fields as text ("x uint16, y uint16, ..."), or "not defined"."""
    if msgtype not in store.fielddefs:
        return "not defined"
    return ", ".join(f"{name} {_type_name(desc)}" for name, desc in store.fielddefs[msgtype][1])
