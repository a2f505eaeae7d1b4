"""`evcap import`: which container a recording is, told by its content, and the import of it."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Literal, assert_never

from evcap.errors import InputError, InputNotFoundError
from evcap.importers.common import ImportSummary

Container = Literal["aedat4", "aedat3", "aedat2", "ros1", "ros2", "text"]
KNOWN = (
    "AEDAT 4 (DV), AEDAT 3.1 (cAER, libcaer), AEDAT 2.0 (jAER), ROS 1 bags, ROS 2 bags "
    "(a folder with metadata.yaml, .db3 or .mcap), event text files (t x y p, the "
    "Event-Camera Dataset's events.txt or its folder)"
)
_MAGIC: tuple[tuple[bytes, Container], ...] = (
    (b"#!AER-DAT4", "aedat4"),
    (b"#!AER-DAT3", "aedat3"),
    (b"#!AER-DAT2", "aedat2"),
    (b"#ROSBAG V2", "ros1"),
    (b"\x89MCAP", "ros2"),
    (b"SQLite format 3\x00", "ros2"),
)


def detect(path: str | os.PathLike) -> Container:
    """The container of the recording at ``path`` (a file, or a ROS 2 bag's or an event text
    sequence's folder), from its content; InputError when it is none evcap reads."""
    path = Path(path)
    if not path.exists():
        raise InputNotFoundError(f"{path}: no such file or folder")
    if path.is_dir():
        if (path / "metadata.yaml").is_file():
            return "ros2"
        if (path / "events.txt").is_file():
            return "text"
        raise InputError(
            f"{path} is a folder without metadata.yaml (a ROS 2 bag) or events.txt (an event "
            f"text sequence); evcap imports {KNOWN}"
        )
    with path.open("rb") as f:
        head = f.read(4096)
    for magic, container in _MAGIC:
        if head.startswith(magic):
            return container
    if head.startswith(b"#!AER-DAT"):
        version = head[9:].splitlines()[0].decode("ascii", "replace")
        raise InputError(f"{path} is AEDAT {version}; evcap imports {KNOWN}")
    if _looks_like_event_text(head):
        return "text"
    raise InputError(f"{path} is not a recording evcap knows; it imports {KNOWN}")


def _looks_like_event_text(head: bytes) -> bool:
    """Whether the first lines read as events: four numbers a line (comments aside)."""
    try:
        text = head.decode("ascii")
    except UnicodeDecodeError:
        return False
    lines = text.splitlines()
    if len(head) == 4096:
        lines = lines[:-1]  # the last line may be cut
    rows = [line.split() for line in lines if line.strip() and not line.startswith("#")][:20]
    try:
        return bool(rows) and all(len(row) == 4 and [float(v) for v in row] for row in rows)
    except ValueError:
        return False


def import_recording(
    src: str | os.PathLike,
    dst: str | os.PathLike,
    *,
    topic: str | None = None,
    chip: str | None = None,
    color_filter: str | None = None,
    width: int | None = None,
    height: int | None = None,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> ImportSummary:
    """Import the recording ``src`` (any container of ``detect``) into the session ``dst``.
    ``topic``: a bag's event topic; ``chip``: an AEDAT 2.0 file's jAER chip class;
    ``width``, ``height``: an event text file's sensor size."""
    container = detect(src)
    given = {
        "--topic": topic is not None,
        "--chip": chip is not None,
        "--width/--height": (width, height) != (None, None),
    }
    takes = {
        "--topic": container in ("ros1", "ros2"),
        "--chip": container == "aedat2",
        "--width/--height": container == "text",
    }
    for option, used in given.items():
        if used and not takes[option]:
            raise InputError(f"{option} is not for {src} (its container: {container})")
    common = {"color_filter": color_filter, "overwrite": overwrite, "progress": progress}
    match container:
        case "aedat4":
            from evcap.importers.aedat4 import import_aedat4

            return import_aedat4(src, dst, **common)
        case "aedat3":
            from evcap.importers.aedat3 import import_aedat3

            return import_aedat3(src, dst, **common)
        case "aedat2":
            from evcap.importers.aedat2 import import_aedat2

            return import_aedat2(src, dst, chip=chip, **common)
        case "ros1" | "ros2":
            from evcap.importers.ros_bag import import_ros_bag

            return import_ros_bag(src, dst, topic=topic, **common)
        case "text":
            from evcap.importers.event_text import import_event_text

            return import_event_text(src, dst, width=width, height=height, **common)
        case _:
            assert_never(container)
